"""POST /collections/{mapId}/localize over HTTP: accuracy, conventions, cache refresh and bad input."""

from __future__ import annotations

import math
import re
import time

import httpx
import numpy as np
import pytest

from mapbuilder.crs import from_wgs84, meridian_convergence_deg, to_wgs84
from tests._api_helpers import shared_server
from tests.test_api_features import assert_problem, karlsruhe_fc  # noqa: F401 (fixture)

CRS = "EPSG:25832"


@pytest.fixture(scope="module")
def api():
    return shared_server("sqlite")


@pytest.fixture(scope="module")
def kmap(api, karlsruhe_fc):  # noqa: F811
    map_id = api.new_map(prefix="loc")
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=api.auth, timeout=60)
    assert r.status_code == 201
    feats = httpx.get(f"{api.base_url}/collections/{map_id}/items?limit=10000").json()["features"]
    return map_id, feats


def along_lane(feats, index: int) -> float:
    """Grid yaw (ENU radians) of a vehicle driving along the lane of marking ``index``."""
    f = feats[index]
    lon, lat = f["geometry"]["coordinates"]
    grid_bearing = f["properties"]["bearing_deg"] - float(meridian_convergence_deg(CRS, lon, lat))
    return math.radians(90.0 - grid_bearing)


def scene(feats, index: int, yaw_grid: float | None = None, offset=(1.0, 0.5)):
    """A true vehicle pose near marking ``index`` and what its camera sees (vehicle frame).

    The camera clusters a solid line at its own phase: its centroids of solid
    pieces lie 0.8 m along the line from the pieces' centres.
    """
    if yaw_grid is None:
        yaw_grid = along_lane(feats, index)
    tr = to_wgs84(CRS)
    from mapbuilder.crs import from_wgs84

    fw = from_wgs84(CRS)
    xy = np.array([fw.transform(*f["geometry"]["coordinates"]) for f in feats])
    b = np.radians([f["properties"]["bearing_deg"] for f in feats])
    solid = np.array([f["properties"].get("kind") == "solid" for f in feats])
    xy = xy + 0.8 * solid[:, None] * np.column_stack([np.sin(b), np.cos(b)])
    w = np.array([f["properties"]["weight"] for f in feats])
    p = xy[index] + np.array(offset)
    c, s = math.cos(yaw_grid), math.sin(yaw_grid)
    v = (xy - p) @ np.array([[c, -s], [s, c]])  # columns: forward, left
    seen = (v[:, 0] > 3) & (v[:, 0] < 35) & (np.abs(v[:, 1]) < 10)
    obs = [{"x": float(a), "y": float(b), "weight": float(g)} for (a, b), g in zip(v[seen], w[seen])]
    lon, lat = tr.transform(*p)
    conv = float(meridian_convergence_deg(CRS, lon, lat))
    heading = (90.0 - math.degrees(yaw_grid) + conv) % 360.0  # clockwise from true north
    return p, lon, lat, heading, obs


def gps_near(p, heading, dx=2.5, dy=-2.0, dh=4.0):
    lon, lat = to_wgs84(CRS).transform(p[0] + dx, p[1] + dy)
    return {"lat": lat, "lon": lon, "heading_deg": heading + dh, "position_sigma_m": 5.0, "heading_sigma_deg": 10.0}


@pytest.mark.parametrize("method", ["default", "pink2008"])
def test_localize_recovers_the_pose(api, kmap, method):
    map_id, feats = kmap
    p, lon, lat, heading, obs = scene(feats, 250)
    assert len(obs) >= 4
    dh = 4.0 if method == "default" else 1.0
    near = {"dx": 0.5, "dy": -0.3} if method == "pink2008" else {}
    body = {"gps": gps_near(p, heading, dh=dh, **near), "observations": obs,
            "method": method}  # fmt: skip
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize", json=body, timeout=60)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["status"] == "ok", out
    assert out["crs"] == CRS
    assert math.hypot(out["easting"] - p[0], out["northing"] - p[1]) < 0.2
    assert abs((out["heading_deg"] - heading + 180) % 360 - 180) < 0.3
    assert out["lon"] == pytest.approx(lon, abs=3e-6) and out["lat"] == pytest.approx(lat, abs=3e-6)
    # REP-103 yaw: counter-clockwise from true east, heading clockwise from true north
    assert out["yaw_enu_rad"] == pytest.approx(math.radians(90.0 - out["heading_deg"]), abs=1e-6)
    cov = np.array(out["covariance"])
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert out["inliers"] >= 3 and out["iterations"] >= 1 and out["rms_m"] < 0.1
    # The default method's posterior probability of the answer; the paper's ICP has none.
    if method == "default":
        assert 0.95 <= out["probability"] <= 1.0
    else:
        assert out["probability"] is None


def test_a_gps_error_ellipse_is_taken_as_the_prior(api, kmap):
    """The fix's ellipse (NMEA GST style) instead of one sigma; the drive's state hands on its covariance."""
    map_id, feats = kmap
    p, lon, lat, heading, obs = scene(feats, 250)
    gps = gps_near(p, heading)
    del gps["position_sigma_m"]
    gps["position_ellipse"] = {"sigma_major_m": 6.0, "sigma_minor_m": 2.0, "orientation_deg": heading + 360.0}
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize", json={"gps": gps, "observations": obs},
                   timeout=60)  # fmt: skip
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["status"] == "ok" and math.hypot(out["easting"] - p[0], out["northing"] - p[1]) < 0.2
    frames, truth = drive_frames(feats, 2)
    gps = gps_near(*truth[0])
    del gps["position_sigma_m"]
    gps["position_ellipse"] = {"sigma_major_m": 5.0, "sigma_minor_m": 1.0, "orientation_deg": truth[0][1]}
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize/sequence", json={"gps": gps, "frames": frames},
                   timeout=60)  # fmt: skip
    assert r.status_code == 200, r.text
    cov = np.array(r.json()["state"]["gps"]["covariance"])
    # 5 m along the heading and 1 m across it, carried 1.5 m: still far longer along the road than across
    val = np.linalg.eigvalsh(cov[:2, :2])
    assert math.sqrt(val[1]) == pytest.approx(5.0, abs=0.1) and 1.0 < math.sqrt(val[0]) < 1.5


def test_index_follows_map_edits(api, kmap):
    map_id, feats = kmap
    p, lon, lat, heading, obs = scene(feats, 10)
    body = {"gps": gps_near(p, heading), "observations": obs}
    url = f"{api.base_url}/collections/{map_id}/localize"
    first = httpx.post(url, json=body, timeout=60)
    assert first.json()["status"] == "ok"
    # the answer names the revision of the map it was localized against
    revision = httpx.get(f"{api.base_url}/collections/{map_id}", timeout=30).json()["revision"]
    assert first.headers["x-map-revision"] == str(revision)
    # remove every marking within 60 m: the cached index must see it
    lon0, lat0 = to_wgs84(CRS).transform(p[0] - 60, p[1] - 60)
    lon1, lat1 = to_wgs84(CRS).transform(p[0] + 60, p[1] + 60)
    near = httpx.get(f"{api.base_url}/collections/{map_id}/items",
                     params={"bbox": f"{lon0},{lat0},{lon1},{lat1}", "limit": 10000}).json()["features"]  # fmt: skip
    changes = [{"op": "delete", "id": f["id"]} for f in near]
    cs = httpx.post(f"{api.base_url}/collections/{map_id}/changesets", json={"changes": changes},
                    headers=api.auth, timeout=60)  # fmt: skip
    assert cs.status_code == 201
    gone = httpx.post(url, json=body, timeout=60)
    assert gone.json()["status"] == "failed" and gone.json()["reason"]
    assert int(gone.headers["x-map-revision"]) > revision
    drive = httpx.post(f"{url}/sequence", json={"gps": body["gps"], "frames": [{"observations": obs}]},
                       timeout=60)  # fmt: skip
    assert drive.headers["x-map-revision"] == gone.headers["x-map-revision"]
    # and the revert brings them back
    r = httpx.post(f"{api.base_url}/collections/{map_id}/changesets/{cs.json()['changeset']}/revert",
                   headers=api.auth, timeout=60)  # fmt: skip
    assert r.status_code == 201
    assert httpx.post(url, json=body, timeout=60).json()["status"] == "ok"


def test_the_localization_thread_logs_under_the_request_id(api, karlsruhe_fc):  # noqa: F811
    """What the localization thread logs (a new map's index) carries the request's ``X-Request-ID``."""
    map_id = api.new_map(prefix="rid")
    part = {**karlsruhe_fc, "features": karlsruhe_fc["features"][:40]}
    assert httpx.post(f"{api.base_url}/collections/{map_id}/import", json=part, headers=api.auth,
                      timeout=60).status_code == 201  # fmt: skip
    lon, lat = part["features"][0]["geometry"]["coordinates"]
    body = {"gps": {"lat": lat, "lon": lon, "heading_deg": 0.0}, "observations": [{"x": 10.0, "y": 0.0}]}
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize", json=body, timeout=60,
                   headers={"X-Request-ID": f"first-frame-{map_id}"})  # fmt: skip
    assert r.status_code == 200 and r.headers["x-request-id"] == f"first-frame-{map_id}"
    built = [ln for ln in api.log().splitlines() if f"map {map_id}: spatial index of 40 markings" in ln]
    assert len(built) == 1 and f"[first-frame-{map_id}]" in built[0], built


def test_no_observations_is_a_failed_status(api, kmap):
    map_id, feats = kmap
    p, *_ = scene(feats, 10)
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize", json={"gps": gps_near(p, 90.0), "observations": []})
    assert r.status_code == 200 and r.json()["status"] == "failed" and r.json()["reason"]


@pytest.mark.parametrize("patch, status, words", [
    ({"gps": {"lat": 200, "lon": 8.4, "heading_deg": 0}}, 422, "gps.lat"),
    ({"gps": {"lat": 49, "lon": 8.4}}, 422, "gps.heading_deg"),
    ({"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0, "position_sigma_m": -1}}, 422, "position_sigma_m"),
    ({"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0, "heading_sigma_deg": 5e-324}}, 422, "heading_sigma_deg"),
    ({"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0, "position_sigma_m": 3,
              "position_ellipse": {"sigma_major_m": 3, "sigma_minor_m": 1, "orientation_deg": 0}}}, 422, "not both"),
    ({"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0,
              "position_ellipse": {"sigma_major_m": 1, "sigma_minor_m": 3, "orientation_deg": 0}}}, 422,
     "sigma_minor_m must not exceed"),
    ({"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0,
              "position_ellipse": {"sigma_major_m": 3, "sigma_minor_m": 1}}}, 422, "orientation_deg"),
    ({"observations": [{"x": 1e6, "y": 0}]}, 422, "observations.0.x"),
    ({"observations": [{"x": 1, "y": 0, "weight": 0}]}, 422, "weight"),
    ({"observations": [{"x": 1, "y": 0}] * 501}, 422, "at most 500"),
    ({"observations": {"x": 1}}, 422, "observations"),
    ({"method": "magic"}, 422, "method"),
    ({"extra": 1}, 422, "extra"),
])  # fmt: skip
def test_bad_localize_input_is_named(api, kmap, patch, status, words):
    map_id, _ = kmap
    body = {"gps": {"lat": 49.0071, "lon": 8.428, "heading_deg": 87.5}, "observations": [{"x": 10, "y": 1}]}
    body.update(patch)
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/localize", json=body), status, words)


def test_localize_needs_a_map_with_markings(api):
    body = {"gps": {"lat": 49.0071, "lon": 8.428, "heading_deg": 87.5}, "observations": [{"x": 10, "y": 1}]}
    assert_problem(httpx.post(f"{api.base_url}/collections/nope/localize", json=body), 404, "nope")
    empty = api.new_map(crs=None)
    assert_problem(httpx.post(f"{api.base_url}/collections/{empty}/localize", json=body), 409, "no markings")
    nan = b'{"gps": {"lat": NaN, "lon": 8.4, "heading_deg": 0}, "observations": []}'
    r = httpx.post(f"{api.base_url}/collections/{empty}/localize", content=nan,
                   headers={"Content-Type": "application/json"})  # fmt: skip
    assert_problem(r, 400, "NaN")


def test_server_timing_splits_the_localizer_from_the_request(api, kmap):
    """``Server-Timing`` tells load tests how long the map index and the localizer took."""
    map_id, feats = kmap
    p, lon, lat, heading, obs = scene(feats, 400)
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize",
                   json={"gps": gps_near(p, heading), "observations": obs}, timeout=60)  # fmt: skip
    assert r.status_code == 200
    parts = dict(part.strip().split(";dur=") for part in r.headers["server-timing"].split(","))
    assert set(parts) == {"queue", "index", "localize"}
    assert 0 < float(parts["localize"]) < r.elapsed.total_seconds() * 1000
    assert float(parts["index"]) >= 0 and float(parts["queue"]) >= 0


def test_a_large_map_answers_from_its_previous_index_until_the_new_one_is_built(tmp_path, karlsruhe_fc):  # noqa: F811
    """With ``LANEMAP_INDEX_BACKGROUND_FROM`` at or below a map's size, an edit never makes its
    fleet wait for the map's new index: the next answer comes from the previous one, says so in
    ``X-Map-Revision`` and is counted; the answers then catch up with the edit."""
    server, map_id, feats = _own_server_with_karlsruhe(tmp_path, karlsruhe_fc,
                                                       {"LANEMAP_INDEX_BACKGROUND_FROM": "800"})
    try:
        p, lon, lat, heading, obs = scene(feats, 10)
        url = f"{server.base_url}/collections/{map_id}/localize"
        body = {"gps": gps_near(p, heading), "observations": obs}
        first = httpx.post(url, json=body, timeout=60)
        revision = int(first.headers["x-map-revision"])
        assert first.json()["status"] == "ok"
        lon0, lat0 = to_wgs84(CRS).transform(p[0] - 60, p[1] - 60)
        lon1, lat1 = to_wgs84(CRS).transform(p[0] + 60, p[1] + 60)
        near = httpx.get(f"{server.base_url}/collections/{map_id}/items",
                         params={"bbox": f"{lon0},{lat0},{lon1},{lat1}", "limit": 10000}).json()["features"]
        cs = httpx.post(f"{server.base_url}/collections/{map_id}/changesets", headers=server.auth, timeout=60,
                        json={"changes": [{"op": "delete", "id": f["id"]} for f in near]})
        assert cs.status_code == 201
        edited = httpx.get(f"{server.base_url}/collections/{map_id}").json()["revision"]
        assert edited > revision
        stale = httpx.post(url, json=body, timeout=60)
        assert stale.status_code == 200 and int(stale.headers["x-map-revision"]) == revision
        assert stale.json()["status"] == "ok"  # the markings are still there in the index it used
        deadline = time.monotonic() + 30
        while True:
            r = httpx.post(url, json=body, timeout=60)
            if int(r.headers["x-map-revision"]) == edited or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert int(r.headers["x-map-revision"]) == edited and r.json()["status"] == "failed"
        metrics = httpx.get(f"{server.base_url}/metrics").text
        counted = re.search(rf'lanemap_localizations_stale_total{{map="{map_id}"}} (\S+)', metrics)
        assert counted and float(counted.group(1)) >= 1
        builds = re.search(r"lanemap_index_build_duration_seconds_count (\S+)", metrics)
        updates = re.search(r"lanemap_index_update_duration_seconds_count (\S+)", metrics)
        # the first index built, then updated with the markings the edit deleted, not built anew
        assert builds and float(builds.group(1)) == 1 and updates and float(updates.group(1)) >= 1
    finally:
        server.stop()


def test_a_server_builds_its_maps_indexes_as_it_starts(tmp_path, karlsruhe_fc):  # noqa: F811
    """``LANEMAP_INDEX_PRELOAD`` (on by default): the maps' indexes are built as the server starts,
    before any vehicle asks; off, at a map's first localization."""
    from mapbuilder.geojson import read_feature_collection
    from mapbuilder.store import Store
    from tests._api_helpers import start_server

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    store = Store(url)
    store.create_map("ka", crs=CRS)
    n = len(store.add_markings("ka", read_feature_collection(karlsruhe_fc), lonlat=True))
    store.create_map("empty")
    store.close()
    built = f"map ka: spatial index of {n} markings"
    server = start_server(url, tmp_path / "data")
    try:
        deadline = time.monotonic() + 30
        while built not in server.log() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert built in server.log() and "building the localization indexes of 1 maps" in server.log()
        assert httpx.get(f"{server.base_url}/health").json()["indexes"] == {"ready": 1, "building": []}
    finally:
        server.stop()
    server = start_server(url, tmp_path / "data2", env={"LANEMAP_INDEX_PRELOAD": "0"})
    try:
        health = httpx.get(f"{server.base_url}/health")
        assert health.status_code == 200 and health.json()["indexes"] == {"ready": 0, "building": []}
        assert built not in server.log()
        lon, lat = karlsruhe_fc["features"][0]["geometry"]["coordinates"]
        r = httpx.post(f"{server.base_url}/collections/ka/localize", timeout=60,
                       json={"gps": {"lat": lat, "lon": lon, "heading_deg": 0.0}, "observations": []})
        assert r.status_code == 200 and built in server.log()
    finally:
        server.stop()


def test_a_server_started_again_reads_the_indexes_it_kept(tmp_path, karlsruhe_fc):  # noqa: F811
    """``LANEMAP_INDEX_DIR``: a large map's index, built once (in a process of its own), is read
    back by the next server start instead of being built; a map edited while no server ran answers
    from the kept index until the newest is built, and that one is kept in its place; deleting the
    map deletes its files."""
    from mapbuilder.geojson import read_feature_collection
    from mapbuilder.model import Marking
    from mapbuilder.store import Store
    from tests._api_helpers import start_server

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    store = Store(url)
    store.create_map("ka", crs=CRS)
    n = len(store.add_markings("ka", read_feature_collection(karlsruhe_fc), lonlat=True))
    first_revision = store.map_head("ka").revision
    store.close()
    # built in a child process too (LANEMAP_INDEX_PROCESS_FROM), as a city's map is
    env = {"LANEMAP_INDEX_DIR_FROM": "500", "LANEMAP_INDEX_BACKGROUND_FROM": "500", "LANEMAP_INDEX_PROCESS_FROM": "500"}
    kept = tmp_path / "data" / "indexes"

    def started(wanted: str):
        server = start_server(url, tmp_path / "data", env=env)
        deadline = time.monotonic() + 30
        while wanted not in server.log() and time.monotonic() < deadline:
            time.sleep(0.1)
        return server

    built = f"map ka: spatial index of {n} markings at revision {first_revision} (coverage: hull) in"
    server = started(built)
    try:
        assert built in server.log() and re.search(r"\(coverage: hull\) in [\d.]+ s, built by process \d+", server.log())
        deadline = time.monotonic() + 10
        while not list(kept.glob("*.index")) and time.monotonic() < deadline:
            time.sleep(0.1)
        (file,) = kept.glob("*.index")
    finally:
        server.stop()
    read = f"map ka: spatial index of {n} markings at revision {first_revision} (coverage: hull) read from"
    server = started(read)
    try:
        assert read in server.log() and built not in server.log()
        metrics = httpx.get(f"{server.base_url}/metrics").text
        assert re.search(r'lanemap_index_file_loads_total{revision="current"} 1\.0', metrics)
    finally:
        server.stop()
    store = Store(url)
    store.add_markings("ka", [Marking(x=457_000.0, y=5_428_000.0, length_m=3.0, width_m=0.12, weight=30.0)])
    edited = store.map_head("ka").revision
    store.close()
    caught_up = (f"map ka: spatial index of {n + 1} markings updated from revision {first_revision} to {edited} "
                 "with 1 changed markings (coverage: hull) in")
    server = started(caught_up)
    try:
        log = server.log()
        assert f"at revision {first_revision} of {edited} (coverage: hull) read from" in log and caught_up in log
        # the kept one first, then the newest, unasked: the kept one updated with the edit, and kept
        assert log.index("read from") < log.index(caught_up)
        deadline = time.monotonic() + 10
        while file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        (newest,) = kept.glob("*.index")
        assert newest != file and f"-r{edited:010d}-" in newest.name
        # deleting the map deletes what was kept of it
        assert httpx.delete(f"{server.base_url}/collections/ka", headers=server.auth).status_code == 204
        assert not list(kept.glob("*.index"))
    finally:
        server.stop()


def _own_server_with_karlsruhe(tmp_path, karlsruhe_fc, env: dict):  # noqa: F811
    """A server of its own (SQLite, settings ``env``) holding the Karlsruhe map: ``(server, map id, features)``."""
    from tests._api_helpers import start_server

    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data", env=env)
    try:
        map_id = server.new_map()
        r = httpx.post(f"{server.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=server.auth,
                       timeout=60)  # fmt: skip
        assert r.status_code == 201
        feats = httpx.get(f"{server.base_url}/collections/{map_id}/items?limit=10000").json()["features"]
    except BaseException:
        server.stop()
        raise
    return server, map_id, feats


def test_the_map_is_picked_by_the_gps_fix(tmp_path, karlsruhe_fc):  # noqa: F811
    """``POST /localize``: the map with the most usable markings within the fix's reach answers,
    and says which it was; a fix far from every map is a 404 problem; rejected markings do not
    make a map the one."""
    import copy

    server, ka, feats = _own_server_with_karlsruhe(tmp_path, karlsruhe_fc, {})
    try:
        shift = 3000.0  # a second map: the same streets 3 km east
        fw, tr = from_wgs84(CRS), to_wgs84(CRS)
        moved = copy.deepcopy(karlsruhe_fc)
        for f in moved["features"]:
            x, y = fw.transform(*f["geometry"]["coordinates"])
            f["geometry"]["coordinates"] = list(tr.transform(x + shift, y))
        east = server.new_map(prefix="east")
        r = httpx.post(f"{server.base_url}/collections/{east}/import", json=moved, headers=server.auth, timeout=60)
        assert r.status_code == 201
        # a map of rejected markings on top of Karlsruhe's: the localizer would not use them
        rejected = copy.deepcopy(karlsruhe_fc)
        for f in rejected["features"]:
            f["properties"]["status"] = "rejected"
        ghost = server.new_map(prefix="a-ghost")
        r = httpx.post(f"{server.base_url}/collections/{ghost}/import", json=rejected, headers=server.auth, timeout=60)
        assert r.status_code == 201
        p, lon, lat, heading, obs = scene(feats, 250)
        for target, offset in ((ka, 0.0), (east, shift)):
            gps = gps_near((p[0] + offset, p[1]), heading)
            r = httpx.post(f"{server.base_url}/localize", json={"gps": gps, "observations": obs}, timeout=60)
            assert r.status_code == 200, r.text
            out = r.json()
            assert out["map"] == target and out["status"] == "ok", out
            assert math.hypot(out["easting"] - p[0] - offset, out["northing"] - p[1]) < 0.2
            assert r.headers["x-map-revision"] == str(httpx.get(f"{server.base_url}/collections/{target}").json()["revision"])
        # the per-map endpoint answers as before, without naming the map
        one = httpx.post(f"{server.base_url}/collections/{ka}/localize",
                         json={"gps": gps_near(p, heading), "observations": obs}, timeout=60).json()  # fmt: skip
        assert one["status"] == "ok" and "map" not in one
        far = gps_near((p[0] + 1500.0, p[1]), heading)  # between the two maps
        assert_problem(httpx.post(f"{server.base_url}/localize", json={"gps": far, "observations": obs}, timeout=60),
                       404, "no map has markings within 45 m of the GPS fix")  # fmt: skip
        wide = {**far, "position_sigma_m": 600.0}  # 1,830 m of reach: Karlsruhe's markings are in it
        r = httpx.post(f"{server.base_url}/localize", json={"gps": wide, "observations": obs}, timeout=60)
        assert r.status_code == 200 and r.json()["map"] in (ka, east)
        assert_problem(httpx.post(f"{server.base_url}/localize", json={"gps": far}, timeout=60), 422, "observations")

        # A drive on the eastern map, streamed: the map is picked by its first fix and kept in its state.
        frames, truth = drive_frames(feats, 4)
        east_frames = frames  # a vehicle frame is the same on the moved streets
        gps = gps_near((truth[0][0][0] + shift, truth[0][0][1]), truth[0][1])
        url = f"{server.base_url}/localize/sequence"
        whole = httpx.post(url, json={"gps": gps, "frames": east_frames}, timeout=60)
        assert whole.status_code == 200, whole.text
        assert whole.json()["map"] == whole.json()["state"]["map"] == east
        first = httpx.post(url, json={"gps": gps, "frames": east_frames[:2]}, timeout=60).json()
        rest = httpx.post(url, json={"state": first["state"], "frames": east_frames[2:]}, timeout=60)
        assert rest.status_code == 200 and rest.json()["map"] == east, rest.text
        assert first["poses"] + rest.json()["poses"] == whole.json()["poses"]
        last, (p_last, _) = whole.json()["poses"][-1], truth[-1]
        assert last["status"] == "ok" and math.hypot(last["easting"] - p_last[0] - shift, last["northing"] - p_last[1]) < 0.3
        # the map's own endpoint goes on with such a state too, but not another map's
        own = httpx.post(f"{server.base_url}/collections/{east}/localize/sequence",
                         json={"state": first["state"], "frames": east_frames[2:]}, timeout=60)  # fmt: skip
        assert own.status_code == 200 and own.json()["poses"] == rest.json()["poses"] and "map" not in own.json()
        assert_problem(httpx.post(f"{server.base_url}/collections/{ka}/localize/sequence",
                                  json={"state": first["state"], "frames": east_frames[2:]}, timeout=60),
                       409, f"the drive is localized on map {east!r}")  # fmt: skip
        # a state of a map's own endpoint names no map; one whose map is gone is a 404
        plain = httpx.post(f"{server.base_url}/collections/{east}/localize/sequence",
                           json={"gps": gps, "frames": east_frames[:2]}, timeout=60).json()  # fmt: skip
        assert "map" not in plain["state"]
        assert_problem(httpx.post(url, json={"state": plain["state"], "frames": east_frames[2:]}, timeout=60),
                       422, "state.map")  # fmt: skip
        # a state whose map is gone goes on on the map where it is, or is a 404 where none is
        gone = httpx.post(url, json={"state": {**first["state"], "map": "gone"}, "frames": east_frames[2:]}, timeout=60)
        assert gone.status_code == 200 and gone.json()["map"] == east, gone.text
        assert gone.json()["poses"] == rest.json()["poses"]
        nowhere = {**first["state"], "map": "gone",
                   "tracks": [{**t, "easting": t["easting"] - 1500.0} for t in first["state"]["tracks"]]}
        assert_problem(httpx.post(url, json={"state": nowhere, "frames": east_frames[2:]}, timeout=60), 404, "gone")
        assert_problem(httpx.post(url, json={"state": {**first["state"], "crs": "EPSG:4326"}, "frames": east_frames[2:]},
                                  timeout=60), 422, "projected")  # fmt: skip
    finally:
        server.stop()


OVERLAP_M = 30.0


def test_a_streamed_drive_is_handed_to_the_next_map(tmp_path, karlsruhe_fc):  # noqa: F811
    """``POST /localize/sequence``: a drive crossing from one map into the next, stored in another
    CRS, goes on there with its hypotheses (the state moved into that CRS), and stays there; a
    copy of its map on top of it (as many markings) does not take it."""
    import copy

    from localizer import GeoFrame
    from localizer.simulate import Camera, Clutter, odometry, sample_trajectories, simulate_scene
    from tests._api_helpers import start_server
    from tests._localizer_helpers import karlsruhe

    _, smap = karlsruhe()
    rng = np.random.default_rng(4)
    drive = sample_trajectories(smap, 1, 30, 1.5, rng, Camera(), min_visible=6)[0]
    frames = []
    for k, p in enumerate(drive):
        obs = simulate_scene(smap, tuple(p), rng, Camera(), Clutter()).observations
        frame = {"observations": [{"x": float(x), "y": float(y), "weight": float(w)} for x, y, w in obs]}
        if k:
            dx, dy, dyaw = odometry(drive[k - 1], p)
            frame["motion"] = {"dx": dx, "dy": dy, "dyaw_deg": math.degrees(dyaw)}
        frames.append(frame)
    # The border: across the drive, halfway along it.
    mid = 0.5 * (drive[0][:2] + drive[-1][:2])
    along = (drive[-1][:2] - drive[0][:2]) / np.linalg.norm(drive[-1][:2] - drive[0][:2])
    fw = from_wgs84(CRS)
    west, east = copy.deepcopy(karlsruhe_fc), copy.deepcopy(karlsruhe_fc)
    s = [float((np.array(fw.transform(*f["geometry"]["coordinates"])) - mid) @ along) for f in karlsruhe_fc["features"]]
    # Maps that meet overlap by a camera's view: at a map's edge what the camera sees beyond it is
    # unexplained, and a pose one dash period back explains more of it.
    west["features"] = [f for f, d in zip(west["features"], s) if d < OVERLAP_M / 2]
    east["features"] = [f for f, d in zip(east["features"], s) if d >= -OVERLAP_M / 2]
    east_crs = "EPSG:25833"  # the next UTM zone: another grid north (3.5° apart here) and scale
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data")
    try:
        maps = {}
        for name, fc, crs in (("a-west", west, CRS), ("b-west-copy", west, CRS), ("c-east", east, east_crs)):
            maps[name] = server.new_map(crs=crs, prefix=name)
            r = httpx.post(f"{server.base_url}/collections/{maps[name]}/import", json=fc, headers=server.auth,
                           timeout=60)  # fmt: skip
            assert r.status_code == 201, r.text
        lon, lat = to_wgs84(CRS).transform(drive[0][0] + 1.5, drive[0][1] - 1.0)
        heading = float(GeoFrame(CRS).grid_yaw_to_heading(drive[0][2] + math.radians(3), lon, lat))
        gps = {"lat": lat, "lon": lon, "heading_deg": heading, "position_sigma_m": 3.0, "heading_sigma_deg": 8.0}
        url = f"{server.base_url}/localize/sequence"
        on, poses, state = [], [], None
        for k, frame in enumerate(frames):
            body = {"frames": [frame], **({"gps": gps} if state is None else {"state": state})}
            r = httpx.post(url, json=body, timeout=60)
            assert r.status_code == 200, r.text
            out = r.json()
            state = out["state"]
            assert out["map"] == state["map"] and out["poses"][0]["crs"] == state["crs"]
            on.append(out["map"])
            poses += out["poses"]
        switch = on.index(maps["c-east"])
        assert set(on[:switch]) == {maps["a-west"]} and set(on[switch:]) == {maps["c-east"]}, on
        assert 0.3 * len(frames) < switch < 0.8 * len(frames), on
        assert state["crs"] == east_crs
        to_east = GeoFrame(east_crs)
        for k, (pose, truth) in enumerate(zip(poses, drive)):
            if k < switch:  # on the western map, in its own CRS
                assert math.hypot(pose["easting"] - truth[0], pose["northing"] - truth[1]) < 0.5, (k, pose)
                continue
            x, y = to_east.to_xy(*to_wgs84(CRS).transform(truth[0], truth[1]))
            assert pose["status"] == "ok" and pose["inliers"] >= 3, pose
            assert math.hypot(pose["easting"] - x, pose["northing"] - y) < 0.5, (pose, x, y)
            true_heading = float(GeoFrame(CRS).grid_yaw_to_heading(truth[2], pose["lon"], pose["lat"]))
            assert abs((pose["heading_deg"] - true_heading + 180) % 360 - 180) < 1.0
        # On the western map alone the same drive's last frames match nothing: it only dead-reckons.
        alone = httpx.post(f"{server.base_url}/collections/{maps['a-west']}/localize/sequence",
                           json={"gps": gps, "frames": frames}, timeout=120).json()  # fmt: skip
        assert all(not p["inliers"] for p in alone["poses"][-5:]), [p["inliers"] for p in alone["poses"]]
        metrics = httpx.get(f"{server.base_url}/metrics", headers=server.auth).text
        assert re.search(r'lanemap_drive_handovers_total\{source="%s",target="%s"\} 1\.0' % (maps["a-west"],
                                                                                              maps["c-east"]), metrics)
    finally:
        server.stop()


def test_a_map_made_anew_by_another_process_is_not_taken_for_the_cached_one(api, karlsruhe_fc, tmp_path):  # noqa: F811
    """The map deleted and made anew under its id by the command line (another process, so the
    server's cache of its index is not told), with markings elsewhere: the server localizes
    against the new map, although it was written as often as the old one."""
    import json
    import os
    import subprocess
    import sys

    map_id = api.new_map(prefix="anew")
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=api.auth, timeout=60)
    assert r.status_code == 201
    feats = httpx.get(f"{api.base_url}/collections/{map_id}/items?limit=10000").json()["features"]
    p, lon, lat, heading, obs = scene(feats, 10)
    body = {"gps": gps_near(p, heading), "observations": obs}
    url = f"{api.base_url}/collections/{map_id}/localize"
    first = httpx.post(url, json=body, timeout=60)
    assert first.json()["status"] == "ok"  # the index is cached at this revision
    far = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon + 0.05 + k * 1e-4, lat]},
         "properties": {"weight": 40.0}} for k in range(5)]}  # fmt: skip
    (tmp_path / "far.geojson").write_text(json.dumps(far))
    env = {**os.environ, "LANEMAP_DATABASE_URL": api.db_url}
    for args in (["maps", "delete", map_id, "--yes"], ["import", map_id, str(tmp_path / "far.geojson"), "--create"]):
        out = subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                             env=env, timeout=120)  # fmt: skip
        assert out.returncode == 0, out.stderr
    again = httpx.post(url, json=body, timeout=60)
    assert again.status_code == 200 and again.json()["status"] == "failed", again.json()
    assert "no map markings within" in again.json()["reason"]
    assert int(again.headers["x-map-revision"]) > int(first.headers["x-map-revision"])


def test_the_server_compiles_the_localizer_before_serving(tmp_path, karlsruhe_fc):  # noqa: F811
    """With nothing in numba's cache, the kernels compile at start, not in the first request."""
    server, map_id, feats = _own_server_with_karlsruhe(
        tmp_path, karlsruhe_fc, {"NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")})
    try:
        assert "localizer kernels ready in" in server.log()
        # ... and what the start left behind is kept out of the full collections (0.1 s each otherwise)
        frozen = re.search(r"(\d+) objects of the start frozen", server.log())
        assert frozen and int(frozen.group(1)) > 50_000, server.log()[-2000:]
        assert any((tmp_path / "numba-cache").rglob("*.nbi"))  # compiled here, not loaded
        p, lon, lat, heading, obs = scene(feats, 400)
        r = httpx.post(f"{server.base_url}/collections/{map_id}/localize",
                       json={"gps": gps_near(p, heading), "observations": obs}, timeout=60)  # fmt: skip
        assert r.status_code == 200 and r.json()["status"] == "ok"
        parts = dict(part.strip().split(";dur=") for part in r.headers["server-timing"].split(","))
        # Compiling takes seconds; a localization, milliseconds.
        assert float(parts["localize"]) < 1000.0, parts
    finally:
        server.stop()


def test_overload_is_refused_at_once_with_503(tmp_path, karlsruhe_fc):  # noqa: F811
    """Beyond LANEMAP_LOCALIZE_MAX_PENDING a server answers 503 problems at once, then recovers."""
    import threading

    server, map_id, feats = _own_server_with_karlsruhe(tmp_path, karlsruhe_fc, {"LANEMAP_LOCALIZE_MAX_PENDING": "1"})
    try:
        p, lon, lat, heading, obs = scene(feats, 400)
        # a wide prior makes each localization long enough to overlap the others
        body = {"gps": {**gps_near(p, heading), "position_sigma_m": 30.0, "heading_sigma_deg": 45.0},
                "observations": obs}  # fmt: skip
        url = f"{server.base_url}/collections/{map_id}/localize"
        answers: list[httpx.Response] = []
        barrier = threading.Barrier(8)

        def one():
            barrier.wait()
            answers.append(httpx.post(url, json=body, timeout=60))

        threads = [threading.Thread(target=one) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        codes = sorted(a.status_code for a in answers)
        assert 200 in codes and 503 in codes and set(codes) == {200, 503}, codes
        busy = next(a for a in answers if a.status_code == 503)
        assert_problem(busy, 503, "busy")
        assert busy.headers["retry-after"] == "1"
        # nothing stays counted: one at a time is always served
        for _ in range(3):
            assert httpx.post(url, json=body, timeout=60).status_code == 200
        assert "Traceback" not in server.log()
        # /metrics counts what was shed, and the answers given
        m = metric_samples(httpx.get(f"{server.base_url}/metrics").text)
        assert m[("lanemap_localizations_shed_total", ())] == codes.count(503)
        assert m[("lanemap_http_requests_total", (("method", "POST"), ("route", "/collections/{mapId}/localize"),
                                                  ("status", "503")))] == codes.count(503)
        answered = sum(v for (name, labels), v in m.items()
                       if name == "lanemap_localizations_total" and ("endpoint", "frame") in labels)
        assert answered == codes.count(200) + 3
    finally:
        server.stop()


def test_a_frame_sent_during_a_long_drive_waits_for_one_of_its_frames(api, kmap):
    """A drive takes the localization thread a frame at a time, not for all its frames at once."""
    import threading

    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize"
    p, lon, lat, heading, obs = scene(feats, 250)
    # Frames of 200 observations that no pose explains, under a fix of any heading:
    # every frame searches the whole neighbourhood again.
    rng = np.random.default_rng(22)
    frames = []
    for k in range(6):
        r, b = np.sqrt(rng.uniform(4.0**2, 148.0**2, 200)), rng.uniform(-1.0, 1.0, 200)
        frames.append({"observations": [{"x": float(x), "y": float(y), "weight": float(w)} for x, y, w in
                                        zip(r * np.cos(b), r * np.sin(b), rng.uniform(20, 200, 200))]})
        if k:
            frames[-1]["motion"] = {"dx": 1.5, "dy": 0.0}
    gps = {"lat": lat, "lon": lon, "heading_deg": heading, "position_sigma_m": 1000.0, "heading_sigma_deg": 180.0}
    drive = {}

    def send_drive():
        t = time.perf_counter()
        r = httpx.post(f"{url}/sequence", json={"gps": gps, "frames": frames}, timeout=300)
        drive.update(answer=r, seconds=time.perf_counter() - t, done=time.perf_counter())

    thread = threading.Thread(target=send_drive)
    thread.start()
    time.sleep(0.3)  # the drive's first frame is being localized
    t = time.perf_counter()
    single = httpx.post(url, json={"gps": gps_near(p, heading), "observations": obs}, timeout=300)
    single_done = time.perf_counter()
    thread.join()
    assert single.status_code == 200 and single.json()["status"] == "ok"
    assert drive["answer"].status_code == 200 and len(drive["answer"].json()["poses"]) == len(frames)
    per_frame = drive["seconds"] / len(frames)
    print(f"drive {drive['seconds']:.2f} s, the frame sent during it {single_done - t:.2f} s")
    # Answered after one of the drive's frames, not after all of them.
    assert single_done - t < 2 * per_frame + 0.3, (single_done - t, drive["seconds"])
    assert single_done < drive["done"] - 2 * per_frame


def test_a_drive_is_localized_frame_by_frame(api, kmap):
    # Behind a dash, with dashes and lines in view. (Behind solid lines alone,
    # marking 400, a pose 1 m along the road explains the view as well: the
    # answers are rightly ambiguous there.)
    map_id, feats = kmap
    frames, truth = drive_frames(feats, 5)
    p0, h0 = truth[0]
    body = {"gps": {**gps_near(p0, h0), "position_sigma_m": 8.0}, "frames": frames}
    r = httpx.post(f"{api.base_url}/collections/{map_id}/localize/sequence", json=body, timeout=60)
    assert r.status_code == 200, r.text
    out = r.json()
    assert len(out["poses"]) == 5 and out["tracks"] >= 1
    assert "localize;dur=" in r.headers["server-timing"]
    for pose, (p, heading) in zip(out["poses"], truth):
        assert pose["status"] == "ok", pose
        assert math.hypot(pose["easting"] - p[0], pose["northing"] - p[1]) < 0.3
        assert abs((pose["heading_deg"] - heading + 180) % 360 - 180) < 0.5
        assert np.array(pose["covariance"]).shape == (3, 3)


def drive_frames(feats, n: int, step: float = 1.5):
    """``n`` frames ``step`` metres apart along the lane of marking 250, with their true poses."""
    yaw = along_lane(feats, 250)
    frames, truth = [], []
    for k in range(n):
        off = (1.0 + k * step * math.cos(yaw), 0.5 + k * step * math.sin(yaw))
        p, lon, lat, heading, obs = scene(feats, 250, yaw, offset=off)
        frame = {"observations": obs}
        if k:
            frame["motion"] = {"dx": step, "dy": 0.0, "dyaw_deg": 0.0}
        frames.append(frame)
        truth.append((p, heading))
    return frames, truth


def test_a_drive_streamed_frame_by_frame_answers_as_one_request(api, kmap):
    """Each request carries one frame and the previous answer's state: the poses of the whole drive's request."""
    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize/sequence"
    frames, truth = drive_frames(feats, 6)
    # A prior wide and far enough off that the first frames are in doubt.
    gps = {**gps_near(truth[0][0], truth[0][1], dx=6.0, dy=-4.0), "position_sigma_m": 8.0}
    whole = httpx.post(url, json={"gps": gps, "frames": frames}, timeout=60)
    assert whole.status_code == 200, whole.text
    streamed, state = [], None
    for k, frame in enumerate(frames):
        body = {"frames": [frame]}
        if state is None:
            body["gps"] = gps
        else:
            body["state"] = state
        r = httpx.post(url, json=body, timeout=60)
        assert r.status_code == 200, r.text
        out = r.json()
        assert out["state"]["frames"] == k + 1 and out["state"]["crs"] == CRS
        streamed += out["poses"]
        state = out["state"]
    assert streamed == whole.json()["poses"]
    assert state == whole.json()["state"]
    last, (p, _) = streamed[-1], truth[-1]
    assert last["status"] == "ok" and math.hypot(last["easting"] - p[0], last["northing"] - p[1]) < 0.3


def test_bad_drive_states_are_named(api, kmap):
    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize/sequence"
    frames, truth = drive_frames(feats, 2)
    state = httpx.post(url, json={"gps": gps_near(*truth[0]), "frames": frames[:1]}, timeout=60).json()["state"]
    cases = [
        ({"frames": frames[1:]}, "gps"),  # neither a fix nor a state
        ({"frames": [frames[0]], "state": state}, "frames[0].motion"),  # continuing needs the odometry
        ({"frames": frames[1:], "state": {**state, "crs": "EPSG:32632"}}, "EPSG:32632"),
        ({"frames": frames[1:], "state": {**state, "gps": {**state["gps"], "sigma_m": 0}}}, "sigma_m"),
        ({"frames": frames[1:], "state": {**state, "frames": 0}}, "frames"),
        ({"frames": frames[1:], "state": {**state, "gps": {**state["gps"], "covariance": [[1, 0.5, 0], [0, 1, 0],
                                                                                         [0, 0, 0.01]]}}},
         "symmetric"),
        ({"frames": frames[1:], "state": {**state, "extra": 1}}, "extra"),
        ({"frames": frames[1:], "state": {**state, "shift": -1}}, "shift"),
        ({"frames": frames[1:], "state": {**state, "history": [{**state["history"][0], "weight": 2}]}}, "weight"),
        ({"frames": frames[1:], "state": {**state, "history": [{**state["history"][0],
                                                                "observations": [[10.0, 1.0, -1.0]]}]}},
         "history[0].observations"),
    ]
    for body, words in cases:
        assert_problem(httpx.post(url, json=body, timeout=60), 422, words)
    # The same state continues the drive, with or without a newer GPS fix, and
    # so does one from before the last frames were kept.
    older = {k: v for k, v in state.items() if k not in ("history", "shift")}
    for extra in ({}, {"gps": gps_near(*truth[1])}, {"state": older}):
        r = httpx.post(url, json={"frames": frames[1:], "state": state, **extra}, timeout=60)
        assert r.status_code == 200 and r.json()["state"]["frames"] == 2, r.text
        assert len(r.json()["state"]["history"]) == (2 if extra.get("state") is None else 1)


def metric_samples(text: str) -> dict[tuple, float]:
    """``/metrics`` as {(sample name, sorted label items): value}."""
    from prometheus_client.parser import text_string_to_metric_families

    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def test_metrics_count_localizations_by_outcome(api, kmap):
    """``/metrics``: answers by endpoint and status, requests by route template, the localizer's time."""
    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize"

    def scrape():
        r = httpx.get(f"{api.base_url}/metrics")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain"), r.text
        # Routes are labelled by their template, not by the path sent; answers by map.
        assert f'route="/collections/{map_id}' not in r.text
        return metric_samples(r.text)

    before = scrape()
    p, lon, lat, heading, obs = scene(feats, 250)
    for _ in range(2):
        assert httpx.post(url, json={"gps": gps_near(p, heading), "observations": obs}, timeout=60).json()[
            "status"] == "ok"
    far = dict(gps_near(p, heading), lat=lat + 0.5)
    assert httpx.post(url, json={"gps": far, "observations": obs}, timeout=60).json()["status"] == "failed"
    bad = [{"x": 10.0, "y": 1.0, "weight": -1.0}]
    assert httpx.post(url, json={"gps": far, "observations": bad}, timeout=60).status_code == 422
    nope = httpx.post(f"{api.base_url}/collections/no-such-map/localize",
                      json={"gps": gps_near(p, heading), "observations": obs}, timeout=60)
    assert nope.status_code == 404
    frames, _ = drive_frames(feats, 3)
    drive = httpx.post(f"{url}/sequence", json={"gps": gps_near(p, heading), "frames": frames}, timeout=60).json()
    # a request with a token is counted under the token's name (the server's one is "api")
    assert httpx.post(url, json={"gps": gps_near(p, heading), "observations": obs}, headers=api.auth,
                      timeout=60).json()["status"] == "ok"  # fmt: skip
    after = scrape()

    def delta(name, **labels):
        key = (name, tuple(sorted(labels.items())))
        return after.get(key, 0.0) - before.get(key, 0.0)

    assert delta("lanemap_localizations_total", map=map_id, endpoint="frame", method="default", status="ok",
                 token="-") == 2
    assert delta("lanemap_localizations_total", map=map_id, endpoint="frame", method="default",
                 status="failed", token="-") == 1
    assert delta("lanemap_localizations_total", map=map_id, endpoint="frame", method="default", status="ok",
                 token="api") == 1
    # A map that does not exist is a 404, and makes no series of its own.
    assert not any(("map", "no-such-map") in labels for _, labels in after)
    by_status = {}
    for pose in drive["poses"]:
        by_status[pose["status"]] = by_status.get(pose["status"], 0) + 1
    for status, n in by_status.items():
        assert delta("lanemap_localizations_total", map=map_id, endpoint="drive", method="default",
                     status=status, token="-") == n
    assert delta("lanemap_localizer_duration_seconds_count", endpoint="frame") == 4
    assert delta("lanemap_localizer_duration_seconds_count", endpoint="drive") == 1
    assert delta("lanemap_localizer_duration_seconds_sum", endpoint="frame") > 0
    route = "/collections/{mapId}/localize"
    assert delta("lanemap_http_requests_total", method="POST", route=route, status="200") == 4
    assert delta("lanemap_http_requests_total", method="POST", route=route, status="422") == 1
    assert delta("lanemap_http_requests_total", method="POST", route=route, status="404") == 1
    assert delta("lanemap_http_requests_total", method="POST", route=route + "/sequence", status="200") == 1
    assert delta("lanemap_http_request_duration_seconds_count", route=route) == 6
    assert delta("lanemap_http_requests_total", method="GET", route="/metrics", status="200") == 1


def test_answers_follow_the_documented_schema(api, kmap):
    """Every kind of answer (ok, ambiguous, failed, a drive) validates against openapi.json."""
    import jsonschema_rs

    spec = httpx.get(f"{api.base_url}/openapi.json").json()

    def validator(path):
        schema = spec["paths"][path]["post"]["responses"]["200"]["content"]["application/json"]["schema"]
        return jsonschema_rs.validator_for({**schema, "components": spec["components"]})

    single = validator("/collections/{mapId}/localize")
    drive = validator("/collections/{mapId}/localize/sequence")
    # and the header naming the map's revision each answer was localized against
    for path in ("/collections/{mapId}/localize", "/localize", "/collections/{mapId}/localize/sequence",
                 "/localize/sequence"):
        header = spec["paths"][path]["post"]["responses"]["200"]["headers"]["X-Map-Revision"]
        assert "previous" in header["description"] and header["schema"]["pattern"] == "^[0-9]+$"
    assert {"probability", "covariance", "mixture_covariance", "hypotheses"} <= set(
        spec["components"]["schemas"]["PoseOut"]["properties"])
    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize"
    p, lon, lat, heading, obs = scene(feats, 250)
    answers = [httpx.post(url, json={"gps": gps_near(p, heading), "observations": obs, "method": m},
                          timeout=60).json() for m in ("default", "pink2008")]  # fmt: skip
    # A few dashes of one line seen from a vague fix: the 9 m period leaves it ambiguous.
    dashes = sorted(obs, key=lambda o: abs(o["y"]))[:3]
    answers.append(httpx.post(url, json={"gps": {**gps_near(p, heading), "position_sigma_m": 20.0},
                                         "observations": dashes}, timeout=60).json())  # fmt: skip
    far = dict(gps_near(p, heading), lat=lat + 0.5)  # 55 km away: no markings
    answers.append(httpx.post(url, json={"gps": far, "observations": obs}, timeout=60).json())
    assert [a["status"] for a in answers[:2]] == ["ok", "ok"] and answers[3]["status"] == "failed"
    assert answers[2]["status"] == "ambiguous" and answers[2]["hypotheses"], answers[2]
    # Each hypothesis has its covariance, and the ambiguous answer the mixture of them (ok: none).
    amb = answers[2]
    assert all(len(h["covariance"]) == 3 for h in amb["hypotheses"])
    assert amb["hypotheses"][0]["covariance"] == amb["covariance"]
    assert np.trace(amb["mixture_covariance"]) > np.trace(amb["covariance"]) + 1.0  # rivals metres apart
    # Each hypothesis says where it lies from the answer, in the answer's vehicle frame.
    assert amb["hypotheses"][0]["offset"] == pytest.approx({"x_m": 0.0, "y_m": 0.0, "heading_deg": 0.0}, abs=1e-6)
    for h in amb["hypotheses"][1:]:
        off = h["offset"]
        assert math.hypot(off["x_m"], off["y_m"]) == pytest.approx(
            math.hypot(h["easting"] - amb["easting"], h["northing"] - amb["northing"]), abs=1e-6)
        turn = (h["heading_deg"] - amb["heading_deg"] + 180.0) % 360.0 - 180.0
        assert off["heading_deg"] == pytest.approx(turn, abs=1e-9) and -180.0 <= turn < 180.0
    assert answers[0]["mixture_covariance"] is None and answers[1]["mixture_covariance"] is None
    for a in answers:
        errors = [e.message for e in single.iter_errors(a)]
        assert not errors, (a, errors)
    body = {"gps": gps_near(p, heading), "frames": [{"observations": obs},
                                                    {"observations": obs, "motion": {"dx": 0.0, "dy": 0.0}}]}
    seq = httpx.post(f"{url}/sequence", json=body, timeout=60).json()
    assert len(seq["poses"]) == 2 and not list(drive.iter_errors(seq))
    # A response missing what the document requires does not validate: the check can fail.
    assert list(single.iter_errors({"status": "ok"}))
    assert list(single.iter_errors({**answers[0], "undocumented": 1}))  # every field is documented


def test_a_request_sets_the_probability_an_ok_answer_needs(api, kmap):
    """``min_probability`` moves the line between ok and ambiguous; the pose and its probability stay."""
    map_id, feats = kmap
    url = f"{api.base_url}/collections/{map_id}/localize"
    # The four markings nearest the lane's middle and a vague fix: an answer in
    # doubt, not hopeless, in most places; the first such place of a few is taken
    # (which one depends on the layout).
    for index in (201, *range(5, len(feats), 37)):
        p, lon, lat, heading, obs = scene(feats, index)
        dashes = sorted(obs, key=lambda o: abs(o["y"]))[:4]
        body = {"gps": {**gps_near(p, heading), "position_sigma_m": 6.0}, "observations": dashes}
        base = httpx.post(url, json=body, timeout=60).json()
        prob = base["probability"]
        if 0.5 <= prob < 0.9999:
            break
    else:
        pytest.fail("no place on the map gave an answer in some doubt")
    strict = httpx.post(url, json={**body, "min_probability": 0.9999}, timeout=60).json()
    lenient = httpx.post(url, json={**body, "min_probability": math.floor(prob * 1e4) / 1e4}, timeout=60).json()
    assert strict["status"] == "ambiguous" and strict["hypotheses"], strict
    assert lenient["status"] == "ok" and not lenient["hypotheses"], lenient
    for a in (strict, lenient):
        assert a["probability"] == pytest.approx(prob)
        assert (a["easting"], a["northing"]) == pytest.approx((base["easting"], base["northing"]))
    # A drive takes it too: its first frame is this one.
    drive = httpx.post(f"{url}/sequence", json={"gps": body["gps"], "frames": [{"observations": dashes}],
                                                "min_probability": 0.9999}, timeout=60).json()  # fmt: skip
    assert drive["poses"][0]["status"] == "ambiguous"
    for extra, words in [({"min_probability": 0.3}, "min_probability"), ({"min_probability": 1.0}, "min_probability"),
                         ({"min_probability": 0.9, "method": "pink2008"}, "pink2008")]:  # fmt: skip
        assert_problem(httpx.post(url, json={**body, **extra}, timeout=60), 422, words)


@pytest.mark.parametrize("frames, words", [
    ([], "frames"),
    ([{"observations": [{"x": 10, "y": 1}]}] * 51, "frames"),
    ([{"observations": [{"x": 10, "y": 1}]}, {"observations": [{"x": 10, "y": 1}]}], "frames[1].motion"),
    ([{"observations": [{"x": 10, "y": 1}]}, {"observations": [], "motion": {"dx": 1.0}}], "dy"),
    ([{"observations": [{"x": 10, "y": 1}]}, {"observations": [], "motion": {"dx": 1.0, "dy": 0, "dyaw_deg": 500}}],
     "dyaw_deg"),
    ([{"observations": [{"x": 1, "y": 0}] * 501}], "frames[0].observations: 501 given"),
    ([{"observations": [{"x": 200, "y": 0}]}], "farther than"),
])  # fmt: skip
def test_bad_drive_input_is_named(api, kmap, frames, words):
    map_id, _ = kmap
    body = {"gps": {"lat": 49.0071, "lon": 8.428, "heading_deg": 87.5}, "frames": frames}
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/localize/sequence", json=body, timeout=60),
                   422, words)  # fmt: skip


def test_the_kinds_a_map_was_imported_with_reach_the_localizer(api):
    # Two solid lines of four 3 m pieces along grid east and two dashes (with
    # one, a pose 1.4 m along the lines explains all but that dash and makes
    # the answer fairly ambiguous). The
    # camera's clusters on the lines' first pieces lie 1.2 m ahead of their
    # centres; knowing the pieces are solid, the localizer matches them across
    # the line only. Without kinds (a detected map) the end pieces look like
    # dashes and drag the pose along the road.
    from mapbuilder.geojson import markings_to_feature_collection
    from mapbuilder.model import Marking

    e0, n0 = 458000.0, 5428000.0
    tr = to_wgs84(CRS)
    lon0, lat0 = tr.transform(e0, n0)
    true_bearing = 90.0 + float(meridian_convergence_deg(CRS, lon0, lat0))
    pieces = [(-12.0 + 3 * k, 1.8) for k in range(4)] + [(-4.0 + 3 * k, -1.8) for k in range(4)]
    obs = [{"x": x, "y": y, "weight": w} for x, y, w in
           ((5.2, 1.8, 60), (9.0, 1.8, 60), (12.0, 1.8, 60), (13.2, -1.8, 60), (16.5, -1.8, 60),
            (20.0, -1.8, 60), (16.0, 5.0, 40), (13.0, 5.0, 40))]
    p = (e0 - 16.0, n0)
    lon, lat = tr.transform(*p)
    heading = 90.0 + float(meridian_convergence_deg(CRS, lon, lat))
    gps = {"lat": lat, "lon": lon, "heading_deg": heading, "position_sigma_m": 1.0, "heading_sigma_deg": 3.0}
    errors = {}
    for kinds in (True, False):
        items = [Marking(x=e0 + dx, y=n0 + dy, length_m=3.0, width_m=0.12, bearing_deg=true_bearing,
                         weight=60.0, kind="solid" if kinds else None) for dx, dy in pieces]
        items += [Marking(x=e0 + dx, y=n0 + 5.0, length_m=0.2, width_m=0.12, bearing_deg=true_bearing,
                          weight=40.0, kind="dash" if kinds else None) for dx in (0.0, -3.0)]
        for m in items:
            m.lon, m.lat = tr.transform(m.x, m.y)
        map_id = api.new_map(prefix="kinds")
        r = httpx.post(f"{api.base_url}/collections/{map_id}/import",
                       json=markings_to_feature_collection(items), headers=api.auth, timeout=60)
        assert r.status_code == 201, r.text
        r = httpx.post(f"{api.base_url}/collections/{map_id}/localize", json={"gps": gps, "observations": obs},
                       timeout=60)
        assert r.status_code == 200, r.text
        out = r.json()
        errors[kinds] = (out["status"], math.hypot(out["easting"] - p[0], out["northing"] - p[1]))
    assert errors[True][0] == "ok" and errors[True][1] < 0.05, errors
    # About a metre along the road (the joint fit with the pitch, which used to
    # carry it farther, now keeps the pose where the ranking put it).
    assert errors[False][1] > 0.5, errors


def _features_of(index, whole: dict) -> dict:
    """The features of the Karlsruhe collection ``whole`` that a part of the map (an index of
    some of them) holds."""
    import copy

    fw = from_wgs84(CRS)
    kept = {tuple(np.round(xy, 3)) for xy in index.xy}
    fc = copy.deepcopy(whole)
    fc["features"] = [f for f in fc["features"]
                      if tuple(np.round(fw.transform(*f["geometry"]["coordinates"]), 3)) in kept]  # fmt: skip
    assert 0 < len(fc["features"]) < len(whole["features"])
    return fc


def _request_of(prior, obs) -> dict:
    """The localization request of a library ``Prior`` and observations."""
    return {"gps": {"lat": prior.lat, "lon": prior.lon, "heading_deg": prior.heading_deg,
                    "position_sigma_m": prior.position_sigma_m, "heading_sigma_deg": prior.heading_sigma_deg},
            "observations": [{"x": float(x), "y": float(y), "weight": float(w)} for x, y, w in obs]}  # fmt: skip


def test_an_answer_at_the_maps_edge_says_why_it_is_not_sure(tmp_path, karlsruhe_fc):  # noqa: F811
    """A frame whose camera sees past the end of the map, with a wide prior: over HTTP the answer
    is ambiguous and its reason names the map's edge, where the localizer without its edge check
    is sure of a pose a dash period off."""
    from localizer import Options, localize
    from tests._api_helpers import start_server
    from tests.test_localizer_edge import _edge_scenes

    for pose, obs, prior, cut, _ in _edge_scenes(40, 6.5, (8.0, 10.0)):
        unchecked = localize(cut, obs, prior, options=Options(edge_share=None))
        if unchecked.status == "ok" and math.hypot(unchecked.easting - pose[0], unchecked.northing - pose[1]) > 1:
            break
    else:
        pytest.fail("no scene at the edge is answered wrongly without the check")
    fc = _features_of(cut, karlsruhe_fc)
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data")
    try:
        map_id = server.new_map()
        assert httpx.post(f"{server.base_url}/collections/{map_id}/import", json=fc, headers=server.auth,
                          timeout=60).status_code == 201  # fmt: skip
        body = _request_of(prior, obs)
        out = httpx.post(f"{server.base_url}/collections/{map_id}/localize", json=body, timeout=60).json()
        assert out["status"] == "ambiguous" and "beyond the map's edge" in out["reason"], out
        assert out["hypotheses"] and out["probability"] >= 0.95
    finally:
        server.stop()


def test_a_maps_coverage_is_its_own_or_the_servers(tmp_path, karlsruhe_fc):  # noqa: F811
    """A map with a stretch of road left out ahead of the vehicle, inside the hull of what it holds.
    A server with ``LANEMAP_MAP_COVERAGE=markings`` answers ambiguous there and names the map's edge,
    where by the hull a pose a dash period off is sure; a map's own coverage (PATCH) goes before
    the server's, and the next request is answered by it."""
    from localizer import localize
    from tests._api_helpers import start_server
    from tests._localizer_helpers import KarlsruheMarkings
    from tests.test_localizer_edge import _edge_scenes

    marks = KarlsruheMarkings()
    for pose, obs, prior, _, _ in _edge_scenes(40, 6.5, (8.0, 10.0), seed=3):
        gap = marks.gap(pose, 10.0)
        by_hull = localize(gap, obs, prior)
        if by_hull.status == "ok" and math.hypot(by_hull.easting - pose[0], by_hull.northing - pose[1]) > 1:
            break
    else:
        pytest.fail("no scene before a stretch left out is answered wrongly by the hull")
    fc = _features_of(gap, karlsruhe_fc)
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                          env={"LANEMAP_MAP_COVERAGE": "markings"})  # fmt: skip
    try:
        map_id = server.new_map()
        url = f"{server.base_url}/collections/{map_id}"
        assert httpx.post(f"{url}/import", json=fc, headers=server.auth, timeout=60).status_code == 201
        body = _request_of(prior, obs)

        def answer():
            return httpx.post(f"{url}/localize", json=body, timeout=60).json()

        got = httpx.get(url).json()
        assert (got["coverage"], got["coverageSet"]) == ("markings", False)
        out = answer()
        assert out["status"] == "ambiguous" and "beyond the map's edge" in out["reason"], out
        r = httpx.patch(url, json={"coverage": "hull"}, headers=server.auth)
        assert r.status_code == 200 and (r.json()["coverage"], r.json()["coverageSet"]) == ("hull", True)
        assert r.json()["revision"] == got["revision"]  # its markings did not change
        out = answer()
        # the stored map went through WGS84: the same answer to a tenth of a millimetre
        assert out["status"] == "ok" and out["easting"] == pytest.approx(by_hull.easting, abs=1e-4), out
        # a title alone leaves the coverage; null gives the server's back
        r = httpx.patch(url, json={"title": "with a gap"}, headers=server.auth)
        assert (r.json()["title"], r.json()["coverage"]) == ("with a gap", "hull")
        r = httpx.patch(url, json={"coverage": None}, headers=server.auth)
        assert (r.json()["coverage"], r.json()["coverageSet"]) == ("markings", False)
        assert answer()["status"] == "ambiguous"
        refused = (({}, "nothing-to-change"), ({"coverage": "convex"}, None), ({"title": None}, "invalid-title"))
        for bad, slug in refused:
            r = httpx.patch(url, json=bad, headers=server.auth)
            assert r.status_code == 422 and r.headers["content-type"] == "application/problem+json", (bad, r.text)
            assert slug is None or r.json()["type"].endswith(slug)
        r = httpx.post(f"{server.base_url}/collections", json={"id": "route", "coverage": "markings"},
                       headers=server.auth)  # fmt: skip
        assert r.status_code == 201 and (r.json()["coverage"], r.json()["coverageSet"]) == ("markings", True)
    finally:
        server.stop()


def test_a_map_covering_its_imagery_speaks_for_the_ground_its_builds_imaged(tmp_path, karlsruhe_fc):  # noqa: F811
    """``coverage: imagery`` over HTTP: before any build recorded its ground, the map speaks only
    for the ground between its markings, and a frame seeing past the end of one of its parts is held
    back there; once a build recorded imagery of the whole district (written by the store, as a
    build's tile does), the next request reads it and the same frame is sure, and right."""
    import shapely

    from localizer import localize
    from mapbuilder.store import Store
    from tests._api_helpers import start_server
    from tests._localizer_helpers import KarlsruheMarkings
    from tests.test_localizer_edge import _edge_scenes, _graded

    marks = KarlsruheMarkings()
    by_markings = marks.index(extent="markings")
    by_imagery = marks.index(extent="markings", extent_area=marks.imaged())
    for pose, obs, prior, _, _ in _edge_scenes(40, 6.5, (8.0, 10.0), seed=3):
        held = localize(by_markings, obs, prior)
        sure = localize(by_imagery, obs, prior)
        if "beyond the map's edge" in (held.reason or "") and _graded(sure, pose)[0] == "ok" \
                and _graded(sure, pose)[1] < 0.5:
            break
    else:
        pytest.fail("no scene is held back by the markings' extent and sure by the imagery's")
    db_url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    server = start_server(db_url, tmp_path / "data")
    try:
        map_id = server.new_map()
        url = f"{server.base_url}/collections/{map_id}"
        assert httpx.post(f"{url}/import", json=karlsruhe_fc, headers=server.auth, timeout=60).status_code == 201
        r = httpx.patch(url, json={"coverage": "imagery"}, headers=server.auth)
        assert r.status_code == 200 and (r.json()["coverage"], r.json()["coverageSet"]) == ("imagery", True)
        body = _request_of(prior, obs)
        r = httpx.post(f"{url}/localize", json=body, timeout=60)
        out, before = r.json(), int(r.headers["X-Map-Revision"])
        assert out["status"] == "ambiguous" and "beyond the map's edge" in out["reason"], out
        store = Store(db_url)
        store.replace_detected(map_id, "ortho-0a1b2c3d/1024/0/0", [], ground=shapely.to_wkb(marks.imaged()))
        store.close()
        r = httpx.post(f"{url}/localize", json=body, timeout=60)
        out = r.json()
        assert int(r.headers["X-Map-Revision"]) > before
        assert out["status"] == "ok" and out["easting"] == pytest.approx(sure.easting, abs=1e-3), out
        assert math.hypot(out["easting"] - pose[0], out["northing"] - pose[1]) < 0.5
    finally:
        server.stop()


def test_a_maps_coverage_is_served_as_the_ground_localization_speaks_for(tmp_path, karlsruhe_fc):  # noqa: F811
    """``GET /collections/{id}/coverage``: the extent the localizer's edge check uses, as a GeoJSON
    Feature in WGS84, redrawn when the map's coverage or its imaged ground changes: the hull holds
    every marking; the markings' extent is the map's seven parts, smaller; the imagery's ground
    (recorded as a build's tile records it) is that ground."""
    import shapely
    from shapely.geometry import shape

    from mapbuilder.store import Store
    from tests._api_helpers import start_server
    from tests._localizer_helpers import KarlsruheMarkings

    db_url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    server = start_server(db_url, tmp_path / "data")
    try:
        map_id = server.new_map()
        url = f"{server.base_url}/collections/{map_id}"
        empty = httpx.get(f"{url}/coverage").json()  # a map without markings has no area
        assert empty["geometry"] is None and empty["properties"]["area_m2"] == 0.0
        assert httpx.post(f"{url}/import", json=karlsruhe_fc, headers=server.auth, timeout=60).status_code == 201
        lonlat = np.array([f["geometry"]["coordinates"] for f in karlsruhe_fc["features"]])

        def coverage():
            r = httpx.get(f"{url}/coverage", timeout=60)
            assert r.status_code == 200 and r.headers["content-type"] == "application/geo+json", r.text
            return r.json(), int(r.headers["X-Map-Revision"])

        hull, rev = coverage()
        assert hull["properties"]["coverage"] == "hull" and hull["properties"]["revision"] == rev
        assert hull["geometry"]["type"] == "Polygon"
        assert shapely.contains_xy(shape(hull["geometry"]), lonlat[:, 0], lonlat[:, 1]).all()
        assert httpx.patch(url, json={"coverage": "markings"}, headers=server.auth).status_code == 200
        parts, _ = coverage()
        assert parts["properties"]["coverage"] == "markings" and parts["geometry"]["type"] == "MultiPolygon"
        assert len(parts["geometry"]["coordinates"]) >= 7  # the Karlsruhe map's parts, and lone markings
        assert shapely.contains_xy(shape(parts["geometry"]), lonlat[:, 0], lonlat[:, 1]).all()
        assert parts["properties"]["area_m2"] < 0.5 * hull["properties"]["area_m2"]
        assert httpx.patch(url, json={"coverage": "imagery"}, headers=server.auth).status_code == 200
        before, _ = coverage()  # no ground recorded yet: the markings' extent
        assert before["properties"]["area_m2"] == parts["properties"]["area_m2"]
        imaged = KarlsruheMarkings().imaged()
        store = Store(db_url)
        store.replace_detected(map_id, "ortho-0a1b2c3d/1024/0/0", [], ground=shapely.to_wkb(imaged))
        store.close()
        ground, rev2 = coverage()
        assert rev2 > rev and ground["properties"]["coverage"] == "imagery"
        assert ground["properties"]["area_m2"] == pytest.approx(imaged.area, rel=1e-6)
        assert_problem(httpx.get(f"{server.base_url}/collections/nowhere/coverage"), 404)
    finally:
        server.stop()

"""Imagery upload (COG), tiles, builds as jobs in worker processes, cancel and restart."""

from __future__ import annotations

import math
import os
import signal
import socket
import time
from pathlib import Path

import httpx
import pytest
import rasterio
from pyproj import Transformer

from tests._api_helpers import USGS_DIR, feature, shared_server, start_server
from tests.test_api_features import assert_problem

USGS = USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1.tif"
USGS_ALPHA = USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1_alpha.tif"
TIFF = {"Content-Type": "image/tiff"}


@pytest.fixture(scope="module")
def api():
    return shared_server("sqlite")


def upload(api, map_id: str, path: Path) -> httpx.Response:
    return httpx.post(f"{api.base_url}/collections/{map_id}/imagery", content=path.read_bytes(),
                      headers={**api.auth, **TIFF}, timeout=120)  # fmt: skip


def tile_of(lon: float, lat: float, z: int) -> tuple[int, int]:
    n = 2**z
    x = int((lon + 180) / 360 * n)
    y = int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * n)
    return x, y


def wait_job(api, job_id: str, timeout: float = 180) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = httpx.get(f"{api.base_url}/jobs/{job_id}").json()
        assert job["status"] in ("accepted", "running", "successful", "failed", "dismissed")
        if job["status"] in ("successful", "failed", "dismissed"):
            return job
        time.sleep(0.3)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s: {job}")


def test_upload_is_stored_as_cog_and_served_as_tiles(api):
    map_id = api.new_map(crs="EPSG:26913")
    r = upload(api, map_id, USGS_ALPHA)
    assert r.status_code == 201, r.text
    img = r.json()
    assert r.headers["location"].endswith(f"/collections/{map_id}/imagery/{img['id']}")
    assert img["crs"] == "EPSG:26913" and img["resolution_m"] == pytest.approx(0.15, abs=0.01)
    stored = list((api.data_dir / "imagery" / map_id).glob("*.tif"))
    assert len(stored) == 1
    with rasterio.open(stored[0]) as ds:
        assert ds.profile.get("tiled") and ds.overviews(1) or ds.width <= 512
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
    listed = httpx.get(f"{api.base_url}/collections/{map_id}/imagery").json()["imagery"]
    assert [i["id"] for i in listed] == [img["id"]]
    w, s, e, n = img["bounds"]
    lon, lat = Transformer.from_crs("EPSG:26913", "EPSG:4326", always_xy=True).transform((w + e) / 2, (s + n) / 2)
    x, y = tile_of(lon, lat, 20)
    t = httpx.get(f"{api.base_url}/collections/{map_id}/imagery/tiles/WebMercatorQuad/20/{x}/{y}.png")
    assert t.status_code == 200 and t.headers["content-type"] == "image/png"
    assert t.content[:8] == b"\x89PNG\r\n\x1a\n"
    far = httpx.get(f"{api.base_url}/collections/{map_id}/imagery/tiles/WebMercatorQuad/20/{x + 1000}/{y}.png")
    assert_problem(far, 404, "no imagery")


def test_bad_uploads_leave_nothing_behind(api, tmp_path):
    map_id = api.new_map(crs="EPSG:26913")
    url = f"{api.base_url}/collections/{map_id}/imagery"
    assert_problem(httpx.post(url, content=b"hello", headers={**api.auth, **TIFF}), 422, "upload")
    assert_problem(httpx.post(url, content=USGS.read_bytes()[:5000], headers={**api.auth, **TIFF}), 422)
    assert_problem(httpx.post(url, content=b"", headers={**api.auth, **TIFF}), 422, "empty")
    assert_problem(httpx.post(url, content=USGS.read_bytes(), headers={**api.auth, "Content-Type": "text/plain"}),
                   415)  # fmt: skip
    assert_problem(httpx.post(url, content=USGS.read_bytes(), headers=TIFF), 401)
    one_band = tmp_path / "gray.tif"
    with rasterio.open(USGS) as src:
        profile = src.profile | {"count": 1}
        with rasterio.open(one_band, "w", **profile) as dst:
            dst.write(src.read(1), 1)
    assert_problem(upload(api, map_id, one_band), 422, "RGB")
    # a connection that dies mid-upload
    port = int(api.base_url.rsplit(":", 1)[1])
    data = USGS.read_bytes()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"POST /collections/%s/imagery HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer %s\r\n"
                  b"Content-Type: image/tiff\r\nContent-Length: %d\r\n\r\n"
                  % (map_id.encode(), api.token.encode(), len(data)))  # fmt: skip
        s.sendall(data[: len(data) // 2])
    incoming = api.data_dir / "imagery" / ".incoming"
    deadline = time.monotonic() + 20
    while list(incoming.glob("*")) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not list(incoming.glob("*"))  # the partial upload was removed
    assert httpx.get(f"{api.base_url}/collections/{map_id}/imagery").json()["imagery"] == []
    assert not list((api.data_dir / "imagery").glob(f"{map_id}/*"))
    assert_problem(httpx.get(f"{api.base_url}/collections/{map_id}/imagery/424242"), 404)


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_build_runs_as_a_job_and_writes_detections(kind):
    api = shared_server(kind)
    map_id = api.new_map(crs="EPSG:26913")
    img = upload(api, map_id, USGS).json()
    r = httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": img["id"]}, headers=api.auth)
    assert r.status_code == 202, r.text
    job_url = r.headers["location"]
    job_id = job_url.rsplit("/", 1)[1]
    assert r.json()["status"] in ("accepted", "running") and r.json()["imagery"] == [img["id"]]
    # The map reads as the job will build it as soon as the build is accepted.
    info = httpx.get(f"{api.base_url}/collections/{map_id}").json()
    assert (info["coverage"], info["coverageSet"]) == ("imagery", True)
    job = wait_job(api, job_id)
    assert job["status"] == "successful", job["message"]
    assert job["progress"] == 100 and job["finished"]
    items = httpx.get(f"{api.base_url}/collections/{map_id}/items?limit=1000").json()
    assert items["numberMatched"] > 0
    assert {f["properties"]["source"] for f in items["features"]} == {"detected"}
    # Created empty and first built into, the map covers its imagery, as one the build had made.
    info = httpx.get(f"{api.base_url}/collections/{map_id}").json()
    assert (info["coverage"], info["coverageSet"]) == ("imagery", True)
    # the ground the build imaged, for a map whose coverage is the imagery: the image's bounds
    import shapely

    from mapbuilder.store import Store

    store = Store(api.db_url)
    ground = store.imaged_footprint(map_id)
    store.close()
    with rasterio.open(USGS) as ds:
        assert ground.symmetric_difference(shapely.box(*ds.bounds)).area < 0.1
    jobs = httpx.get(f"{api.base_url}/jobs", params={"map": map_id}).json()["jobs"]
    assert [j["jobID"] for j in jobs] == [job_id]
    # the job's quicklook: a PNG of the imagery at its own 15 cm with the detections drawn on
    preview = [ln["href"] for ln in job["links"] if ln["rel"] == "preview"]
    assert preview == [f"{api.base_url}/jobs/{job_id}/quicklook.png"]
    r = httpx.get(preview[0], timeout=60)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    assert r.content[:8] == b"\x89PNG\r\n\x1a\n" and r.headers["x-map-revision"]
    width, height = int.from_bytes(r.content[16:20], "big"), int.from_bytes(r.content[20:24], "big")
    assert (width, height) == (383, 233)
    kept = sorted((api.data_dir / "quicklooks").glob(f"job-{job_id}-*.png"))
    assert len(kept) == 1 and httpx.get(preview[0], timeout=60).content == r.content  # made once
    small = httpx.get(preview[0], params={"size": 100}, timeout=60)
    assert small.status_code == 200 and int.from_bytes(small.content[16:20], "big") == 100
    assert len(list((api.data_dir / "quicklooks").glob(f"job-{job_id}-*.png"))) == 2  # one per size
    # an edit of the map makes the next picture anew, at the map's new revision
    fid = items["features"][0]["id"]
    assert httpx.delete(f"{api.base_url}/collections/{map_id}/items/{fid}", headers=api.auth).status_code == 204
    again = httpx.get(preview[0], timeout=60)
    assert int(again.headers["x-map-revision"]) == int(r.headers["x-map-revision"]) + 1 and again.content != r.content
    assert len(list((api.data_dir / "quicklooks").glob(f"job-{job_id}-*.png"))) == 1  # the older ones went
    assert_problem(httpx.get(f"{api.base_url}/jobs/{job_id}/quicklook.png", params={"size": 10}), 422, "size")
    assert_problem(httpx.get(f"{api.base_url}/jobs/987654/quicklook.png"), 404)
    # The default build verifies its clusters; without verification the same
    # imagery gives the kerbs and car outlines back. (This map is created
    # without a CRS: its first build gives it the image's.)
    raw_map = api.new_map(crs=None)
    raw_img = upload(api, raw_map, USGS).json()
    assert httpx.get(f"{api.base_url}/collections/{raw_map}").json()["storageCrs"] is None
    # a build refused leaves the map as it was
    assert_problem(httpx.post(f"{api.base_url}/collections/{raw_map}/builds",
                              json={"imagery": raw_img["id"], "tile_px": 8}, headers=api.auth), 422, "tile_px")
    refused = httpx.get(f"{api.base_url}/collections/{raw_map}").json()
    assert (refused["storageCrs"], refused["coverageSet"]) == (None, False)
    r = httpx.patch(f"{api.base_url}/collections/{raw_map}", json={"coverage": "hull"}, headers=api.auth)
    assert r.status_code == 200 and r.json()["coverageSet"], r.text  # said before the build: kept
    r = httpx.post(f"{api.base_url}/collections/{raw_map}/builds",
                   json={"imagery": raw_img["id"], "verify": False}, headers=api.auth)
    assert r.status_code == 202, r.text
    storage = httpx.get(f"{api.base_url}/collections/{raw_map}").json()["storageCrs"]
    assert storage == "http://www.opengis.net/def/crs/EPSG/0/26913"
    raw_job = wait_job(api, r.headers["location"].rsplit("/", 1)[1])
    assert raw_job["status"] == "successful"
    store = Store(api.db_url)
    assert store.get_job(int(raw_job["jobID"])).params["crs"] == "EPSG:26913"  # the CRS it was built in
    store.close()
    raw = httpx.get(f"{api.base_url}/collections/{raw_map}/items?limit=1000").json()["numberMatched"]
    assert httpx.get(f"{api.base_url}/collections/{raw_map}").json()["coverage"] == "hull"
    assert raw > items["numberMatched"] + 3
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": "999999"},
                              headers=api.auth), 422, "imagery")  # fmt: skip
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds",
                              json={"imagery": img["id"], "verify": "sometimes"}, headers=api.auth),
                   422, "verify")  # fmt: skip
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": img["id"],
                              "tile_px": 8}, headers=api.auth), 422, "tile_px")  # fmt: skip
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": img["id"],
                              "verify_threshold": 1.5}, headers=api.auth), 422, "verify_threshold")  # fmt: skip
    for floor in (1.0, -0.1):
        assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds",
                                  json={"imagery": img["id"], "verify_continuation_min": floor},
                                  headers=api.auth), 422, "verify_continuation_min")  # fmt: skip
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": img["id"],
                              "threshold_low": 0.3}, headers=api.auth), 422, "threshold_low")  # fmt: skip
    assert_problem(httpx.post(f"{api.base_url}/collections/{map_id}/builds", json={"imagery": img["id"],
                              "threshold_low": 0.1, "hysteresis": False}, headers=api.auth),
                   422, "threshold_low")  # fmt: skip


def test_an_import_job_runs_beside_the_builds_not_behind_them(tmp_path):
    """With one build worker busy and builds waiting for it, an import sent with
    ``Prefer: respond-async`` still runs at once, in a slot of its own."""
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                          env={"LANEMAP_BUILD_WORKERS": "1"})  # fmt: skip
    try:
        maps = [server.new_map(crs="EPSG:26913") for _ in range(5)]
        imgs = [upload(server, m, USGS).json()["id"] for m in maps]
        target = server.new_map()
        builds = []
        for m, img in zip(maps, imgs):
            r = httpx.post(f"{server.base_url}/collections/{m}/builds", json={"imagery": img}, headers=server.auth)
            assert r.status_code == 202, r.text
            builds.append(r.json()["jobID"])
        fc = {"type": "FeatureCollection", "features": [feature(8.4 + 1e-5 * k, 49.0) for k in range(500)]}
        r = httpx.post(f"{server.base_url}/collections/{target}/import", json=fc,
                       headers={**server.auth, "Prefer": "respond-async"})  # fmt: skip
        assert r.status_code == 202, r.text
        job = wait_job(server, r.json()["jobID"], timeout=60)
        assert job["status"] == "successful" and job["result"]["imported"] == 500, job
        # The last build still waits for the only build worker.
        assert httpx.get(f"{server.base_url}/jobs/{builds[-1]}").json()["status"] == "accepted"
        for b in builds:
            httpx.delete(f"{server.base_url}/jobs/{b}", headers=server.auth)
    finally:
        server.stop()


def test_cancel_a_waiting_job_and_restart_resumes_interrupted_ones(tmp_path):
    db = f"sqlite:///{tmp_path / 'db.sqlite'}"
    server = start_server(db, tmp_path / "data", env={"LANEMAP_BUILD_WORKERS": "1"})
    try:
        maps = [server.new_map(crs="EPSG:26913") for _ in range(3)]
        imgs = [upload(server, m, USGS).json()["id"] for m in maps]
        jobs = []
        for m, i in zip(maps, imgs):
            r = httpx.post(f"{server.base_url}/collections/{m}/builds", json={"imagery": i}, headers=server.auth)
            assert r.status_code == 202
            jobs.append(r.json()["jobID"])
        # one worker: the second job waits, and is cancelled before it starts
        d = httpx.delete(f"{server.base_url}/jobs/{jobs[1]}", headers=server.auth)
        assert d.status_code == 200 and d.json()["status"] == "dismissed"
        assert_problem(httpx.delete(f"{server.base_url}/jobs/{jobs[1]}"), 401)
        # a crash while jobs are unfinished
        states = {j: httpx.get(f"{server.base_url}/jobs/{j}").json()["status"] for j in (jobs[0], jobs[2])}
        os.kill(server.proc.pid, signal.SIGKILL)  # the server only: its build worker must end by itself
        server.proc.wait(10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                os.killpg(server.proc.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.2)
        else:
            server.kill_hard()
            raise AssertionError("a build worker outlived its server")
        unfinished = [j for j, st in states.items() if st in ("accepted", "running")]
        assert unfinished, states  # the last job waits for the only worker
        server = start_server(db, tmp_path / "data", env={"LANEMAP_BUILD_WORKERS": "1"})
        for j in (jobs[0], jobs[2]):
            job = wait_job(server, j)
            assert job["status"] == "successful", job["message"]
        assert wait_job(server, jobs[1])["status"] == "dismissed"
        counts = [httpx.get(f"{server.base_url}/collections/{m}/items").json()["numberMatched"] for m in maps]
        assert counts[0] > 0 and counts[2] > 0 and counts[1] == 0
    finally:
        server.stop()

"""The build job end to end: rendered and real imagery, tiles, the store, resume, rebuild."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mapbuilder import synth
from mapbuilder.build import BuildError, BuildParams, build_map
from mapbuilder.cluster import ClusterParams
from mapbuilder.model import Marking
from mapbuilder.raster import ImageryError
from mapbuilder.store import Change, Store, StoreError
from tests._build_helpers import (
    USGS_ALPHA,
    USGS_BASE,
    USGS_NODATA,
    BrightnessModel,
    match,
    pipeline_model,
    stall_centres,
)

REPO = Path(__file__).resolve().parents[1]
CRS = "EPSG:25832"
X0, Y0 = 456000.0, 5430000.0


def _dash(cx, cy, bearing, length=3.0, width=0.15, kind="dash"):
    b = math.radians(bearing)
    dx, dy = 0.5 * length * math.sin(b), 0.5 * length * math.cos(b)
    return Marking(x=cx, y=cy, length_m=length, width_m=width, bearing_deg=bearing,
                   x0=cx - dx, y0=cy - dy, x1=cx + dx, y1=cy + dy, kind=kind)


@pytest.fixture(scope="module")
def border_scene(tmp_path_factory):
    """Dashes on plain asphalt, many of them straddling the borders of 12.8 m tiles."""
    rng = np.random.default_rng(7)
    marks = []
    for i in range(5):
        for j in range(5):
            # Centres near multiples of 12.8 m (tile borders at 0.1 m and 128 px).
            cx = X0 + 12.8 * (i % 3 + 1) + rng.uniform(-1.2, 1.2) + (i // 3) * 6.4
            cy = Y0 - 6.0 - 7.0 * j + rng.uniform(-0.5, 0.5)
            marks.append(_dash(cx, cy, rng.uniform(0, 180)))
    out = tmp_path_factory.mktemp("border") / "border.tif"
    result = synth.render(marks, out, 0.1, crs=CRS, seed=3,
                          bounds=(X0, Y0 - 40.0, X0 + 51.2, Y0))
    return result


def _all(store, map_id):
    return list(store.iter_markings(map_id))


def _detected(store, map_id):
    return [m for m in _all(store, map_id) if m.source == "detected"]


def _xy(ms):
    return np.array([(m.x, m.y) for m in ms], float).reshape(-1, 2)


def test_markings_crossing_tile_borders_are_found_once(border_scene, sqlite_url):
    store = Store(sqlite_url)
    model = pipeline_model()
    small = build_map(store, "small", [border_scene.path],
                      BuildParams(tile_px=128, model=model), workers=1, progress=False)
    whole = build_map(store, "whole", [border_scene.path],
                      BuildParams(tile_px=4096, model=model), workers=1, progress=False)
    h, w = border_scene.shape
    assert small.tiles_total == math.ceil(h / 128) * math.ceil(w / 128) and whole.tiles_total == 1
    a, b = _detected(store, "small"), _detected(store, "whole")
    truth = _xy(border_scene.markings)
    crossing_idx = []
    inv = ~border_scene.transform
    for j, m in enumerate(border_scene.markings):
        (c0, r0), (c1, r1) = inv @ (m.x0, m.y0), inv @ (m.x1, m.y1)
        if (c0 // 128 != c1 // 128) or (r0 // 128 != r1 // 128):
            crossing_idx.append(j)
    assert len(crossing_idx) >= 8
    # The small tiles found the same markings as one tile, measured the same:
    # nothing lost and nothing found twice at a border.
    assert len(a) == len(b)
    pairs, d = match(_xy(a), _xy(b), 0.3)
    assert len(pairs) == len(a)
    assert d.max() < 0.03
    xy = _xy(a)
    gaps = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert gaps.min() > 0.5
    # And they are the true dashes, each one once.
    # The scene is meaningful: the dashes, those crossing borders too, are found.
    pairs, d = match(xy, truth, 0.3)
    assert len(pairs) >= 0.9 * len(truth)
    found = {j for _, j in pairs}
    assert sum(j in found for j in crossing_idx) >= 0.75 * len(crossing_idx)
    keys = {m.tile_key for m in a}
    assert len(keys) > 5 and all("/128/" in k for k in keys)
    store.close()


@pytest.fixture(scope="module")
def comb_scene(tmp_path_factory):
    """Stall lines ending on a lot's border line (the junctions the build cuts), tile
    borders every 12.8 m across both."""
    stalls = stall_centres((X0 + 4.0, Y0 - 20.0), 15, 3.0, 4.6, 30.0)
    marks = [_dash(X0 + 25.6, Y0 - 20.0, 90.0, length=47.0, width=0.12)]
    marks += [_dash(cx, cy, 30.0, length=4.6, width=0.12) for cx, cy in stalls]
    out = tmp_path_factory.mktemp("comb") / "comb.tif"
    result = synth.render(marks, out, 0.1, crs=CRS, seed=5, bounds=(X0, Y0 - 32.0, X0 + 51.2, Y0))
    return result, stalls


def test_verified_builds_cut_junctions_alike_in_any_tiling(comb_scene, sqlite_url):
    """The default build of the command line (verified, hysteresis, junction cut) finds
    the markings of one tile in 12.8 m tiles too, at the same places, none twice, and
    finds the stall lines. (Before the features' grids were anchored to the image, tiles
    disagreed on pixel probabilities by up to 0.3; before the junction cut, a third of
    this scene's markings came out differently.)"""
    from mapbuilder.build import default_threshold, default_threshold_low

    scene, stalls = comb_scene
    cluster = ClusterParams(threshold=default_threshold(True),
                            threshold_low=default_threshold_low(True), verify=True)
    store = Store(sqlite_url)
    small = build_map(store, "comb-small", [scene.path], BuildParams(tile_px=128, cluster=cluster),
                      workers=1, progress=False)
    whole = build_map(store, "comb-whole", [scene.path], BuildParams(tile_px=4096, cluster=cluster),
                      workers=1, progress=False)
    assert small.tiles_total > 8 and whole.tiles_total == 1
    a, b = _detected(store, "comb-small"), _detected(store, "comb-whole")
    store.close()
    pairs, d = match(_xy(a), _xy(b), 0.3)
    assert len(pairs) == len(b) and d.max() < 0.01
    # what the small tiles find beside: at most a junction's sliver
    extra = [m for i, m in enumerate(a) if i not in {i for i, _ in pairs}]
    assert len(extra) <= 1 and all(m.length_m < 0.5 for m in extra)
    xy = _xy(a)
    gaps = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert gaps.min() > 0.1  # nothing found twice
    # every stall line is found along its axis, in its direction
    u = np.array([math.sin(math.radians(30.0)), math.cos(math.radians(30.0))])
    found = 0
    for c in stalls:
        off = _xy(a) - c
        across = np.abs(off @ np.array([u[1], -u[0]]))
        along = np.abs(off @ u)
        brg = np.array([m.bearing_deg for m in a])
        found += bool(np.any((across < 0.1) & (along < 2.3) & (np.abs(brg - 30.0) < 5.0)))
    assert found >= 0.9 * len(stalls)


@pytest.fixture(scope="module")
def road_scene(tmp_path_factory):
    """Two solid 47 m edge lines and a dashed centre line (3 m dashes, 6 m gaps)."""
    marks = [_dash(X0 + 25.6, Y0 - y, 90.0, length=47.0, width=0.12, kind="solid") for y in (9.0, 16.0)]
    marks += [_dash(X0 + 4.0 + 9.0 * k, Y0 - 12.5, 90.0, length=3.0, width=0.12) for k in range(5)]
    out = tmp_path_factory.mktemp("road") / "road.tif"
    return synth.render(marks, out, 0.1, crs=CRS, seed=11, bounds=(X0, Y0 - 25.6, X0 + 51.2, Y0))


def test_pieces_of_a_line_are_stored_solid_and_reach_the_index_as_segments(road_scene, sqlite_url):
    """The pieces the build cuts from one long cluster are stored as
    ``kind="solid"`` in any tiling, the two end pieces of each line too, and the
    localizer's index, built from the store as the service builds it, matches them
    as segments: by the distance across their line. The dashes' kind stays unknown.
    (Without the kind, the index guesses from the geometry and leaves the end pieces
    of every line point-like.)"""
    from localizer import MapIndex
    from service.map_index import index_from_markings

    store = Store(sqlite_url)
    model = pipeline_model()
    built = {}
    for tile_px in (128, 4096):
        build_map(store, f"road-{tile_px}", [road_scene.path], BuildParams(tile_px=tile_px, model=model),
                  workers=1, progress=False)
        built[tile_px] = _detected(store, f"road-{tile_px}")
    a, b = built[128], built[4096]
    pairs, _ = match(_xy(a), _xy(b), 0.1)
    assert len(pairs) == len(a) == len(b)
    assert all(a[i].kind == b[j].kind for i, j in pairs)
    for y in (9.0, 16.0):
        line = [m for m in b if abs(m.y - (Y0 - y)) < 0.2]
        assert sum(m.length_m for m in line) > 45.0
        assert len(line) >= 15 and all(m.kind == "solid" for m in line)
    dashes = [m for m in b if abs(m.y - (Y0 - 12.5)) < 0.2]
    assert len(dashes) == 5 and all(m.kind is None for m in dashes)

    arrays = store.marking_arrays("road-128")
    index = index_from_markings(arrays, CRS)
    on_line = np.abs(arrays.y - (Y0 - 12.5)) > 1.0
    first = np.argmin(np.where(on_line, arrays.x, np.inf))
    assert np.all(index.half_length[on_line] > 0) and np.all(index.half_length[~on_line] == 0)
    guessed = MapIndex.from_arrays(arrays.x, arrays.y, arrays.weight, CRS,
                                   bearing_deg=arrays.bearing_deg, length_m=arrays.length_m)
    assert guessed.half_length[first] == 0  # a line's end piece, taken for a dash
    store.close()


def test_build_summary_and_job(border_scene, sqlite_url):
    store = Store(sqlite_url)
    result = build_map(store, "m", [border_scene.path],
                       BuildParams(tile_px=256, model=pipeline_model()), workers=1,
                       progress=False)
    h, w = border_scene.shape
    assert result.tiles_total == result.tiles_run == math.ceil(h / 256) * math.ceil(w / 256)
    assert result.markings == len(_detected(store, "m"))
    assert result.megapixels == pytest.approx(h * w / 1e6)
    assert result.mpx_per_s > 0
    assert "markings" in result.summary() and "Mpx/s" in result.summary()
    assert "not verified at pixel threshold 0.5" in result.summary()
    assert not result.resumed and result.tiles_skipped == 0
    job = store.get_job(result.job_id)
    assert job.status == "successful" and job.progress == 100.0
    assert len(store.done_tiles(result.job_id)) == result.tiles_total
    info = store.get_map("m")
    assert info.crs == CRS and info.coverage == "imagery"  # made by the build: it covers its imagery
    assert [i.path for i in store.list_imagery("m")] == [str(Path(border_scene.path).resolve())]
    # Bearings are stored from TRUE north: grid bearing + meridian convergence (-0.4° here).
    truth = border_scene.markings
    found = _detected(store, "m")
    pairs, _ = match(_xy(found), _xy(truth), 0.3)
    diffs = [((found[i].bearing_deg - truth[j].bearing_deg + 90) % 180) - 90 for i, j in pairs]
    assert abs(np.median(diffs)) < 0.5
    store.close()


def test_rebuild_keeps_manual_edits(border_scene, store):
    params = BuildParams(tile_px=256, model=pipeline_model())
    build_map(store, "m", [border_scene.path], params, workers=1, progress=False)
    first = sorted(_detected(store, "m"), key=lambda m: (m.x, m.y))
    assert len(first) >= 20
    moved, rejected = first[0], first[1]
    manual = Marking(x=X0 + 45.0, y=Y0 - 3.0, length_m=2.0, width_m=0.15, bearing_deg=10.0,
                     source="manual", kind="dash")
    (manual_id,) = store.add_markings("m", [manual], who="person")
    store.apply_changeset("m", [
        Change("update", moved.id, fields={"x": moved.x + 0.2, "y": moved.y - 0.1,
                                           "status": "accepted"}),
        Change("update", rejected.id, fields={"status": "rejected"}),
    ], who="person")

    build_map(store, "m", [border_scene.path], params, workers=1, progress=False)
    after = _all(store, "m")
    by_id = {m.id: m for m in after}
    # What the person decided stays as they left it.
    assert by_id[manual_id].source == "manual"
    assert by_id[moved.id].status == "accepted"
    assert by_id[moved.id].x == pytest.approx(moved.x + 0.2)
    assert by_id[rejected.id].status == "rejected"
    # Detections were replaced, not duplicated, and none reappears next to a decision.
    fresh = [m for m in after if m.source == "detected" and m.status == "unreviewed"]
    assert len(fresh) == len(first) - 2
    assert not ({m.id for m in fresh} & {m.id for m in first})
    xy = _xy(after)
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert d.min() > 0.5


def test_build_runs_as_a_given_job(border_scene, sqlite_url):
    """A server creates the job first and hands its id to the build."""
    store = Store(sqlite_url)
    store.create_map("m", crs=CRS)
    job_id = store.create_job("build", "m", {"requested_by": "api"})
    result = build_map(store, "m", [border_scene.path], BuildParams(model=pipeline_model()),
                       workers=1, progress=False, job_id=job_id)
    assert result.job_id == job_id
    assert store.get_job(job_id).status == "successful"
    assert [j.id for j in store.find_jobs(kind="build")] == [job_id]
    other = store.create_job("localize", "m", {})
    with pytest.raises(BuildError, match="not a build"):
        build_map(store, "m", [border_scene.path], BuildParams(model=pipeline_model()),
                  progress=False, job_id=other)
    store.close()


def test_changing_the_tile_size_replaces_the_old_tiles(border_scene, sqlite_url):
    store = Store(sqlite_url)
    model = pipeline_model()
    build_map(store, "m", [border_scene.path], BuildParams(tile_px=128, model=model),
              workers=1, progress=False)
    n = len(_detected(store, "m"))
    build_map(store, "m", [border_scene.path], BuildParams(tile_px=256, model=model),
              workers=1, progress=False)
    after = _detected(store, "m")
    assert len(after) == n
    assert all("/256/" in m.tile_key for m in after)
    store.close()


def test_local_process_pool_matches_inline(border_scene, sqlite_url):
    store = Store(sqlite_url)
    params = BuildParams(tile_px=128, model=pipeline_model())
    inline = build_map(store, "a", [border_scene.path], params, workers=1, progress=False)
    pooled = build_map(store, "b", [border_scene.path], params, workers=2, progress=False)
    assert pooled.tiles_run == inline.tiles_run == inline.tiles_total > 6
    a = sorted((round(m.x, 6), round(m.y, 6), m.weight, m.tile_key) for m in _detected(store, "a"))
    b = sorted((round(m.x, 6), round(m.y, 6), m.weight, m.tile_key) for m in _detected(store, "b"))
    assert a == b
    store.close()


def test_geographic_image_is_built_in_its_utm_zone(tmp_path, sqlite_url):
    """Reading through a WarpedVRT keeps positions to centimetres.

    The transparent brightness classifier isolates the geometry of the
    reprojection from the learned model's own errors.
    """
    marks = [_dash(X0 + 5 + 4 * i, Y0 - 10 - (i % 2) * 5, 20 * i) for i in range(6)]
    r = synth.render(marks, tmp_path / "geo.tif", 0.1, crs="EPSG:4326", seed=2,
                     markings_crs=CRS, bounds=(X0, Y0 - 20, X0 + 30, Y0))
    store = Store(sqlite_url)
    build_map(store, "geo", [r.path], BuildParams(tile_px=128, model=BrightnessModel()),
              workers=1, progress=False)
    assert store.get_map("geo").crs == "EPSG:32632"
    found = _detected(store, "geo")
    from mapbuilder.crs import from_wgs84

    tx, ty = from_wgs84("EPSG:32632").transform([m.x for m in r.markings],
                                                 [m.y for m in r.markings])
    # The renderer may hide part of one dash; every other one is found, in place.
    pairs, d = match(_xy(found), np.column_stack([tx, ty]), 0.3)
    assert len(pairs) >= len(marks) - 1
    assert len(found) <= len(marks) + 1
    # Across the dash the position is exact to centimetres; along it, it also
    # depends on how much of the dash the renderer left visible.
    cross, along = [], []
    for i, j in pairs:
        b = math.radians(r.markings[j].bearing_deg)
        dx, dy = found[i].x - tx[j], found[i].y - ty[j]
        cross.append(dx * math.cos(b) - dy * math.sin(b))
        if r.markings[j].extra.get("visible", 1.0) >= 0.95:
            along.append(dx * math.sin(b) + dy * math.cos(b))
    assert np.sqrt(np.mean(np.square(cross))) < 0.03
    assert np.max(np.abs(along)) < 0.15
    store.close()


def test_bad_imagery_fails_before_any_job(tmp_path, sqlite_url):
    import rasterio
    from rasterio.transform import from_origin

    grey = tmp_path / "grey.tif"
    with rasterio.open(grey, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8",
                       crs=CRS, transform=from_origin(X0, Y0, 0.1, 0.1)) as dst:
        dst.write(np.zeros((1, 64, 64), np.uint8))
    store = Store(sqlite_url)
    store.create_map("m", crs=CRS)
    with pytest.raises(ImageryError, match="single band"):
        build_map(store, "m", [grey], BuildParams(model=pipeline_model()), progress=False)
    with pytest.raises(ImageryError, match="not found"):
        build_map(store, "m", [tmp_path / "missing.tif"], BuildParams(model=pipeline_model()),
                  progress=False)
    with pytest.raises(BuildError, match="halo"):
        BuildParams(halo_m=2.0)
    assert store.find_jobs(kind="build") == []
    store.close()


def _lanemap(*args, env, **kw):
    return subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


@pytest.fixture(scope="module")
def big_scene(tmp_path_factory):
    scene = synth.procedural_scene(size_m=(96.0, 96.0), origin=(X0, Y0), seed=21)
    return synth.render(scene, tmp_path_factory.mktemp("big") / "big.tif", 0.1, seed=21)


def test_killed_build_resumes_without_duplicates(big_scene, tmp_path):
    url = f"sqlite:///{tmp_path / 'kill.sqlite'}"
    env = {**os.environ, "LANEMAP_DATABASE_URL": url}
    args = ["build", str(big_scene.path), "--map", "m", "--tile-size", "96", "-j", "2",
            "--no-progress"]
    proc = _lanemap(*args, env=env, start_new_session=True)
    store = Store(url)
    deadline = time.monotonic() + 120
    done = 0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            jobs = store.find_jobs(kind="build", map_id="m") if _has_map(store, "m") else []
            done = len(store.done_tiles(jobs[0].id)) if jobs else 0
            if done >= 15:
                break
            time.sleep(0.05)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:  # it finished first; the asserts below say so
            pass
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    job = store.find_jobs(kind="build", map_id="m")[0]
    assert job.status == "running"
    done = len(store.done_tiles(job.id))
    n_total = math.ceil(big_scene.shape[0] / 96) * math.ceil(big_scene.shape[1] / 96)
    assert 15 <= done < n_total, "the build must be killed midway"
    partial = len(_detected(store, "m"))

    proc = _lanemap(*args, env=env)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert f"{done} resumed" in out
    assert ", verified at pixel threshold 0.2" in out  # the command verifies by default
    jobs = store.find_jobs(kind="build", map_id="m")
    assert [j.id for j in jobs] == [job.id] and jobs[0].status == "successful"
    assert len(store.done_tiles(job.id)) == n_total

    # The same build as the command line's defaults (verified clusters), uninterrupted.
    from mapbuilder.build import default_threshold, default_threshold_low
    from mapbuilder.cluster import ClusterParams

    cluster = ClusterParams(threshold=default_threshold(True),
                            threshold_low=default_threshold_low(True), verify=True)
    ref = build_map(store, "ref", [big_scene.path], BuildParams(tile_px=96, cluster=cluster),
                    workers=1, progress=False)
    resumed = sorted((round(m.x, 6), round(m.y, 6), m.weight, m.tile_key)
                     for m in _detected(store, "m"))
    uninterrupted = sorted((round(m.x, 6), round(m.y, 6), m.weight, m.tile_key)
                           for m in _detected(store, "ref"))
    assert ref.markings == len(uninterrupted) > partial > 0
    assert resumed == uninterrupted
    store.close()


def _has_map(store, map_id):
    from mapbuilder.store import UnknownMapError

    try:
        store.get_map(map_id)
        return True
    except UnknownMapError:
        return False


def test_cli_build_reports_bad_input_in_one_line(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from service.cli import app

    url = f"sqlite:///{tmp_path / 'cli.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    bad = tmp_path / "junk.tif"
    bad.write_bytes(b"junk")
    runner = CliRunner()
    for args, needle in [
        (["build", str(tmp_path / "none.tif"), "--map", "m"], "image not found"),
        (["build", str(USGS_BASE), "--map", "m", "--halo", "1"], "halo"),
        (["build", str(USGS_BASE), "--map", "m", "--model", str(bad)], "model"),
        (["build", str(USGS_BASE), "--map", "m", "--verify", "--verifier",
          str(tmp_path / "none.onnx")], "verifier"),
        (["build", str(USGS_BASE), "--map", "m", "--verify", "--verifier", str(bad)], "model"),
        (["build", str(USGS_BASE), "--map", "m", "--verify-threshold", "1.5"], "verify_threshold"),
        (["build", str(USGS_BASE), "--map", "m", "--continuation-min", "1"],
         "verify_continuation_min"),
        (["build", str(USGS_BASE), "--map", "m", "--threshold-low", "0.3"], "threshold_low"),
        (["build", str(USGS_BASE), "--map", "m", "--threshold-low", "0.1", "--no-hysteresis"],
         "--no-hysteresis"),
    ]:
        res = runner.invoke(app, args)
        assert res.exit_code == 1, (args, res.output)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0]
    # And from the real console script, end to end.
    env = {**os.environ, "LANEMAP_DATABASE_URL": url}
    proc = _lanemap("build", str(bad), "--map", "m", env=env)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 1
    assert err.strip().startswith("error: ") and "cannot open image" in err
    assert len(err.strip().splitlines()) == 1
    assert Store(url).find_jobs(kind="build") == []


def test_a_map_created_without_a_crs_takes_its_first_builds(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from mapbuilder.raster import default_storage_crs
    from service.cli import app

    url = f"sqlite:///{tmp_path / 'cli.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    runner = CliRunner()
    res = runner.invoke(app, ["maps", "create", "usgs"])
    assert res.exit_code == 0 and "chosen at the first import or build" in res.stdout, res.output
    res = runner.invoke(app, ["build", str(USGS_BASE), "--map", "usgs"])
    assert res.exit_code == 0, res.output
    store = Store(url)
    info = store.get_map("usgs", with_count=True)
    assert info.crs == default_storage_crs(USGS_BASE) == "EPSG:26913"
    assert info.count and info.count > 0
    # Made empty without a coverage, it covers its imagery from its first build on, as if the build had made it.
    assert info.coverage == "imagery"
    # Later data keeps it; a CRS that is not metric is refused.
    assert store.adopt_crs("usgs", "EPSG:25832") == "EPSG:26913"
    store.create_map("empty")
    with pytest.raises(StoreError, match="metre|metric|projected"):
        store.adopt_crs("empty", "EPSG:4326")
    assert store.get_map("empty").crs is None
    store.close()


def test_cli_verify_threshold_trades_markings_and_is_recorded(tmp_path, monkeypatch):
    """``--verify-threshold``: a stricter verifier keeps fewer markings of the USGS crop,
    and the threshold is part of the job's parameters (a build resumes only with the
    threshold it was started with)."""
    from typer.testing import CliRunner

    from service.cli import app

    url = f"sqlite:///{tmp_path / 'vt.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    runner = CliRunner()
    counts = {}
    for map_id, extra in (("loose", ["--verify-threshold", "0.05"]), ("default", []),
                          ("strict", ["--verify-threshold", "0.999"]),
                          ("every-continuation", ["--continuation-min", "0"])):
        res = runner.invoke(app, ["build", str(USGS_BASE), "--map", map_id, "--no-progress", *extra])
        assert res.exit_code == 0, res.output
        store = Store(url)
        counts[map_id] = len(list(store.iter_markings(map_id)))
        (job,) = store.find_jobs(kind="build", map_id=map_id)
        store.close()
        cluster = job.params["params"]["cluster"]
        if extra[:1] == ["--continuation-min"]:
            assert cluster["verify_continuation_min"] == 0.0
            assert cluster["verify_threshold"] == ClusterParams.verify_threshold
            continue
        want = float(extra[1]) if extra else ClusterParams.verify_threshold
        assert cluster["verify_threshold"] == want
        assert cluster["verify_continuation_min"] == ClusterParams.verify_continuation_min
    assert counts["loose"] > counts["default"] > counts["strict"], counts
    assert counts["default"] >= 4  # the four visible stall lines
    # without a floor, continuations take back what the verifier rejects outright too
    assert counts["every-continuation"] >= counts["default"], counts


def test_cli_hysteresis_grows_markings_and_is_recorded(tmp_path, monkeypatch):
    """A verified build keeps the faint pixels connected to a marking (hysteresis at
    0.05) unless told not to: the USGS stall lines come out with more pixels, and the
    low threshold is part of the job's parameters."""
    from typer.testing import CliRunner

    from mapbuilder.cluster import CNN_PIXEL_THRESHOLD_LOW
    from service.cli import app

    url = f"sqlite:///{tmp_path / 'hy.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    runner = CliRunner()
    weight, lows = {}, {}
    for map_id, extra in (("default", []), ("off", ["--no-hysteresis"]),
                          ("given", ["--threshold-low", "0.1"]),
                          ("unverified", ["--no-verify"])):
        res = runner.invoke(app, ["build", str(USGS_BASE), "--map", map_id, "--no-progress", *extra])
        assert res.exit_code == 0, res.output
        store = Store(url)
        marks = list(store.iter_markings(map_id))
        (job,) = store.find_jobs(kind="build", map_id=map_id)
        store.close()
        weight[map_id] = (len(marks), sum(m.weight for m in marks))
        lows[map_id] = job.params["params"]["cluster"]["threshold_low"]
    assert lows == {"default": CNN_PIXEL_THRESHOLD_LOW, "off": None, "given": 0.1,
                    "unverified": None}
    assert weight["default"][0] >= 4 and weight["off"][0] >= 4
    assert weight["default"][1] > 1.1 * weight["off"][1], weight


@pytest.fixture(scope="module")
def usgs_builds(tmp_path_factory):
    url = f"sqlite:///{tmp_path_factory.mktemp('usgs') / 'usgs.sqlite'}"
    store = Store(url)
    out = {}
    for name, path in [("plain", USGS_BASE), ("alpha", USGS_ALPHA), ("nodata", USGS_NODATA)]:
        build_map(store, name, [path], BuildParams(tile_px=128), workers=1, progress=False)
        out[name] = _detected(store, name)
        out[name + " ground"] = store.imaged_footprint(name)
    store.close()
    return out


#: Detections the default model may make elsewhere in the USGS crop (kerbs, cars, roofs).
FALSE_POSITIVES_USGS = 25

#: Stall lines of the USGS crop (EPSG:26913): x of each, and the y range they span.
STALLS_X = np.array([519487.2, 519490.0, 519493.0, 519496.0])
STALLS_Y = (4311652.5, 4311659.5)


def _on_stalls(ms):
    return [m for m in ms if np.abs(STALLS_X - m.x).min() < 0.4
            and STALLS_Y[0] <= m.y <= STALLS_Y[1]]


def _by_line(ms):
    lines: dict[int, list] = {}
    for m in _on_stalls(ms):
        lines.setdefault(int(np.abs(STALLS_X - m.x).argmin()), []).append(m)
    return lines


def test_usgs_crop_finds_the_stall_lines(usgs_builds):
    ms = usgs_builds["plain"]
    lines = _by_line(ms)
    assert sorted(lines) == [0, 1, 2, 3], f"stall lines found by the default model: {sorted(lines)}"
    pieces = [m for v in lines.values() for m in v]
    assert all(0.08 <= m.width_m <= 0.6 for m in pieces)
    # Stall lines run north-south: bearings near 0/180 (true north, ~-0.4° convergence),
    # weighted by length since a short fragment has a loose direction.
    off_north = np.array([min(m.bearing_deg, 180 - m.bearing_deg) for m in pieces])
    length = np.array([m.length_m for m in pieces])
    assert np.sum(off_north * length) / np.sum(length) < 20
    assert max(length) >= 0.8
    n_on = sum(len(p) for p in lines.values())
    assert len(ms) - n_on <= FALSE_POSITIVES_USGS


def test_usgs_masked_variants_give_the_same_stall_lines(usgs_builds):
    ref = {k: sum(m.weight for m in v) for k, v in _by_line(usgs_builds["plain"]).items()}
    for name in ("alpha", "nodata"):
        got = {k: sum(m.weight for m in v) for k, v in _by_line(usgs_builds[name]).items()}
        # A few pixels next to the cars are masked in these variants, so the
        # painted area found may differ, never the lines.
        assert sorted(got) == sorted(ref), name
        assert sum(got.values()) == pytest.approx(sum(ref.values()), rel=0.4), name
    # Nothing is detected in the masked-out areas.
    import rasterio

    for name, path in (("alpha", USGS_ALPHA), ("nodata", USGS_NODATA)):
        with rasterio.open(path) as ds:
            mask = ds.dataset_mask()
            inv = ~ds.transform
            for m in usgs_builds[name]:
                c, r = inv @ (m.x, m.y)
                assert mask[int(r), int(c)] > 0


def test_a_build_records_the_ground_its_imagery_shows(usgs_builds):
    """The real crop: whole, its ground is the image's bounds; with an alpha band or a nodata
    value, no masked pixel lies in it, and the ground it leaves out is the masked pixels and at
    most a 2 m cell beside them."""
    import rasterio
    import shapely

    with rasterio.open(USGS_BASE) as ds:
        plain = usgs_builds["plain ground"]  # 15 tiles, joined on a millimetre grid
        assert plain.geom_type == "Polygon" and plain.symmetric_difference(shapely.box(*ds.bounds)).area < 0.1
        whole = shapely.box(*ds.bounds).area
    for name, path in (("alpha", USGS_ALPHA), ("nodata", USGS_NODATA)):
        ground = usgs_builds[name + " ground"]
        with rasterio.open(path) as ds:
            masked = ds.dataset_mask() == 0
            r, c = np.nonzero(masked)
            x, y = ds.transform * (c + 0.5, r + 0.5)
            px = abs(ds.transform.a * ds.transform.e)
        assert masked.any() and not shapely.contains_xy(ground, x, y).any(), name
        # each masked blob costs at most its own 2 m cells and their neighbours
        assert whole - masked.sum() * px - 120.0 < ground.area < whole - masked.sum() * px, name


#: Detections the CNN-verified build may make elsewhere in the USGS crop.
FALSE_POSITIVES_USGS_VERIFIED = 4


@pytest.mark.parametrize("tile_px", [128, 2048])
def test_usgs_crop_verified_build_keeps_the_stall_lines(tmp_path, tile_px):
    """The real 15 cm crop (never trained on): the CNN verifier keeps all four stall
    lines between the parked cars in every variant, and drops most other detections."""
    from mapbuilder.cluster import CNN_PIXEL_THRESHOLD, ClusterParams

    store = Store(f"sqlite:///{tmp_path / 'v.sqlite'}")
    params = BuildParams(tile_px=tile_px,
                         cluster=ClusterParams(threshold=CNN_PIXEL_THRESHOLD, verify=True))
    for name, path in [("plain", USGS_BASE), ("alpha", USGS_ALPHA), ("nodata", USGS_NODATA)]:
        build_map(store, name, [path], params, workers=1, progress=False)
        ms = _detected(store, name)
        lines = _by_line(ms)
        assert sorted(lines) == [0, 1, 2, 3], (name, sorted(lines))
        n_on = sum(len(v) for v in lines.values())
        assert len(ms) - n_on <= FALSE_POSITIVES_USGS_VERIFIED, (name, len(ms) - n_on)
    store.close()


def _kerb_and_line_tif(path: Path, sidewalk=(150, 150, 145)) -> Path:
    """A real GeoTIFF: asphalt with a 0.15 m painted line (asphalt on both sides) at
    x = 10 m, and a 0.25 m bright kerb at x = 25 m with a sidewalk beyond it."""
    import rasterio
    from rasterio.transform import from_origin

    res, h, w = 0.1, 300, 400
    x = np.arange(w) * res
    img = np.empty((h, w, 3), np.float32)
    img[:] = (72, 72, 75)
    img[:, (x >= 10.0) & (x < 10.15)] = (205, 205, 200)
    img[:, (x >= 25.0) & (x < 25.25)] = (200, 198, 190)
    img[:, x >= 25.25] = sidewalk
    img += np.random.default_rng(0).normal(0, 4, img.shape)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8",
                       crs=CRS, transform=from_origin(X0, Y0, res, res)) as ds:
        ds.write(np.clip(img, 0, 255).astype(np.uint8).transpose(2, 0, 1))
    return path


@pytest.mark.parametrize("sidewalk", [(150, 150, 145), (110, 118, 90)])
def test_verifier_drops_a_kerb_and_keeps_a_two_sided_line(tmp_path, sidewalk):
    from mapbuilder.cluster import ClusterParams

    tif = _kerb_and_line_tif(tmp_path / "kerb.tif", sidewalk)
    found = {}
    for verify in (False, True):
        store = Store(f"sqlite:///{tmp_path / f'v{verify}.sqlite'}")
        build_map(store, "m", [tif], BuildParams(cluster=ClusterParams(verify=verify)),
                  workers=1, progress=False)
        ms = _all(store, "m")
        found[verify] = (sum(abs(m.x - (X0 + 10.075)) < 0.3 for m in ms),
                         sum(abs(m.x - (X0 + 25.125)) < 0.3 for m in ms))
        store.close()
    line_plain, kerb_plain = found[False]
    line_checked, kerb_checked = found[True]
    # the pixel classifier alone takes the kerb for paint ...
    assert kerb_plain >= 5 and line_plain >= 8
    # ... the verifier, seeing the sidewalk on one side, does not; the line stays whole
    assert kerb_checked == 0
    assert line_checked == line_plain


def test_build_reports_worker_cpu_seconds(border_scene, tmp_path):
    store = Store(f"sqlite:///{tmp_path / 'cpu.sqlite'}")
    r = build_map(store, "m", [border_scene.path], BuildParams(tile_px=128, model=pipeline_model()),
                  workers=1, progress=False)
    # CPU seconds of the tiles: positive, and never more than their wall time plus a margin
    # for threads (one here)
    assert 0 < r.cpu_seconds <= 1.5 * sum(r.timings.values()) + 0.5
    store.close()


def test_default_thresholds_follow_the_verifier():
    """The CNN verifier pairs with a low pixel threshold and hysteresis; the context
    verifier and unverified builds keep the classifier's own threshold and none."""
    from mapbuilder.build import default_threshold, default_threshold_low
    from mapbuilder.classify import context_verifier_path
    from mapbuilder.cluster import CNN_PIXEL_THRESHOLD, CNN_PIXEL_THRESHOLD_LOW

    assert default_threshold(True) == CNN_PIXEL_THRESHOLD
    assert default_threshold_low(True) == CNN_PIXEL_THRESHOLD_LOW
    assert default_threshold(False) == ClusterParams.threshold
    assert default_threshold_low(False) is None
    ctx = context_verifier_path()
    assert default_threshold(True, ctx) == ClusterParams.threshold
    assert default_threshold_low(True, ctx) is None
    # a pixel threshold at or below the hysteresis threshold leaves no room for it
    assert default_threshold_low(True, threshold=CNN_PIXEL_THRESHOLD_LOW) is None
    assert default_threshold_low(True, threshold=0.1) == CNN_PIXEL_THRESHOLD_LOW


def test_a_build_saves_a_quicklook_of_its_markings_over_the_imagery(tmp_path, monkeypatch):
    """``lanemap build --quicklook``: the real USGS crop at its own 15 cm (a picture never finer
    than the imagery), its detections drawn where they lie, and only there."""
    import matplotlib.image as mpimg
    from typer.testing import CliRunner

    from mapbuilder.quicklook import render_quicklook
    from service.cli import app

    url = f"sqlite:///{tmp_path / 'cli.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    png = tmp_path / "look.png"
    res = CliRunner().invoke(app, ["build", str(USGS_BASE), "--map", "usgs", "--no-progress", "--quicklook", str(png)])
    assert res.exit_code == 0, res.output
    assert f"quicklook: {png} (383 x 233 px, 0.15 m per pixel)" in res.stdout
    store = Store(url)
    found = store.list_markings("usgs", limit=100)[0]
    crs = store.get_map("usgs").crs
    store.close()
    assert len(found) >= 4
    drawn = mpimg.imread(png)[..., :3]
    bare = render_quicklook([str(USGS_BASE)], [], crs, tmp_path / "bare.png", max_px=3000)
    assert drawn.shape[:2] == bare.shape == (233, 383)  # square 0.1498 m pixels over 35 m
    plain = mpimg.imread(tmp_path / "bare.png")[..., :3]
    changed = np.abs(drawn - plain).max(axis=2) > 0.1
    h, w = changed.shape
    changed[:25, :330] = False  # the label (which counts the markings)
    changed[-40:, int(0.65 * w):] = False  # the colour bar
    minx, _, _, maxy = bare.bounds
    rows, cols = np.nonzero(changed)
    x = minx + (cols + 0.5) * bare.resolution_m
    y = maxy - (rows + 0.5) * bare.resolution_m
    # every changed pixel lies on a marking's axis (within its line's width) ...
    d = np.full(x.shape, np.inf)
    for m in found:
        a, b = np.array([m.x0, m.y0]), np.array([m.x1, m.y1])
        t = np.clip(((x - a[0]) * (b - a)[0] + (y - a[1]) * (b - a)[1]) / max(np.sum((b - a) ** 2), 1e-9), 0, 1)
        d = np.minimum(d, np.hypot(x - (a[0] + t * (b - a)[0]), y - (a[1] + t * (b - a)[1])))
    assert changed.sum() > 20 * len(found) and d.max() < 0.5
    # ... and every marking's centroid is drawn
    for m in found:
        r, c = int((maxy - m.y) / bare.resolution_m), int((m.x - minx) / bare.resolution_m)
        assert changed[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].any(), m

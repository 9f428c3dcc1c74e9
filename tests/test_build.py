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
from sqlalchemy import create_engine, text

from tests._build_helpers import USGS_ALPHA, USGS_BASE, USGS_NODATA, match, pipeline_model
from mapbuilder import synth
from mapbuilder.build import BuildError, BuildParams, build_map
from mapbuilder.model import Marking
from mapbuilder.raster import ImageryError
from mapbuilder.store import Change, Store

REPO = Path(__file__).resolve().parents[1]
CRS = "EPSG:25832"
X0, Y0 = 456000.0, 5430000.0


def _dash(cx, cy, bearing, length=3.0, width=0.15):
    b = math.radians(bearing)
    dx, dy = 0.5 * length * math.sin(b), 0.5 * length * math.cos(b)
    return Marking(x=cx, y=cy, length_m=length, width_m=width, bearing_deg=bearing,
                   x0=cx - dx, y0=cy - dy, x1=cx + dx, y1=cy + dy, kind="dash")


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
    crossing = 0
    inv = ~border_scene.transform
    for m in border_scene.markings:
        (c0, r0), (c1, r1) = inv @ (m.x0, m.y0), inv @ (m.x1, m.y1)
        crossing += (c0 // 128 != c1 // 128) or (r0 // 128 != r1 // 128)
    assert crossing >= 8
    # The small tiles found the same markings as one tile, measured the same:
    # nothing lost and nothing found twice at a border.
    assert len(a) == len(b)
    pairs, d = match(_xy(a), _xy(b), 0.3)
    assert len(pairs) == len(a)
    assert d.max() < 0.01
    xy = _xy(a)
    gaps = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    assert gaps.min() > 0.5
    # And they are the true dashes, each one once.
    pairs, d = match(xy, truth, 0.3)
    assert len(pairs) >= 0.9 * len(truth)
    assert len(a) <= len(truth) + 3
    keys = {m.tile_key for m in a}
    assert len(keys) > 5 and all("/128/" in k for k in keys)
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
    job = store.get_job(result.job_id)
    assert job.status == "successful" and job.progress == 100.0
    assert len(store.done_tiles(result.job_id)) == result.tiles_total
    info = store.get_map("m")
    assert info.crs == CRS
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
    marks = [_dash(X0 + 5 + 4 * i, Y0 - 10 - (i % 2) * 5, 20 * i) for i in range(6)]
    r = synth.render(marks, tmp_path / "geo.tif", 0.1, crs="EPSG:4326", seed=2,
                     markings_crs=CRS, bounds=(X0, Y0 - 20, X0 + 30, Y0))
    store = Store(sqlite_url)
    build_map(store, "geo", [r.path], BuildParams(tile_px=128, model=pipeline_model()),
              workers=1, progress=False)
    assert store.get_map("geo").crs == "EPSG:32632"
    found = _detected(store, "geo")
    from mapbuilder.crs import from_wgs84

    tx, ty = from_wgs84("EPSG:32632").transform([m.x for m in r.markings],
                                                 [m.y for m in r.markings])
    pairs, d = match(_xy(found), np.column_stack([tx, ty]), 0.3)
    assert len(pairs) == len(marks) == len(found)
    assert np.sqrt(np.mean(d**2)) < 0.06
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

"""The synthetic aerial renderer: georeferencing, truth, masks, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from pyproj import CRS, Transformer
from typer.testing import CliRunner

from mapbuilder.crs import meridian_convergence_deg, to_wgs84
from mapbuilder.lanelet2 import layout_markings, read_lanelet2
from mapbuilder.synth import (
    SynthError,
    lanelet_scene,
    marking_polygon,
    procedural_scene,
    read_truth_geojson,
    render,
)
from service.cli import app

from ._model_helpers import KARLSRUHE_OSM, read_rgb

ORIGIN = (500000.0, 5400000.0)


@pytest.fixture(scope="module")
def scene():
    return procedural_scene((40.0, 40.0), origin=ORIGIN, seed=21)


def test_render_is_georeferenced_with_requested_grid(scene, tmp_path):
    r = render(scene, tmp_path / "a.tif", 0.08, seed=1, labels_tif=tmp_path / "lab.tif")
    with rasterio.open(r.path) as ds:
        assert CRS.from_user_input(ds.crs) == CRS.from_epsg(25832)
        assert ds.res == pytest.approx((0.08, 0.08))
        assert (ds.width, ds.height) == (500, 500)
        assert ds.count == 3 and ds.dtypes[0] == "uint8"
        assert ds.bounds.left == pytest.approx(ORIGIN[0])
        assert ds.bounds.top == pytest.approx(ORIGIN[1] + 40.0)
        img = ds.read()
    assert img.std() > 10  # a real picture, not a flat fill
    with rasterio.open(tmp_path / "lab.tif") as ds:
        assert ds.transform == r.transform and ds.read(1).any()


def test_truth_matches_the_drawn_markings(scene, tmp_path):
    r = render(scene, tmp_path / "a.tif", 0.1, seed=2, labels_tif=tmp_path / "lab.tif")
    rgb, _, transform, _ = read_rgb(r.path)
    with rasterio.open(tmp_path / "lab.tif") as ds:
        label = ds.read(1) > 0
    lum = rgb.astype(float).mean(axis=2)
    assert len(r.markings) > 10
    inv = ~transform
    checked = 0
    for m in r.markings:
        if m.extra["visible"] < 0.95 or m.width_m < 0.12:
            continue
        c, row = inv @ (m.x, m.y)
        c, row = int(c), int(row)
        if not (3 <= c < rgb.shape[1] - 3 and 3 <= row < rgb.shape[0] - 3):
            continue
        # the label raster is set at the centroid and the paint is brighter than
        # the road 0.5 m across the marking (an edge line has the curb on one side)
        assert label[row - 1:row + 2, c - 1:c + 2].any()
        h = np.radians(m.bearing_deg)
        ox, oy = 0.5 * np.cos(h), -0.5 * np.sin(h)  # across the axis
        sides = []
        for s in (-1, 1):
            cc, rr = inv @ (m.x + s * ox, m.y + s * oy)
            sides.append(lum[int(rr), int(cc)])
        assert lum[row - 1:row + 2, c - 1:c + 2].max() > min(sides) + 15, m
        checked += 1
    assert checked >= 5


def test_truth_geojson_is_wgs84_with_properties(scene, tmp_path):
    r = render(scene, tmp_path / "a.tif", 0.1, seed=3)
    data = json.loads(r.truth_path.read_text())
    assert data["type"] == "FeatureCollection"
    feats = read_truth_geojson(r.truth_path)
    assert len(feats) == len(r.markings)
    lon, lat = to_wgs84("EPSG:25832").transform(r.markings[0].x, r.markings[0].y)
    assert feats[0]["lon"] == pytest.approx(lon, abs=1e-8)
    assert feats[0]["lat"] == pytest.approx(lat, abs=1e-8)
    assert 8.9 < lon < 9.1 and 48.7 < lat < 48.8
    for f in feats:
        assert 0 <= f["bearing_deg"] < 180
        assert f["length_m"] > 0.3 and 0.08 <= f["width_m"] <= 0.6
        assert f["kind"] in {"dash", "solid", "stop_line", "stall"}


def test_truth_bearings_are_true_north(tmp_path):
    lmap = read_lanelet2(KARLSRUHE_OSM)
    grid = layout_markings(lmap, phase_m=1.0)
    m0 = max(grid, key=lambda m: m.length_m if m.kind == "dash" else 0)
    b = (m0.x - 20, m0.y - 20, m0.x + 20, m0.y + 20)
    scene = lanelet_scene(lmap, seed=4, bounds=b, phase_m=1.0)
    r = render(scene, tmp_path / "k.tif", 0.1, seed=4)
    near = min(r.markings, key=lambda m: np.hypot(m.x - m0.x, m.y - m0.y))
    assert np.hypot(near.x - m0.x, near.y - m0.y) < 1e-6
    lon, lat = to_wgs84("EPSG:25832").transform(m0.x, m0.y)
    conv = float(meridian_convergence_deg("EPSG:25832", lon, lat))
    assert conv == pytest.approx(-0.43, abs=0.1)
    assert near.bearing_deg == pytest.approx((m0.bearing_deg + conv) % 180, abs=1e-6)


def test_render_in_geographic_crs_with_alpha(scene, tmp_path):
    r = render(scene, tmp_path / "g.tif", 0.1, crs="EPSG:4326", seed=5, alpha=True, jpeg_quality=85)
    with rasterio.open(r.path) as ds:
        assert ds.crs.is_geographic and ds.count == 4
        # about 10 cm pixels: 40 m span over ~400 pixels each way
        assert 380 <= ds.width <= 420 and 380 <= ds.height <= 420
        mask = ds.dataset_mask()
    assert 0.02 < (mask == 0).mean() < 0.3
    rgb, valid, transform, _ = read_rgb(r.path)
    assert rgb[~valid].mean() < 15  # black under the mask, up to JPEG ringing
    inv = ~transform
    for m in r.markings:  # truth lies in the image CRS and in valid pixels
        c, row = inv @ (m.x, m.y)
        assert valid[int(row), int(c)]
    t = Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True)
    x, y = t.transform(r.markings[0].x, r.markings[0].y)
    assert ORIGIN[0] <= x <= ORIGIN[0] + 40 and ORIGIN[1] <= y <= ORIGIN[1] + 40


def test_render_with_nodata(scene, tmp_path):
    r = render(scene, tmp_path / "n.tif", 0.1, crs="EPSG:32632", seed=6, nodata=0)
    with rasterio.open(r.path) as ds:
        assert ds.nodata == 0
        mask = ds.dataset_mask()
        img = ds.read()
    assert (mask == 0).any() and (mask > 0).mean() > 0.7
    assert (img[:, mask > 0].max(axis=0) > 0).all()  # no real pixel reads as nodata


def test_strips_do_not_change_the_picture(scene, tmp_path):
    a = render(scene, tmp_path / "a.tif", 0.1, seed=7, strip_rows=256, labels_tif=tmp_path / "la.tif")
    b = render(scene, tmp_path / "b.tif", 0.1, seed=7, strip_rows=48, labels_tif=tmp_path / "lb.tif")
    with rasterio.open(tmp_path / "la.tif") as da, rasterio.open(tmp_path / "lb.tif") as db:
        assert (da.read() == db.read()).all()
    ia, ib = read_rgb(a.path)[0].astype(int), read_rgb(b.path)[0].astype(int)
    assert np.abs(ia - ib).mean() < 6  # only the sensor noise differs
    assert len(a.markings) == len(b.markings)


def test_marking_polygon_has_the_marking_shape():
    from mapbuilder.model import Marking

    m = Marking(x=10.0, y=20.0, length_m=3.0, width_m=0.15, bearing_deg=30.0)
    p = marking_polygon(m)
    assert p.area == pytest.approx(0.45, rel=1e-6)
    assert p.centroid.x == pytest.approx(10.0) and p.centroid.y == pytest.approx(20.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"resolution_m": 0.0}, "resolution_m"), ({"crs": "EPSG:999999"}, "CRS")],
)
def test_render_rejects_bad_parameters(scene, tmp_path, kwargs, match):
    args = {"resolution_m": 0.1, **kwargs}
    with pytest.raises(SynthError, match=match):
        render(scene, tmp_path / "x.tif", **args)


def test_procedural_scene_rejects_empty_size():
    with pytest.raises(SynthError, match="size_m"):
        procedural_scene((0.0, 10.0))


def test_cli_synth(tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli.tif"
    res = runner.invoke(app, ["synth", str(out), "--size", "20,15", "--seed", "3", "--no-progress",
                              "--labels", str(tmp_path / "cli_lab.tif")])
    assert res.exit_code == 0, res.output
    assert out.exists() and out.with_suffix(".truth.geojson").exists()
    with rasterio.open(out) as ds:
        assert (ds.width, ds.height) == (200, 150)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--bounds", "1,2,3"], "--bounds"),
        (["--bounds", "10,10,5,20"], "--bounds"),
        (["--resolution", "5"], "resolution_m"),
        (["--jpeg", "0"], "--jpeg"),
        (["--lanelet2", "/nonexistent/map.osm"], "Lanelet2"),
    ],
)
def test_cli_synth_bad_input(tmp_path, args, message):
    runner = CliRunner()
    res = runner.invoke(app, ["synth", str(tmp_path / "x.tif"), "--no-progress", *args])
    assert res.exit_code == 1
    assert "error:" in res.output and message in res.output
    assert "Traceback" not in res.output


def test_parking_scene_has_full_rows_of_stalls_between_cars():
    from mapbuilder.synth import parking_scene

    sc = parking_scene(seed=3)
    stalls = [m for m in sc.markings if m.kind == "stall"]
    assert len(stalls) >= 8 and len(stalls) == len(sc.markings)
    cars = sc.layers["car"]
    # stall lines of 4.8-5.6 m are two true pieces each; most stalls hold a car
    assert len(cars) >= 0.6 * len(stalls) / 2
    # cars are parked close to the lines: most lines have a car body within 0.6 m
    polys = [marking_polygon(m) for m in stalls]
    near = [min(p.distance(c.geom) for c in cars) < 0.6 for p in polys]
    assert np.mean(near) >= 0.5
    with pytest.raises(SynthError):
        parking_scene((10.0, 0.0))


def test_camera_artefacts_fringe_and_sharpen_the_edges_of_lines():
    """The processing artefacts of real orthophotos: coloured fringes and dark rims beside
    white lines, while the road away from them keeps its brightness."""
    from scipy import ndimage

    from mapbuilder.synth import camera_artefacts, markings_scene, random_look, render_array

    lines = [_line(ORIGIN[0] + 5 + 2 * k, ORIGIN[1] + 5, 0.0, 0.15) for k in range(5)]
    sc = markings_scene(lines, "EPSG:25832", seed=1,
                        bounds=(ORIGIN[0], ORIGIN[1], ORIGIN[0] + 20, ORIGIN[1] + 12))
    base = random_look(np.random.default_rng(0), 0.15) | {"noise": 0.5, "blur_px": 0.4}
    art = camera_artefacts(np.random.default_rng(1))
    assert set(art) == {"channel_shift_px", "chroma_blur_px", "sharpen", "sharpen_px"}
    art["chroma_blur_px"] = 0.0
    shifted = art | {"channel_shift_px": np.array([[0, 0.8], [0, 0], [0, -0.8]], np.float32),
                     "sharpen": 0.0}
    sharpened = art | {"channel_shift_px": np.zeros((3, 2), np.float32), "sharpen": 1.2,
                       "sharpen_px": 1.0}
    plain, label, _ = render_array(sc, 0.15, seed=2, look=base)
    fringed, label2, _ = render_array(sc, 0.15, seed=2, look=base | shifted)
    sharp, _, _ = render_array(sc, 0.15, seed=2, look=base | sharpened)
    np.testing.assert_array_equal(label, label2)
    rim = ndimage.binary_dilation(label, iterations=1) & ~label
    ring = ndimage.binary_dilation(label, iterations=2) & ~ndimage.binary_dilation(label)
    far = ~ndimage.binary_dilation(label, iterations=5)

    def sat(img):
        i = img.astype(int)
        return i.max(axis=2) - i.min(axis=2)

    def lum(img):
        return img.astype(float).mean(axis=2)

    # misregistered channels: coloured rims, the road away from the lines unchanged
    assert sat(fringed)[rim].mean() > sat(plain)[rim].mean() + 15
    assert abs(lum(fringed)[far].mean() - lum(plain)[far].mean()) < 2
    # sharpening: brighter lines with darker road just beside them
    assert lum(sharp)[label].mean() > lum(plain)[label].mean() + 5
    assert lum(sharp)[ring].mean() < lum(plain)[ring].mean() - 3
    assert abs(lum(sharp)[far].mean() - lum(plain)[far].mean()) < 2
    again, _, _ = render_array(sc, 0.15, seed=2, look=base | shifted)
    np.testing.assert_array_equal(again, fringed)


def _line(x, y, bearing, width, length=5.0):
    from mapbuilder.model import Marking

    return Marking(kind="stall", x=x, y=y, bearing_deg=bearing, length_m=length,
                   width_m=width)


def _union(scene, layer):
    import shapely

    return shapely.union_all([p.geom for p in scene.layers[layer]])


@pytest.mark.parametrize("seed", [0, 1, 5])
def test_procedural_curbs_stop_before_the_road_they_meet(seed):
    """At a junction the curb of one road ends before the other road: drawn across its
    asphalt it would be a bright stripe the truth does not list (a false "marking")."""
    sc = procedural_scene((60.0, 60.0), seed=seed)
    assert len(sc.layers["road"]) >= 2  # these seeds have a junction
    road, curb = _union(sc, "road"), _union(sc, "curb")
    assert curb.area > 10.0
    assert curb.intersection(road).area < 1e-6


def test_lanelet_pavement_has_no_slivers_and_every_curb_borders_it():
    """Where the pavement gives way to lanes and painted lines, no strip of it narrower
    than half a metre is left on the asphalt, and no curb stands alone there: both
    would look like painted lines (the Karlsruhe crop below had 6 m² of such slivers)."""
    lmap = read_lanelet2(KARLSRUHE_OSM)
    sc = lanelet_scene(lmap, seed=3, bounds=(458046.0, 5428573.0, 458146.0, 5428633.0))
    verge, curb = _union(sc, "verge"), _union(sc, "curb")
    assert verge.area > 1000.0 and curb.area > 100.0
    assert verge.difference(verge.buffer(-0.25).buffer(0.25)).area < 0.1
    assert curb.difference(verge.buffer(0.2)).area < 1e-6

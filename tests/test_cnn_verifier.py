"""The CNN cluster verifier: oriented crops, the shipped ONNX file, builds that use it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from mapbuilder.classify import ClusterVerifier, MarkingModel, ModelError, default_verifier_path
from mapbuilder.cluster import (
    CNN_PIXEL_THRESHOLD,
    CROP_ACROSS,
    CROP_ALONG,
    CROP_CHANNELS,
    CROP_SCALARS,
    ClusterParams,
    cluster_crops,
    detect_markings,
)

REFERENCE = Path(__file__).parent / "data" / "cluster_cnn_reference.npz"
X0, Y0 = 456000.0, 5430000.0


def test_shipped_cnn_verifier_matches_the_torch_model():
    """onnxruntime on the shipped file gives what the torch model gave when it was trained."""
    v = ClusterVerifier(default_verifier_path())
    assert v.kind == "crops"
    assert v.metadata["lanemap.crop_channels"] == ",".join(CROP_CHANNELS)
    d = np.load(REFERENCE)
    p = v.predict_crops(d["crops"].astype(np.float32), d["scalars"])
    np.testing.assert_allclose(p, d["torch_probability"], atol=1e-5)
    # the reference crops are half paint, half not: the model tells most apart
    assert np.mean((p > 0.5) == d["label"]) >= 0.8
    assert v.predict_crops(np.zeros((0, len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG),
                                    np.float32), np.zeros((0, len(CROP_SCALARS)))).shape == (0,)
    # a crop classifier is neither a context verifier nor a pixel model
    with pytest.raises(ModelError, match="crops"):
        v.predict(np.zeros((2, 16), np.float32))
    with pytest.raises(ModelError, match="input"):
        MarkingModel(default_verifier_path())


def _stripe(res: float, bearing: float, length=2.0, width=0.25, size=200):
    """Probability and image of one bright stripe through the centre of a window."""
    t = Affine(res, 0, X0, 0, -res, Y0)
    rows, cols = np.mgrid[0:size, 0:size]
    x = X0 + (cols + 0.5) * res - size * res / 2
    y = Y0 - (rows + 0.5) * res + size * res / 2
    b = math.radians(bearing)
    along = x * math.sin(b) + y * math.cos(b)
    across = x * math.cos(b) - y * math.sin(b)
    on = (np.abs(along - (X0 * math.sin(b) + Y0 * math.cos(b))) <= length / 2) \
        & (np.abs(across - (X0 * math.cos(b) - Y0 * math.sin(b))) <= width / 2)
    rgb = np.full((size, size, 3), 80, np.uint8)
    rgb[on] = 220
    return on.astype(np.float32), rgb, t


@pytest.mark.parametrize("res", [0.05, 0.1, 0.15])
@pytest.mark.parametrize("bearing", [0.0, 33.0, 90.0, 135.0])
def test_cluster_crops_lie_along_the_cluster(res, bearing):
    prob, rgb, t = _stripe(res, bearing)
    c = detect_markings(prob, None, t)
    assert len(c) == 1
    crops, sc = cluster_crops(c, rgb, None, t, prob)
    assert crops.shape == (1, len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG)
    assert sc.shape == (1, len(CROP_SCALARS)) and np.isfinite(sc).all()
    lum, p, ok = crops[0, 0], crops[0, 2], crops[0, 3]
    mid = CROP_ACROSS // 2
    # the 2 m stripe runs along the middle rows (10 cm samples: 20 columns of it),
    # the road beside it is at the crop's median
    centre = lum[mid - 1:mid + 1, 8:24]
    assert centre.max(axis=0).min() > 0.8  # the stripe is 140 grey levels above the road
    assert np.abs(lum[:mid - 3]).max() < 0.2 and np.abs(lum[mid + 3:]).max() < 0.2
    assert p[:, :5].max() < 0.05 and p[:, -5:].max() < 0.05  # beyond its ends
    assert ok.min() == 1.0
    assert sc[0, 4] == pytest.approx(res / 0.1)


def test_cluster_crops_mark_nodata_and_the_window_edge():
    prob, rgb, t = _stripe(0.1, 0.0, size=60)  # 6 m window, the crop reaches past it
    valid = np.ones(prob.shape, bool)
    valid[:, :25] = False
    c = detect_markings(prob, valid, t)
    crops, _ = cluster_crops(c, rgb, valid, t, prob)
    ok = crops[0, 3]
    assert ok.min() == 0.0 and ok.max() == 1.0
    assert np.all(crops[0, :3][:, ok == 0] == 0)
    # the turn and shift training applies move the stripe off the crop's middle
    turned, _ = cluster_crops(c, rgb, None, t, prob, rotate_deg=np.array([90.0]))
    assert turned[0, 2, CROP_ACROSS // 2, :10].max() < 0.05


def test_cnn_verified_build_of_a_held_out_render(tmp_path):
    """A held-out procedural render (seed 9101, never trained on) at 10 cm, built with the
    shipped CNN verifier: precision and recall as the build-quality benchmark scores them."""
    from mapbuilder import synth
    from mapbuilder.build import BuildParams, build_map
    from mapbuilder.evaluate import evaluate_markings
    from mapbuilder.store import Store

    scene = synth.procedural_scene((80.0, 80.0), seed=9101)
    r = synth.render(scene, tmp_path / "h.tif", 0.1, seed=9200)
    import rasterio

    with rasterio.open(r.path) as ds:
        bounds = tuple(ds.bounds)
    found = {}
    for verify in (False, True):
        store = Store(f"sqlite:///{tmp_path / f'{verify}.sqlite'}")
        cluster = ClusterParams(threshold=CNN_PIXEL_THRESHOLD, verify=True) if verify \
            else ClusterParams()
        build_map(store, "m", [r.path], BuildParams(cluster=cluster,
                                                    verifier=str(default_verifier_path())),
                  workers=1, progress=False)
        ev = evaluate_markings(list(store.iter_markings("m")), r.markings, bounds)
        store.close()
        found[verify] = (ev.precision, ev.recall)
    assert ev.n_true >= 40
    (p0, _), (p1, r1) = found[False], found[True]
    assert p1 >= 0.9 and r1 >= 0.8, found
    assert p1 > p0 + 0.1, found


def test_cli_build_verifies_with_the_cnn(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from mapbuilder import synth
    from mapbuilder.store import Store
    from service.cli import app

    url = f"sqlite:///{tmp_path / 'cli.sqlite'}"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    scene = synth.procedural_scene((40.0, 40.0), seed=9103)
    r = synth.render(scene, tmp_path / "s.tif", 0.1, seed=9203)
    runner = CliRunner()
    counts = {}
    for args in (["--no-verify"], ["--verify"],
                 ["--verify", "--verifier", str(default_verifier_path())]):
        res = runner.invoke(app, ["build", str(r.path), "--map", "m", "--restart",
                                  "--no-progress", "-j", "1", *args])
        assert res.exit_code == 0, res.output
        store = Store(url)
        counts[" ".join(args[:1])] = len(list(store.iter_markings("m")))
        store.close()
    # the verifier removes detections (kerbs, car outlines) and keeps most
    assert 0.3 * counts["--no-verify"] < counts["--verify"] < counts["--no-verify"]
    # the CNN is a verifier, not a pixel model
    res = runner.invoke(app, ["build", str(r.path), "--map", "m2", "--model",
                              str(default_verifier_path())])
    assert res.exit_code == 1 and "model" in res.stderr


def test_detections_do_not_depend_on_the_image_memory_layout():
    """The reader hands out band-sequential windows; renders and callers pass interleaved ones."""
    from mapbuilder.build import detect_window
    from mapbuilder.classify import load_model
    from mapbuilder.raster import inspect_imagery, open_grid
    from rasterio.windows import Window

    from tests._build_helpers import USGS_BASE

    info = inspect_imagery(USGS_BASE)
    with open_grid(USGS_BASE, info.grid) as reader:
        planar, valid = reader.read(Window(0, 0, info.grid.width, info.grid.height))
    interleaved = np.ascontiguousarray(planar)
    assert not planar.flags.c_contiguous and interleaved.flags.c_contiguous
    params = ClusterParams(threshold=CNN_PIXEL_THRESHOLD, verify=True)
    out = [detect_window(rgb, valid, info.grid.affine, info.grid.resolution_m, load_model(), params)
           for rgb in (planar, interleaved)]
    (c1, p1), (c2, p2) = out
    np.testing.assert_array_equal(p1, p2)
    assert len(c1) >= 4  # the stall lines
    for f in ("x", "y", "weight", "length_m", "bearing_deg", "score"):
        np.testing.assert_array_equal(getattr(c1, f), getattr(c2, f))
    # both ways of sampling the crops: a few clusters (corner pixels), a tile's worth (whole window)
    for k in (c1.take(np.arange(2)), c1.take(np.repeat(np.arange(len(c1)), 40))):
        a = cluster_crops(k, planar, valid, info.grid.affine, p1)
        b = cluster_crops(k, interleaved, valid, info.grid.affine, p1)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])

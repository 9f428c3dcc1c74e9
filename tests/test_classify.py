"""The shipped marking model on held-out renders and on the real USGS crop."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from mapbuilder.classify import MarkingModel, ModelError, default_model_path, load_model
from mapbuilder.features import (
    FEATURE_NAMES,
    FEATURE_VERSION,
    FeatureError,
    candidate_features,
    pixel_features,
)
from mapbuilder.synth import procedural_scene, render

from ._model_helpers import (
    USGS,
    USGS_ALPHA,
    USGS_NODATA,
    pixel_precision_recall,
    read_rgb,
    stall_line_scores,
)


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.fixture(scope="module")
def heldout(tmp_path_factory):
    """A render the default model never saw (it trains on seeds 1000–1999)."""
    tmp = tmp_path_factory.mktemp("heldout")
    scene = procedural_scene((60.0, 60.0), seed=9321)
    r = render(scene, tmp / "h.tif", 0.1, seed=4, labels_tif=tmp / "h_lab.tif")
    rgb, valid, transform, _ = read_rgb(r.path)
    with rasterio.open(tmp / "h_lab.tif") as ds:
        label = ds.read(1) > 0
    return rgb, valid, label


def test_default_model_ships_with_matching_features(model):
    assert default_model_path().is_file()
    assert default_model_path().stat().st_size < 2_000_000
    assert model.metadata["lanemap.feature_version"] == FEATURE_VERSION
    assert model.metadata["lanemap.features"] == ",".join(FEATURE_NAMES)
    assert load_model(None) is model  # cached per process


def test_separates_markings_from_asphalt_on_a_heldout_render(model, heldout):
    rgb, valid, label = heldout
    prob = model.predict(rgb, valid, 0.1)
    assert prob.shape == label.shape and prob.dtype == np.float32
    assert 0.0 <= prob.min() and prob.max() <= 1.0
    precision, recall = pixel_precision_recall(prob, label, valid)
    assert precision > 0.75, precision
    assert recall > 0.5, recall
    # marking pixels score far higher than the rest
    assert np.median(prob[label]) > 0.5
    assert np.percentile(prob[~label], 99) < 0.5


def test_lights_up_the_stall_lines_of_the_usgs_crop(model):
    """The real crop, at the pixel threshold of the default (verified) build and at
    that of ``--no-verify``: every stall line is lit along much of its length, and
    a good share of what is lit lies on them (the crop holds cars, a tree, kerbs)."""
    from mapbuilder.cluster import CNN_PIXEL_THRESHOLD

    rgb, valid, transform, _ = read_rgb(USGS)
    prob = model.predict(rgb, valid, abs(transform.a))
    near_share, cover = stall_line_scores(prob, transform, CNN_PIXEL_THRESHOLD)
    assert near_share > 0.15, near_share
    assert min(cover) > 0.15, cover
    assert np.mean(cover) > 0.4, cover
    near_share, cover = stall_line_scores(prob, transform, 0.5)
    assert near_share > 0.25, near_share
    assert np.mean(cover) > 0.3, cover


@pytest.mark.parametrize("path", [USGS_ALPHA, USGS_NODATA], ids=["alpha", "nodata"])
def test_masked_usgs_variants(model, path):
    rgb, valid, transform, _ = read_rgb(path)
    assert (~valid).any()
    prob = model.predict(rgb, valid, abs(transform.a))
    assert (prob[~valid] == 0).all()
    # no halo of false markings along the mask border
    from scipy import ndimage

    border = ndimage.binary_dilation(~valid, iterations=3) & valid
    assert (prob[border] > 0.5).mean() < 0.02
    near_share, cover = stall_line_scores(prob, transform)
    assert np.mean(cover) > 0.3, cover


def test_invalid_pixels_get_zero(model, heldout):
    rgb, _, label = heldout
    valid = np.ones(label.shape, bool)
    valid[:, : label.shape[1] // 2] = False
    prob = model.predict(rgb, valid, 0.1)
    assert (prob[~valid] == 0).all()
    assert (prob[valid] > 0.5).any()


def test_overlapping_windows_agree_on_the_pixels_they_share(model, heldout):
    """Tiles read with halos start at any offset: given their origin in the image, two
    windows give the pixels well inside both the same probability. Without it, the
    coarse background grids sit at different places and probabilities differ."""
    rgb, valid, _ = heldout
    whole = model.predict(rgb, valid, 0.1)
    diffs = []
    for r0, c0 in ((88, 41), (130, 203), (7, 5)):
        win = (slice(r0, r0 + 300), slice(c0, c0 + 300))
        inner = (slice(r0 + 60, r0 + 240), slice(c0 + 60, c0 + 240))
        got = model.predict(rgb[win], valid[win], 0.1, origin=(r0, c0))
        np.testing.assert_allclose(got[60:240, 60:240], whole[inner], atol=1e-5)
        unanchored = model.predict(rgb[win], valid[win], 0.1)
        diffs.append(np.abs(unanchored[60:240, 60:240] - whole[inner]).max())
    assert max(diffs) > 0.01


def test_candidates_are_the_full_features_at_those_pixels(heldout):
    rgb, valid, _ = heldout
    sub = rgb[:256, :256]
    full = pixel_features(sub, None, 0.1)
    assert full.shape == (256, 256, len(FEATURE_NAMES)) and full.dtype == np.float32
    assert np.isfinite(full).all()
    feats, idx = candidate_features(sub, None, 0.1)
    assert 0 < len(idx) < 0.5 * 256 * 256
    np.testing.assert_allclose(feats, full.reshape(-1, full.shape[-1])[idx], rtol=1e-5, atol=1e-5)


def test_features_are_resolution_aware():
    """A 15 cm line looks the same to the features at 5 cm and at 15 cm per pixel."""
    values = []
    for res in (0.05, 0.15):
        n = int(round(12.0 / res))
        img = np.full((n, n, 3), 70, np.uint8)
        half = max(1, int(round(0.15 / res / 2)))
        img[:, n // 2 - half: n // 2 + half] = 200
        f = pixel_features(img, None, res)
        values.append(f[n // 2, n // 2])
    names = ["tophat_narrow", "tophat_wide", "side_contrast", "continuation"]
    for name in names:
        i = FEATURE_NAMES.index(name)
        assert values[0][i] > 0.5 and values[1][i] > 0.5
        assert values[0][i] == pytest.approx(values[1][i], rel=0.25), name
    # and a 2 m wide bright slab is not a thin line at either resolution
    i = FEATURE_NAMES.index("tophat_narrow")
    img = np.full((240, 240, 3), 70, np.uint8)
    img[:, 100:140] = 200
    assert pixel_features(img, None, 0.05)[120, 120, i] == 0


@pytest.mark.parametrize(
    "rgb, valid, res, match",
    [
        (np.zeros((10, 10), np.uint8), None, 0.1, "shape"),
        (np.zeros((10, 10, 3), np.float32), None, 0.1, "uint8"),
        (np.zeros((10, 10, 3), np.uint8), np.ones((5, 5), bool), 0.1, "valid"),
        (np.zeros((10, 10, 3), np.uint8), None, 0.0, "resolution_m"),
        (np.zeros((10, 10, 3), np.uint8), None, "a", "resolution_m"),
    ],
)
def test_predict_rejects_bad_input(model, rgb, valid, res, match):
    with pytest.raises(FeatureError, match=match):
        model.predict(rgb, valid, res)
    assert issubclass(FeatureError, ValueError)


def test_bad_model_files(tmp_path):
    with pytest.raises(ModelError, match="does not exist"):
        MarkingModel(tmp_path / "missing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not an onnx model")
    with pytest.raises(ModelError, match="cannot load"):
        load_model(junk)


def test_default_cluster_verifier_ships_and_loads(tmp_path):
    from mapbuilder.classify import (ClusterVerifier, context_verifier_path,
                                     default_verifier_path, load_verifier)
    from mapbuilder.cluster import CONTEXT_FEATURES, CONTEXT_VERSION, CROP_VERSION

    v = load_verifier()
    assert v.path == default_verifier_path() and v.kind == "crops"
    assert v.metadata["lanemap.crop_version"] == CROP_VERSION
    # the context-feature verifier still ships, for --verifier
    v = load_verifier(context_verifier_path())
    assert v.kind == "context"
    assert v.metadata["lanemap.context_version"] == CONTEXT_VERSION
    p = v.predict(np.zeros((3, len(CONTEXT_FEATURES)), np.float32))
    assert p.shape == (3,) and np.all((p >= 0) & (p <= 1))
    assert v.predict(np.zeros((0, len(CONTEXT_FEATURES)), np.float32)).shape == (0,)
    with pytest.raises(ModelError, match="does not exist"):
        ClusterVerifier(tmp_path / "missing.onnx")

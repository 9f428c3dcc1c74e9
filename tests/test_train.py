"""Training a marking model: files → ONNX → load → predict, and bad inputs of ``lanemap train``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from typer.testing import CliRunner

from mapbuilder.classify import MarkingModel
from mapbuilder.features import FEATURE_NAMES
from mapbuilder.synth import procedural_scene, render
from mapbuilder.train import (
    QuadraticSVM,
    TrainingError,
    export_onnx,
    fit_svm,
    train_from_files,
)
from service.cli import app

from ._model_helpers import pixel_precision_recall, read_rgb


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """The two halves of one survey (same scene palette and camera), with label rasters
    and truth GeoJSON: one half to train on, the other to test on."""
    tmp = tmp_path_factory.mktemp("train")
    scene = procedural_scene((90.0, 45.0), origin=(500000.0, 5400000.0), seed=5101)
    out = {}
    for name, x0 in (("train", 500000.0), ("test", 500045.0)):
        r = render(scene, tmp / f"{name}.tif", 0.1, seed=77, labels_tif=tmp / f"{name}_lab.tif",
                   bounds=(x0, 5400000.0, x0 + 45.0, 5400045.0))
        out[name] = (r.path, tmp / f"{name}_lab.tif", r.truth_path)
    return out


def _score(model_path, image, labels):
    rgb, valid, _, _ = read_rgb(image)
    with rasterio.open(labels) as ds:
        label = ds.read(1) > 0
    return pixel_precision_recall(MarkingModel(model_path).predict(rgb, valid, 0.1), label, valid)


def test_train_onnx_load_predict_round_trip(labelled, tmp_path):
    image, labels, _ = labelled["train"]
    r = train_from_files(image, labels, tmp_path / "m.onnx")
    assert r.path.is_file() and r.path.stat().st_size < 100_000
    assert r.n_positive > 500 and r.candidate_recall > 0.8
    model = MarkingModel(r.path)
    assert model.metadata["lanemap.trained_on"] == "train.tif"
    precision, recall = _score(r.path, *labelled["test"][:2])
    assert precision > 0.6 and recall > 0.4, (precision, recall)


def test_train_from_truth_geojson(labelled, tmp_path):
    image, _, truth = labelled["train"]
    r = train_from_files(image, truth, tmp_path / "g.onnx")
    precision, recall = _score(r.path, *labelled["test"][:2])
    assert precision > 0.6 and recall > 0.4, (precision, recall)


def test_onnx_graph_matches_the_fitted_model(tmp_path):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(4000, len(FEATURE_NAMES))).astype(np.float32)
    y = (X[:, 0] * X[:, 1] + 0.3 * X[:, 2] > 0.2)  # needs the quadratic terms
    model = fit_svm(X, y)
    assert isinstance(model, QuadraticSVM)
    p = model.predict_proba(X)[:, 1]
    assert ((p > 0.5) == y).mean() > 0.9
    path = export_onnx(model, tmp_path / "q.onnx")
    np.testing.assert_allclose(MarkingModel(path).predict_features(X), p, atol=1e-4)


def test_fit_rejects_too_few_markings():
    X = np.zeros((5000, len(FEATURE_NAMES)), np.float32)
    y = np.zeros(5000, bool)
    y[:10] = True
    with pytest.raises(TrainingError, match="too few marking pixels"):
        fit_svm(X, y)


def _invoke(*args):
    res = CliRunner().invoke(app, ["train", *map(str, args)])
    return res.exit_code, res.output


def test_cli_train(labelled, tmp_path):
    image, labels, _ = labelled["train"]
    code, out = _invoke(image, labels, "--out", tmp_path / "cli.onnx")
    assert code == 0, out
    assert (tmp_path / "cli.onnx").is_file() and "wrote" in out


def _write_tif(path, array, crs="EPSG:25832", transform=None):
    bands = array if array.ndim == 3 else array[None]
    with rasterio.open(path, "w", driver="GTiff", width=bands.shape[2], height=bands.shape[1],
                       count=bands.shape[0], dtype=bands.dtype, crs=crs,
                       transform=transform) as ds:
        ds.write(bands)


def test_cli_train_bad_inputs(labelled, tmp_path):
    image, labels, truth = labelled["train"]
    with rasterio.open(image) as ds:
        transform, shape = ds.transform, (ds.height, ds.width)
    out = tmp_path / "m.onnx"
    cases = []
    cases.append(((tmp_path / "missing.tif", labels), "does not exist"))
    plain = tmp_path / "plain.tif"  # no georeferencing
    with rasterio.open(plain, "w", driver="GTiff", width=50, height=50, count=3, dtype="uint8") as ds:
        ds.write(np.zeros((3, 50, 50), np.uint8))
    cases.append(((plain, labels), "no georeferencing"))
    grey = tmp_path / "grey.tif"
    _write_tif(grey, np.zeros((1, 50, 50), np.uint8), transform=transform)
    cases.append(((grey, labels), "band"))
    other_crs = tmp_path / "lab_crs.tif"
    with rasterio.open(labels) as ds:
        lab = ds.read(1)
    _write_tif(other_crs, lab, crs="EPSG:32632", transform=transform)
    cases.append(((image, other_crs), "CRS"))
    shifted = tmp_path / "lab_far.tif"
    _write_tif(shifted, lab, transform=from_origin(transform.c + 5000, transform.f, 0.1, 0.1))
    cases.append(((image, shifted), "does not overlap"))
    misaligned = tmp_path / "lab_mis.tif"
    _write_tif(misaligned, lab[: shape[0] // 2], transform=transform)
    cases.append(((image, misaligned), "not aligned"))
    empty = tmp_path / "empty.tif"
    _write_tif(empty, np.zeros_like(lab), transform=transform)
    cases.append(((image, empty), "at least"))
    far = tmp_path / "far.geojson"
    data = json.loads(truth.read_text())
    for f in data["features"]:
        f["geometry"]["coordinates"][0] += 1.0  # a degree east: no overlap
    far.write_text(json.dumps(data))
    cases.append(((image, far), "overlap"))
    bad_points = tmp_path / "bad.geojson"
    bad_points.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [9.0, 48.75]}, "properties": {}}]}))
    cases.append(((image, bad_points), "length_m"))
    txt = tmp_path / "labels.txt"
    txt.write_text("x")
    cases.append(((image, txt), ".geojson"))
    for (img, lab_path), message in cases:
        code, output = _invoke(img, lab_path, "--out", out)
        assert code == 1, (message, output)
        assert output.startswith("error:") and message in output, (message, output)
        assert "Traceback" not in output
    assert not out.exists()
    code, output = _invoke(image, labels, "--out", out, "--C", "0")
    assert code == 1 and "--C" in output


def test_verifier_from_renders_onnx_round_trip(tmp_path):
    """Clusters of two small renders → verifier → ONNX → the same probabilities."""
    from mapbuilder.classify import ClusterVerifier, ModelError
    from mapbuilder.cluster import CONTEXT_FEATURES
    from mapbuilder.train import export_verifier_onnx, fit_verifier, verifier_training_set

    X, y = verifier_training_set([1000, 1001], resolutions=(0.1,), size_m=80.0)
    assert X.shape == (len(y), len(CONTEXT_FEATURES)) and np.isfinite(X).all()
    # the renders hold both paint and other bright stripes (kerbs, lot borders, cars)
    assert y.sum() >= 50 and len(y) - y.sum() >= 30
    clf = fit_verifier(np.concatenate([X, X]), np.concatenate([y, y]), max_iter=20)
    path = export_verifier_onnx(clf, tmp_path / "v.onnx")
    v = ClusterVerifier(path)
    np.testing.assert_allclose(v.predict(X), clf.predict_proba(X)[:, 1], atol=1e-4)
    assert v.metadata["lanemap.context_features"] == ",".join(CONTEXT_FEATURES)
    with pytest.raises(TrainingError, match="too few clusters"):
        fit_verifier(X[:10], y[:10])
    # a pixel model is not a verifier
    from mapbuilder.classify import default_model_path

    with pytest.raises(ModelError, match="context features"):
        ClusterVerifier(default_model_path())


def test_cluster_labels_follow_the_painted_axis():
    from affine import Affine

    from mapbuilder.cluster import detect_markings
    from mapbuilder.train import cluster_labels

    t = Affine(0.1, 0, 0.0, 0, -0.1, 30.0)
    prob = np.zeros((300, 300), np.float32)
    prob[50:80, 100:102] = 0.9   # on paint
    prob[150:180, 200:202] = 0.9  # not
    label = np.zeros((300, 300), bool)
    label[48:82, 100:102] = True
    c = detect_markings(prob, None, t)
    lab = cluster_labels(c, label, t)
    assert sorted(zip(np.round(c.x, 1), lab)) == [(10.1, True), (20.1, False)]


def test_crop_training_set_from_renders_is_the_same_made_in_parts():
    """Crops and labels of the CNN verifier's training set depend on each render's seed
    alone, so the set the training script renders in several processes is the same."""
    from mapbuilder.cluster import CROP_ACROSS, CROP_ALONG, CROP_CHANNELS, CROP_SCALARS
    from mapbuilder.train import crop_training_set

    C, S, y = crop_training_set([1000, 1001], resolutions=(0.1,), size_m=50.0)
    assert C.shape == (len(y), len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG)
    assert S.shape == (len(y), len(CROP_SCALARS)) and np.isfinite(S).all()
    assert np.isfinite(C.astype(np.float32)).all()
    # the renders hold both paint and other bright things
    assert 20 <= y.sum() <= len(y) - 20
    parts = [crop_training_set([s], resolutions=(0.1,), size_m=50.0) for s in (1000, 1001)]
    for whole, k in ((C, 0), (S, 1), (y, 2)):
        np.testing.assert_array_equal(whole, np.concatenate([p[k] for p in parts]))

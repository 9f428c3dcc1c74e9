"""Train a marking classifier and export it to ONNX.

The model is a linear SVM (scikit-learn ``LinearSVC``) on the degree-2
polynomial expansion of the features of :mod:`mapbuilder.features` — an
explicit quadratic kernel, which lets the margin use products such as "bright
*and* unsaturated" — with Platt scaling so that it outputs a probability. The
fitted margin is a quadratic form zᵀAz + bᵀz + c of the standardised
features, exported as a tiny ONNX graph (a few kB; one F x F product per pixel). It is
trained on candidate pixels only — the pixels :func:`candidate_features`
keeps — exactly as :class:`mapbuilder.classify.MarkingModel` evaluates it.

Labelled imagery comes from :mod:`mapbuilder.synth` renders or from a GeoTIFF
plus labels (:func:`train_from_files`): a GeoJSON of markings (Points with
``length_m``, ``width_m``, ``bearing_deg`` become oriented rectangles;
LineStrings are buffered by ``width_m`` or 0.15 m; Polygons are used as they
are) or a label GeoTIFF aligned with the image (non-zero = marking).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .features import CANDIDATE_TOPHAT, FEATURE_NAMES, FEATURE_VERSION, candidate_features

log = logging.getLogger(__name__)

#: Fewest marking pixels a training set must have.
MIN_POSITIVE_PIXELS = 200


class TrainingError(ValueError):
    """Training inputs that cannot produce a model."""


@dataclass
class TrainingSet:
    """Candidate-pixel features and labels gathered from labelled images."""

    X: list[np.ndarray] = field(default_factory=list)
    y: list[np.ndarray] = field(default_factory=list)
    positives_total: int = 0  # labelled marking pixels, candidates or not

    def add(self, X: np.ndarray, y: np.ndarray, positives_total: int) -> None:
        self.X.append(X)
        self.y.append(y)
        self.positives_total += int(positives_total)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.X:
            return np.empty((0, len(FEATURE_NAMES)), np.float32), np.empty(0, bool)
        return np.concatenate(self.X), np.concatenate(self.y)


def sample_pixels(
    rgb: np.ndarray,
    label: np.ndarray,
    valid: np.ndarray | None,
    resolution_m: float,
    rng: np.random.Generator,
    neg_per_pos: float = 6.0,
    max_pixels: int = 60000,
) -> tuple[np.ndarray, np.ndarray]:
    """Features and labels of a sample of candidate pixels of one image.

    All candidate marking pixels are kept (up to ``max_pixels`` / (1 + neg_per_pos))
    and ``neg_per_pos`` times as many candidate background pixels.

    Returns
    -------
    X : (N, F) float32
    y : (N,) bool
    """
    from scipy import ndimage

    feats, idx = candidate_features(rgb, valid, resolution_m)
    label = np.asarray(label, bool)
    y = label.ravel()[idx]
    # the blurred rim of a marking is neither paint nor background: leave it out
    rim = (ndimage.binary_dilation(label, iterations=1) & ~label).ravel()[idx]
    pos = np.flatnonzero(y)
    neg = np.flatnonzero(~y & ~rim)
    n_pos = min(len(pos), int(max_pixels / (1 + neg_per_pos)))
    n_neg = min(len(neg), max(int(n_pos * neg_per_pos), 2000))
    keep = np.concatenate([rng.choice(pos, n_pos, replace=False) if n_pos else pos[:0],
                           rng.choice(neg, n_neg, replace=False) if n_neg else neg[:0]])
    return feats[keep], y[keep]


@dataclass
class QuadraticSVM:
    """A fitted marking classifier: linear SVM on degree-2 features, Platt-scaled.

    P(marking | x) = sigmoid(platt_a * f(z) + platt_b), with z = (x - mean) / scale
    and the SVM margin f(z) = zᵀ A z + bᵀ z + c written as a quadratic form.
    """

    mean: np.ndarray  # (F,)
    scale: np.ndarray  # (F,)
    A: np.ndarray  # (F, F), symmetric
    b: np.ndarray  # (F,)
    c: float
    platt_a: float
    platt_b: float

    def decision_function(self, X: np.ndarray) -> np.ndarray:
        z = (np.asarray(X, np.float64) - self.mean) / self.scale
        return np.einsum("ni,ij,nj->n", z, self.A, z) + z @ self.b + self.c

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        p = 1.0 / (1.0 + np.exp(-(self.platt_a * self.decision_function(X) + self.platt_b)))
        return np.column_stack([1.0 - p, p])


def fit_svm(X: np.ndarray, y: np.ndarray, C: float = 0.5, seed: int = 0,
            max_samples: int = 400_000) -> QuadraticSVM:
    """Fit the quadratic-feature linear SVM and its Platt scaling.

    The SVM (scikit-learn ``LinearSVC`` on ``PolynomialFeatures(2)`` of the
    standardised features) is fitted on 80 % of the pixels; the logistic
    calibration of its margin on the other 20 %.

    Raises
    ------
    TrainingError
        Too few marking or background pixels.
    """
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import PolynomialFeatures
    from sklearn.svm import LinearSVC

    X = np.asarray(X, np.float64)
    y = np.asarray(y, bool)
    if y.sum() < MIN_POSITIVE_PIXELS:
        raise TrainingError(
            f"too few marking pixels to train: {int(y.sum())} (need {MIN_POSITIVE_PIXELS})")
    if (~y).sum() < MIN_POSITIVE_PIXELS:
        raise TrainingError(f"too few background pixels to train: {int((~y).sum())}")
    rng = np.random.default_rng(seed)
    if len(y) > max_samples:
        keep = rng.choice(len(y), max_samples, replace=False)
        X, y = X[keep], y[keep]
    mean = X.mean(axis=0)
    scale = X.std(axis=0)
    scale[scale < 1e-6] = 1.0
    Z = (X - mean) / scale
    poly = PolynomialFeatures(degree=2, include_bias=False)
    P = poly.fit_transform(Z)
    fold = rng.random(len(y)) < 0.8
    svm = LinearSVC(C=C, dual=False, max_iter=2000, random_state=seed)
    svm.fit(P[fold], y[fold])
    margin = svm.decision_function(P[~fold])
    platt = LogisticRegression(C=1e4).fit(margin[:, None], y[~fold])
    nf = X.shape[1]
    A = np.zeros((nf, nf))
    b = np.zeros(nf)
    for w, powers in zip(svm.coef_[0], poly.powers_):
        nz = np.flatnonzero(powers)
        if powers.sum() == 1:
            b[nz[0]] += w
        elif len(nz) == 1:
            A[nz[0], nz[0]] += w
        else:
            A[nz[0], nz[1]] += w / 2
            A[nz[1], nz[0]] += w / 2
    return QuadraticSVM(mean, scale, A, b, float(svm.intercept_[0]),
                        float(platt.coef_[0, 0]), float(platt.intercept_[0]))


def export_onnx(model: QuadraticSVM, path: str | Path, metadata: dict | None = None) -> Path:
    """Write a :class:`QuadraticSVM` as an ONNX graph with lanemap metadata.

    The graph takes ``features`` (N, F) float32 and outputs ``probabilities``
    (N, 2) float32 (column 1: marking). It is a handful of tensor operations
    (one F x F matrix product), far cheaper than an expanded polynomial pipeline.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nf = len(FEATURE_NAMES)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    inits = [
        numpy_helper.from_array(f32(model.mean)[None], "mean"),
        numpy_helper.from_array(f32(1.0 / model.scale)[None], "inv_scale"),
        numpy_helper.from_array(f32(model.A), "A"),
        numpy_helper.from_array(f32(model.b)[:, None], "b"),
        numpy_helper.from_array(f32([model.platt_a * model.c + model.platt_b]), "bias"),
        numpy_helper.from_array(f32([model.platt_a]), "platt_a"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
        numpy_helper.from_array(f32([1.0]), "one"),
    ]
    nodes = [
        helper.make_node("Sub", ["features", "mean"], ["centred"]),
        helper.make_node("Mul", ["centred", "inv_scale"], ["z"]),
        helper.make_node("MatMul", ["z", "A"], ["zA"]),
        helper.make_node("Mul", ["zA", "z"], ["zAz"]),
        helper.make_node("ReduceSum", ["zAz", "axis1"], ["quad"], keepdims=1),
        helper.make_node("MatMul", ["z", "b"], ["lin"]),
        helper.make_node("Add", ["quad", "lin"], ["margin0"]),
        helper.make_node("Mul", ["margin0", "platt_a"], ["scaled"]),
        helper.make_node("Add", ["scaled", "bias"], ["logit"]),
        helper.make_node("Sigmoid", ["logit"], ["p1"]),
        helper.make_node("Sub", ["one", "p1"], ["p0"]),
        helper.make_node("Concat", ["p0", "p1"], ["probabilities"], axis=1),
    ]
    graph = helper.make_graph(
        nodes, "lanemap_marking_svm",
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, [None, nf])],
        [helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, [None, 2])],
        inits,
    )
    onx = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                            producer_name="lanemap")
    onx.ir_version = 8
    onnx.checker.check_model(onx)
    meta = {
        "lanemap.kind": "marking-pixel-classifier",
        "lanemap.model": "linear SVM on degree-2 features, Platt-scaled",
        "lanemap.feature_version": FEATURE_VERSION,
        "lanemap.features": ",".join(FEATURE_NAMES),
        "lanemap.candidate_tophat": str(CANDIDATE_TOPHAT),
    }
    return _save_onnx(onx, path, meta, metadata)


def _save_onnx(onx, path: str | Path, meta: dict[str, str], metadata: dict | None) -> Path:
    """Write an ONNX model with lanemap's metadata (``meta``) and the caller's (``metadata``)."""
    import onnx

    meta = {**meta, **{k: str(v) for k, v in (metadata or {}).items()}}
    for k, v in meta.items():
        entry = onx.metadata_props.add()
        entry.key, entry.value = k, v
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(onx, str(path))
    return path


# --------------------------------------------------------------------------- synthetic data

def _training_lanes(lanelet_map) -> list | None:
    """Centrelines of the west half of a Lanelet2 map: the east half is kept for testing."""
    if lanelet_map is None:
        return None
    xs = np.array([c[len(c) // 2, 0] for c in lanelet_map.centerlines])
    cut = np.median(xs)
    return [c for c, x in zip(lanelet_map.centerlines, xs) if x < cut and len(c) > 5]


def _render_training(i: int, seed: int, resolutions, size_m: float, lanelet_map, lanes, rng,
                     realism: bool = False, max_px: int = 1500):
    """Render the ``i``-th training scene: ``(resolution m, rgb, label, transform)``.

    Resolutions cycle through ``resolutions``; every other render is JPEG-compressed.
    With ``realism`` every sixth scene is a full parking lot
    (:func:`mapbuilder.synth.parking_scene`) and half the renders get the
    processing artefacts of real orthophotos (:func:`mapbuilder.synth.camera_artefacts`),
    drawn from a generator of their own, so the other renders stay as without it.
    """
    from .synth import camera_artefacts, random_look, render_array

    res = float(resolutions[i % len(resolutions)])
    side = min(size_m, max_px * res)
    scene = _training_scene(i, seed, side, lanelet_map, lanes, rng, parking=realism)
    jpeg = int(rng.integers(60, 95)) if i % 2 else None
    look = None
    if realism:
        art = np.random.default_rng(31337 + int(seed))
        if art.random() < 0.5:
            look = random_look(art, res) | camera_artefacts(art, float(art.uniform(0.5, 1.5)))
    rgb, label, transform = render_array(scene, res, seed=seed + 7, jpeg_quality=jpeg, look=look)
    return res, rgb, label, transform


def _training_scene(i: int, seed: int, side: float, lanelet_map, lanes, rng: np.random.Generator,
                    parking: bool = False):
    """Scene ``i`` of a training set: every third one a window of the map's lanes, else procedural.

    With ``parking``, every sixth one (``i % 6 == 1``) is a parking lot, not a procedural scene.
    """
    from .synth import lanelet_scene, parking_scene, procedural_scene

    if lanes and i % 3 == 2:
        c = lanes[int(rng.integers(len(lanes)))]
        x, y = c[len(c) // 2]
        return lanelet_scene(lanelet_map, seed=seed, bounds=(x - side / 2, y - side / 2, x + side / 2, y + side / 2))
    if parking and i % 6 == 1:
        return parking_scene((min(side, 50.0), min(side, 50.0)), seed=seed)
    return procedural_scene((side, side), seed=seed)


def synthetic_training_set(
    seeds: Sequence[int],
    resolutions: Sequence[float] = (0.05, 0.075, 0.1, 0.15, 0.2),
    size_m: float = 70.0,
    lanelet_map=None,
    progress: bool = False,
    neg_per_pos: float = 3.0,
    realism: bool = False,
) -> TrainingSet:
    """Render procedural (and, with ``lanelet_map``, Karlsruhe) scenes and sample pixels.

    Each seed gives one scene at one resolution (cycling through
    ``resolutions``), at most 1000 px a side, with JPEG compression on every
    other render; ``realism`` adds parking lots and orthophoto artefacts as
    for the CNN verifier (:func:`_render_training`).
    """
    from tqdm import tqdm

    ts = TrainingSet()
    rng = np.random.default_rng(12345 + int(seeds[0]) if len(seeds) else 0)
    lanes = _training_lanes(lanelet_map)
    for i, seed in enumerate(tqdm(list(seeds), desc="render+sample", disable=not progress)):
        res, rgb, label, _ = _render_training(i, int(seed), resolutions, size_m, lanelet_map,
                                              lanes, rng, realism=realism, max_px=1000)
        X, y = sample_pixels(rgb, label, None, res, rng, neg_per_pos=neg_per_pos)
        ts.add(X, y, int(label.sum()))
    return ts


# --------------------------------------------------------------------------- labelled files


def _read_image(path: Path):
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    try:
        with warnings.catch_warnings():
            # reported below as a clear error instead
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(path)
    except Exception as exc:
        raise TrainingError(f"cannot open image {path}: {exc}") from exc
    with ds:
        if ds.crs is None or ds.transform.is_identity:
            raise TrainingError(f"image {path} has no georeferencing")
        if not ds.crs.is_projected:
            raise TrainingError(f"image {path} must be in a projected metric CRS, got {ds.crs}")
        if ds.count < 3:
            raise TrainingError(f"image {path} has {ds.count} band(s), RGB expected")
        if ds.width * ds.height > 200_000_000:
            raise TrainingError(f"image {path} is too large to train on at once "
                                f"({ds.width}x{ds.height}); crop it")
        rgb = np.moveaxis(ds.read([1, 2, 3]), 0, -1)
        if rgb.dtype != np.uint8:
            raise TrainingError(f"image {path} must be 8-bit, got {rgb.dtype}")
        valid = ds.dataset_mask() > 0
        res = float(abs(ds.transform.a))
        return rgb, valid, res, ds.transform, ds.crs, (ds.height, ds.width), ds.bounds


def _geojson_shapes(path: Path, dst_crs) -> list:
    import shapely
    from pyproj import CRS, Transformer
    from shapely.geometry import LineString, Point, shape

    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TrainingError(f"cannot read labels {path}: {exc}") from exc
    feats = data.get("features") if isinstance(data, dict) else None
    if not isinstance(feats, list) or not feats:
        raise TrainingError(f"labels {path} hold no GeoJSON features")
    t = Transformer.from_crs(CRS.from_epsg(4326), dst_crs, always_xy=True)
    shapes = []
    for k, f in enumerate(feats):
        try:
            g = shape(f["geometry"])
        except Exception as exc:
            raise TrainingError(f"labels {path}: feature {k} has a bad geometry: {exc}") from exc
        props = f.get("properties") or {}
        g = shapely.transform(g, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))
        if g.geom_type == "Point":
            try:
                length = float(props["length_m"])
                width = float(props["width_m"])
                bearing = float(props["bearing_deg"])
            except (KeyError, TypeError, ValueError):
                raise TrainingError(
                    f"labels {path}: point feature {k} needs numeric length_m, width_m, bearing_deg"
                ) from None
            # bearing is clockwise from true north; close enough to grid north for a label raster
            h = math.radians(bearing)
            dx, dy = 0.5 * length * math.sin(h), 0.5 * length * math.cos(h)
            p = Point(g)
            g = LineString([(p.x - dx, p.y - dy), (p.x + dx, p.y + dy)]).buffer(
                width / 2, cap_style="flat")
        elif g.geom_type in ("LineString", "MultiLineString"):
            g = g.buffer(float(props.get("width_m", 0.15)) / 2, cap_style="flat")
        elif g.geom_type not in ("Polygon", "MultiPolygon"):
            raise TrainingError(f"labels {path}: unsupported geometry {g.geom_type} in feature {k}")
        shapes.append(g)
    return shapes


def read_labels(labels: str | Path, transform, crs, shape: tuple[int, int], bounds) -> np.ndarray:
    """Label mask (True = marking) aligned with an image grid, from GeoJSON or a label GeoTIFF."""
    import rasterio
    from rasterio.features import rasterize

    labels = Path(labels)
    if not labels.exists():
        raise TrainingError(f"labels file {labels} does not exist")
    suffix = labels.suffix.lower()
    if suffix in (".geojson", ".json"):
        shapes = _geojson_shapes(labels, crs)
        return rasterize(((g, 1) for g in shapes), out_shape=shape, transform=transform,
                         fill=0, dtype="uint8").astype(bool)
    if suffix in (".tif", ".tiff"):
        try:
            ds = rasterio.open(labels)
        except Exception as exc:
            raise TrainingError(f"cannot open label raster {labels}: {exc}") from exc
        with ds:
            if ds.crs is None or ds.crs != crs:
                raise TrainingError(f"label raster CRS {ds.crs} differs from the image CRS {crs}")
            if (ds.height, ds.width) != tuple(shape) or not ds.transform.almost_equals(transform):
                lb = ds.bounds
                overlap = not (lb.right <= bounds.left or lb.left >= bounds.right
                               or lb.top <= bounds.bottom or lb.bottom >= bounds.top)
                if not overlap:
                    raise TrainingError(f"label raster {labels} does not overlap the image")
                raise TrainingError(
                    f"label raster {labels} is not aligned with the image "
                    f"(shape {ds.height}x{ds.width} vs {shape[0]}x{shape[1]}, or transform)")
            return ds.read(1) != 0
    raise TrainingError(f"labels must be .geojson/.json or .tif, got {labels.name}")


@dataclass
class TrainResult:
    """A trained model file and what it was trained on."""

    path: Path
    n_pixels: int
    n_positive: int
    candidate_recall: float  # share of labelled marking pixels that are candidates
    train_precision: float
    train_recall: float


def train_from_files(
    image: str | Path,
    labels: str | Path,
    out: str | Path,
    C: float = 0.5,
    seed: int = 0,
) -> TrainResult:
    """Train a model from one labelled GeoTIFF and write it as ONNX.

    Raises
    ------
    TrainingError
        Unreadable or ungeoreferenced image, labels in another CRS, not
        overlapping or misaligned, or too few marking pixels.
    """
    image, labels = Path(image), Path(labels)
    if not image.exists():
        raise TrainingError(f"image {image} does not exist")
    rgb, valid, res, transform, crs, shape, bounds = _read_image(image)
    if not 0.02 <= res <= 0.3:
        raise TrainingError(f"image resolution {res:.3f} m/px is outside 0.02–0.3 m")
    label = read_labels(labels, transform, crs, shape, bounds)
    label &= valid
    n_lab = int(label.sum())
    if n_lab < MIN_POSITIVE_PIXELS:
        raise TrainingError(
            f"labels cover {n_lab} valid image pixels; at least {MIN_POSITIVE_PIXELS} needed "
            "(do the labels overlap the image?)")
    rng = np.random.default_rng(seed)
    X, y = sample_pixels(rgb, label, valid, res, rng, max_pixels=200000)
    model = fit_svm(X, y, C=C, seed=seed)
    p = model.predict_proba(X)[:, 1] > 0.5
    tp = int((p & y).sum())
    path = export_onnx(model, out, {"lanemap.trained_on": image.name})
    return TrainResult(
        path=path, n_pixels=len(y), n_positive=int(y.sum()),
        candidate_recall=float(y.sum() / max(n_lab, 1)),
        train_precision=tp / max(int(p.sum()), 1), train_recall=tp / max(int(y.sum()), 1),
    )


def train_synthetic(
    out: str | Path,
    seeds: Iterable[int] = range(1000, 1060),
    lanelet_map=None,
    C: float = 0.5,
    progress: bool = False,
    realism: bool = False,
) -> Path:
    """Train the default model on synthetic renders and write it as ONNX."""
    seeds = list(seeds)
    ts = synthetic_training_set(seeds, lanelet_map=lanelet_map, progress=progress, realism=realism)
    X, y = ts.arrays()
    log.info("training on %d pixels (%d marking)", len(y), int(y.sum()))
    model = fit_svm(X, y, C=C)
    return export_onnx(model, out, {
        "lanemap.trained_on": f"synthetic renders, seeds {seeds[0]}..{seeds[-1]}",
        "lanemap.n_pixels": len(y),
    })


# --------------------------------------------------------------------------- cluster verifier


def cluster_labels(clusters, label: np.ndarray, transform, min_share: float = 0.6) -> np.ndarray:
    """Which clusters are paint: at least ``min_share`` of their axis lies on a marking.

    The axis is sampled as :func:`mapbuilder.cluster.context_features` samples
    it; the label mask is grown by one pixel so that a centroid line on the
    blurred rim of a thin marking still counts.
    """
    from scipy import ndimage

    from .cluster import N_ALONG

    if len(clusters) == 0:
        return np.zeros(0, bool)
    grown = ndimage.binary_dilation(np.asarray(label, bool), iterations=1)
    h, w = grown.shape
    inv = ~transform
    t = (np.arange(N_ALONG) + 0.5) / N_ALONG * 0.8 + 0.1
    x = clusters.x0[:, None] + (clusters.x1 - clusters.x0)[:, None] * t[None]
    y = clusters.y0[:, None] + (clusters.y1 - clusters.y0)[:, None] * t[None]
    col = np.clip(np.floor(inv.a * x + inv.b * y + inv.c).astype(np.intp), 0, w - 1)
    row = np.clip(np.floor(inv.d * x + inv.e * y + inv.f).astype(np.intp), 0, h - 1)
    return grown[row, col].mean(axis=1) >= min_share


def verifier_training_set(
    seeds: Sequence[int],
    model=None,
    resolutions: Sequence[float] = (0.05, 0.075, 0.1, 0.15, 0.2),
    size_m: float = 100.0,
    lanelet_map=None,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Context features and paint labels of the clusters the pixel model finds in renders.

    Renders scenes as :func:`synthetic_training_set` does (same seeds give the
    same scenes), classifies each with ``model`` (default: the shipped pixel
    model), clusters with the default :class:`~mapbuilder.cluster.ClusterParams`
    without verification, and labels each cluster with :func:`cluster_labels`.

    Returns
    -------
    X : (N, F) float32
        :data:`mapbuilder.cluster.CONTEXT_FEATURES` of every cluster.
    y : (N,) bool
    """
    from tqdm import tqdm

    from .classify import load_model
    from .cluster import ClusterParams, context_features, detect_markings

    model = model or load_model()
    params = ClusterParams(verify=False)
    rng = np.random.default_rng(777 + int(seeds[0]) if len(seeds) else 0)
    lanes = _training_lanes(lanelet_map)
    Xs, ys = [], []
    for i, seed in enumerate(tqdm(list(seeds), desc="render+cluster", disable=not progress)):
        res, rgb, label, transform = _render_training(i, int(seed), resolutions, size_m, lanelet_map, lanes, rng)
        prob = model.predict(rgb, None, res)
        clusters = detect_markings(prob, None, transform, params)
        Xs.append(context_features(clusters, rgb, None, transform))
        ys.append(cluster_labels(clusters, label, transform))
    return np.concatenate(Xs), np.concatenate(ys)


def fit_verifier(X: np.ndarray, y: np.ndarray, seed: int = 0, max_iter: int = 200,
                 max_depth: int = 4):
    """Fit the cluster verifier: gradient-boosted trees on the context features.

    Parameters
    ----------
    X : (N, F) float
        :data:`mapbuilder.cluster.CONTEXT_FEATURES` of clusters.
    y : (N,) bool
        True for paint (:func:`cluster_labels`).
    max_iter : int
        Number of trees.
    max_depth : int
        Depth of each tree.

    Raises
    ------
    TrainingError
        Too few paint or non-paint clusters.
    """
    from sklearn.ensemble import GradientBoostingClassifier

    X = np.asarray(X, np.float32)
    y = np.asarray(y, bool)
    if y.sum() < 50 or (~y).sum() < 50:
        raise TrainingError(f"too few clusters to train a verifier: {int(y.sum())} paint, "
                            f"{int((~y).sum())} other (need 50 of each)")
    # skl2onnx converts the classic GradientBoostingClassifier reliably
    clf = GradientBoostingClassifier(n_estimators=max_iter, max_depth=max_depth,
                                     learning_rate=0.1, subsample=0.8, random_state=seed)
    return clf.fit(X, y)


def export_verifier_onnx(clf, path: str | Path, metadata: dict | None = None) -> Path:
    """Write a fitted verifier as ONNX (``features`` (N, F) → ``probabilities`` (N, 2))."""
    from skl2onnx import to_onnx
    from skl2onnx.common.data_types import FloatTensorType

    from .cluster import CONTEXT_FEATURES, CONTEXT_VERSION

    nf = len(CONTEXT_FEATURES)
    onx = to_onnx(clf, initial_types=[("features", FloatTensorType([None, nf]))],
                  options={id(clf): {"zipmap": False}}, target_opset={"": 17, "ai.onnx.ml": 3})
    meta = {
        "lanemap.kind": "marking-cluster-verifier",
        "lanemap.model": "gradient-boosted trees on cluster shape and context",
        "lanemap.context_version": CONTEXT_VERSION,
        "lanemap.context_features": ",".join(CONTEXT_FEATURES),
    }
    return _save_onnx(onx, path, meta, metadata)


def train_synthetic_verifier(
    out: str | Path,
    seeds: Iterable[int] = range(1000, 1160),
    lanelet_map=None,
    model=None,
    progress: bool = False,
) -> Path:
    """Train the default cluster verifier on synthetic renders and write it as ONNX.

    ``model`` is the pixel model whose clusters it learns to check (default:
    the shipped one); retrain the verifier whenever the pixel model changes.
    """
    seeds = list(seeds)
    X, y = verifier_training_set(seeds, model=model, lanelet_map=lanelet_map, progress=progress)
    log.info("training the verifier on %d clusters (%d paint)", len(y), int(y.sum()))
    clf = fit_verifier(X, y)
    return export_verifier_onnx(clf, out, {
        "lanemap.trained_on": f"synthetic renders, seeds {seeds[0]}..{seeds[-1]}",
        "lanemap.n_clusters": len(y),
    })


# --------------------------------------------------------------------------- CNN cluster verifier


def crop_training_set(
    seeds: Sequence[int],
    model=None,
    params=None,
    resolutions: Sequence[float] = (0.05, 0.075, 0.1, 0.15, 0.2),
    size_m: float = 100.0,
    lanelet_map=None,
    progress: bool = False,
    min_share: float = 0.6,
    realism: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Oriented crops, scalars and paint labels of the clusters the pixel model finds in renders.

    Renders the scenes of :func:`verifier_training_set` (same seeds, same
    scenes), classifies each with ``model`` (default: the shipped pixel
    model), clusters with ``params`` (default: :class:`~mapbuilder.cluster.ClusterParams`
    with :data:`mapbuilder.cluster.CNN_PIXEL_THRESHOLD`, the pixel threshold
    builds with the CNN verifier use) without verification, and labels a
    cluster paint when at least ``min_share`` of its pixels lie on (one pixel
    around) a painted marking. With ``realism`` (the default) a sixth of the
    scenes are full parking lots and half the renders carry the processing
    artefacts of real orthophotos (see :func:`_render_training`): without
    them the verifier rejected the stall lines of the real USGS crop, whose
    edges are sharpened and colour-fringed, with cars close on both sides.

    Returns
    -------
    crops : (N, C, A, L) float16
        :func:`mapbuilder.cluster.cluster_crops` of every cluster.
    scalars : (N, S) float32
    y : (N,) bool
    """
    from scipy import ndimage
    from tqdm import tqdm

    from .classify import load_model
    from .cluster import CNN_PIXEL_THRESHOLD, ClusterParams, cluster_crops, detect_markings

    model = model or load_model()
    params = params or ClusterParams(threshold=CNN_PIXEL_THRESHOLD, verify=False)
    lanes = _training_lanes(lanelet_map)
    Cs, Ss, ys = [], [], []
    for seed in tqdm(list(seeds), desc="render+crop", disable=not progress):
        # everything random about a render follows from its seed alone, so a set
        # made in parts (ranges of seeds) equals the set made at once
        i = int(seed)
        rng = np.random.default_rng(777 + i)
        res, rgb, label, transform = _render_training(i, int(seed), resolutions, size_m,
                                                      lanelet_map, lanes, rng, realism)
        prob = model.predict(rgb, None, res)
        # paint: most of a cluster's pixels on (one pixel around) a painted marking;
        # unlike the axis test of cluster_labels, this holds for pieces of curved lines
        grown = ndimage.binary_dilation(np.asarray(label, bool), iterations=1)
        clusters = detect_markings(prob, None, transform, params, pixel_share=grown)
        # half the crops turned (up to 20 degrees) and moved off the cluster's axis
        n = len(clusters)
        jit = rng.random(n) < 0.5
        rot = np.where(jit, rng.uniform(-20, 20, n), 0.0)
        shift = np.where(jit[:, None], rng.uniform(-1, 1, (n, 2)) * [0.2, 0.06], 0.0)
        c, s = cluster_crops(clusters, rgb, None, transform, prob, rot, shift)
        Cs.append(c.astype(np.float16))
        Ss.append(s)
        ys.append(clusters.share >= min_share)
    return np.concatenate(Cs), np.concatenate(Ss), np.concatenate(ys)

"""Marking probability per pixel, from an ONNX model run with onnxruntime.

A model file is any ONNX classifier taking ``features`` (N, F) float32 —
the features of :mod:`mapbuilder.features` — and returning class
probabilities (N, 2). The default model ships in ``mapbuilder/data/``; train
your own with :mod:`mapbuilder.train` or ``lanemap train``.

Only candidate pixels (narrow white top-hat above a few grey levels, low
saturation) are evaluated; every other pixel gets probability 0.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

import numpy as np

from .features import CANDIDATE_TOPHAT, FEATURE_NAMES, FEATURE_VERSION, candidate_features

log = logging.getLogger(__name__)

#: File name of the default model inside ``mapbuilder/data``.
DEFAULT_MODEL = "marking_svm.onnx"

#: File name of the default cluster verifier inside ``mapbuilder/data``: a small
#: CNN on oriented crops around each cluster (:mod:`mapbuilder.train_cnn`).
DEFAULT_VERIFIER = "cluster_cnn.onnx"

#: File name of the earlier verifier on hand-made context features (boosted trees).
CONTEXT_VERIFIER = "cluster_verifier.onnx"


class ModelError(ValueError):
    """A model file that cannot be loaded or does not fit lanemap's features."""


def default_model_path() -> Path:
    """Path of the default model shipped with the package."""
    return Path(str(resources.files("mapbuilder") / "data" / DEFAULT_MODEL))


def default_verifier_path() -> Path:
    """Path of the default cluster verifier shipped with the package."""
    return Path(str(resources.files("mapbuilder") / "data" / DEFAULT_VERIFIER))


def context_verifier_path() -> Path:
    """Path of the context-feature cluster verifier shipped with the package."""
    return Path(str(resources.files("mapbuilder") / "data" / CONTEXT_VERIFIER))


def _session(path: Path, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    # Batches differ in size from tile to tile; an arena keeps the largest one's
    # memory for good (about 110 MB per build worker), and costs no measurable
    # time to go without.
    opts.enable_cpu_mem_arena = False
    opts.enable_mem_pattern = False
    try:
        return ort.InferenceSession(str(path), sess_options=opts,
                                    providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise ModelError(f"cannot load model {path}: {exc}") from exc


class ClusterVerifier:
    """Accepts or rejects whole clusters from their shape and road-surface context.

    The pixel classifier sees a few decimetres around a pixel; a kerb, the
    rim of a white car roof and a painted line all look like thin bright
    stripes there. The verifier sees a whole cluster: how straight it is and
    what lies on either side along its length
    (:func:`mapbuilder.cluster.context_features`).

    Parameters
    ----------
    path : path
        ONNX classifier taking ``features`` (N, F) float32 over
        :data:`mapbuilder.cluster.CONTEXT_FEATURES` and returning class
        probabilities (N, 2).
    """

    def __init__(self, path: str | Path, threads: int = 1):
        from .cluster import (CONTEXT_FEATURES, CONTEXT_VERSION, CROP_ACROSS, CROP_ALONG,
                              CROP_CHANNELS, CROP_SCALARS, CROP_VERSION)

        self.path = Path(path)
        if not self.path.is_file():
            raise ModelError(f"verifier file {self.path} does not exist")
        self._session = _session(self.path, threads)
        meta = self._session.get_modelmeta().custom_metadata_map
        self.metadata = dict(meta)
        inputs = self._session.get_inputs()
        #: "crops" for a CNN on oriented crops, "context" for context features
        self.kind = "crops" if meta.get("lanemap.kind") == "marking-cluster-cnn" else "context"
        if self.kind == "crops":
            version = meta.get("lanemap.crop_version")
            if version != CROP_VERSION:
                raise ModelError(
                    f"verifier {self.path} was made for crops v{version}, "
                    f"this lanemap samples v{CROP_VERSION}")
            names = {i.name: i for i in inputs}
            if set(names) != {"crops", "scalars"} or list(names["crops"].shape[1:]) != [
                    len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG] \
                    or names["scalars"].shape[-1] != len(CROP_SCALARS):
                raise ModelError(
                    f"verifier {self.path} must take crops (N, {len(CROP_CHANNELS)}, "
                    f"{CROP_ACROSS}, {CROP_ALONG}) and scalars (N, {len(CROP_SCALARS)})")
            self._input = None
        else:
            version = meta.get("lanemap.context_version")
            if version != CONTEXT_VERSION:
                raise ModelError(
                    f"verifier {self.path} was made for context features v{version}, "
                    f"this lanemap computes v{CONTEXT_VERSION}")
            if len(inputs) != 1 or inputs[0].shape[-1] not in (
                    len(CONTEXT_FEATURES), None, "None"):
                raise ModelError(
                    f"verifier {self.path} must take one (N, {len(CONTEXT_FEATURES)}) input")
            self._input = inputs[0].name
        outs = self._session.get_outputs()
        prob = [o for o in outs if "prob" in o.name.lower()]
        self._output = (prob[0] if prob else outs[-1]).name

    def __repr__(self) -> str:
        return f"ClusterVerifier({str(self.path)!r})"

    def _run(self, feeds: dict) -> np.ndarray:
        out = np.asarray(self._session.run([self._output], feeds)[0])
        if out.ndim == 2 and out.shape[1] == 2:
            out = out[:, 1]
        return out.reshape(-1).astype(np.float32)

    def predict(self, feats: np.ndarray) -> np.ndarray:
        """P(paint) per cluster from context features, (N,) float32 (context verifiers)."""
        if self.kind != "context":
            raise ModelError(f"verifier {self.path} classifies crops, not context features")
        if len(feats) == 0:
            return np.zeros(0, np.float32)
        return self._run({self._input: np.ascontiguousarray(feats, np.float32)})

    def predict_crops(self, crops: np.ndarray, scalars: np.ndarray,
                      batch: int = 512) -> np.ndarray:
        """P(paint) per cluster from oriented crops and scalars (CNN verifiers)."""
        if self.kind != "crops":
            raise ModelError(f"verifier {self.path} classifies context features, not crops")
        out = [self._run({"crops": np.ascontiguousarray(crops[i:i + batch], np.float32),
                          "scalars": np.ascontiguousarray(scalars[i:i + batch], np.float32)})
               for i in range(0, len(crops), batch)]
        return np.concatenate(out) if out else np.zeros(0, np.float32)

    def predict_clusters(self, clusters, rgb: np.ndarray, valid: np.ndarray | None,
                         transform, prob: np.ndarray) -> np.ndarray:
        """P(paint) of measured clusters of one window, (N,) float32."""
        from .cluster import cluster_crops, context_features

        if len(clusters) == 0:
            return np.zeros(0, np.float32)
        if self.kind == "crops":
            return self.predict_crops(*cluster_crops(clusters, rgb, valid, transform, prob))
        return self.predict(context_features(clusters, rgb, valid, transform))


_verifiers: dict[str, ClusterVerifier] = {}


def load_verifier(path: str | Path | None = None) -> ClusterVerifier:
    """Load a cluster verifier (cached per process); None loads the default one."""
    p = default_verifier_path() if path is None else Path(path)
    key = str(p.resolve())
    v = _verifiers.get(key)
    if v is None:
        v = ClusterVerifier(p)
        _verifiers[key] = v
    return v


class MarkingModel:
    """A pixel classifier for lane markings.

    Parameters
    ----------
    path : path
        ONNX model file.
    threads : int
        onnxruntime intra-op threads; 1 so that tiles parallelise across processes.
    """

    def __init__(self, path: str | Path, threads: int = 1):
        self.path = Path(path)
        if not self.path.is_file():
            raise ModelError(f"model file {self.path} does not exist")
        self._session = _session(self.path, threads)
        meta = self._session.get_modelmeta().custom_metadata_map
        self.metadata = dict(meta)
        version = meta.get("lanemap.feature_version")
        if version is not None and version != FEATURE_VERSION:
            raise ModelError(
                f"model {self.path} was trained on features v{version}, "
                f"this lanemap computes v{FEATURE_VERSION}")
        inputs = self._session.get_inputs()
        if len(inputs) != 1 or inputs[0].shape[-1] not in (len(FEATURE_NAMES), None, "None"):
            raise ModelError(
                f"model {self.path} must take one (N, {len(FEATURE_NAMES)}) input, "
                f"got {[(i.name, i.shape) for i in inputs]}")
        self._input = inputs[0].name
        outs = self._session.get_outputs()
        prob = [o for o in outs if "prob" in o.name.lower()]
        self._output = (prob[0] if prob else outs[-1]).name
        self.candidate_tophat = float(meta.get("lanemap.candidate_tophat", CANDIDATE_TOPHAT))

    def __repr__(self) -> str:
        return f"MarkingModel({str(self.path)!r})"

    def predict_features(self, feats: np.ndarray) -> np.ndarray:
        """P(marking) for rows of features, (N,) float32."""
        if len(feats) == 0:
            return np.zeros(0, np.float32)
        out = self._session.run([self._output], {self._input: np.ascontiguousarray(feats, np.float32)})[0]
        out = np.asarray(out)
        return (out[:, 1] if out.ndim == 2 else out).astype(np.float32)

    def predict(self, rgb: np.ndarray, valid: np.ndarray | None, resolution_m: float,
                origin: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Probability of "marking" per pixel.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
            Image window including its halo.
        valid : (H, W) bool or None
            False at nodata / alpha-0 / outside-image pixels.
        resolution_m : float
            Ground sampling distance, metres per pixel.
        origin : (int, int)
            Row and column of the window in its image: overlapping windows then
            agree on the pixels they share (see
            :func:`mapbuilder.features.candidate_features`).

        Returns
        -------
        (H, W) float32
            P(marking) in [0, 1]; 0 at invalid pixels and at pixels that cannot be
            markings (not brighter than their surroundings).
        """
        feats, idx = candidate_features(rgb, valid, resolution_m, self.candidate_tophat, origin)
        h, w = rgb.shape[:2]
        prob = np.zeros(h * w, np.float32)
        prob[idx] = self.predict_features(feats)
        return prob.reshape(h, w)


_cache: dict[str, MarkingModel] = {}


def load_model(path: str | Path | None = None) -> MarkingModel:
    """Load a marking model (cached per process).

    Parameters
    ----------
    path : path or None
        ONNX model file; None loads the default model shipped in ``mapbuilder/data``.
    """
    p = default_model_path() if path is None else Path(path)
    key = str(p.resolve())
    model = _cache.get(key)
    if model is None:
        model = MarkingModel(p)
        _cache[key] = model
    return model

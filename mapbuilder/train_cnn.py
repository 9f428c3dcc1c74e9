"""Train the CNN cluster verifier (PyTorch) and export it to ONNX.

Training needs PyTorch (``pip install -e '.[train-cnn]'``); building maps does
not: the exported ONNX file runs in onnxruntime like every other lanemap model
(:class:`mapbuilder.classify.ClusterVerifier`).

The network sees each cluster the pixel classifier found as an oriented crop
(:func:`mapbuilder.cluster.cluster_crops`: 16 x 32 samples, 10 cm apart,
across and along the cluster; luminance, saturation, pixel probability,
valid data) and a few scalars of the cluster's shape. It is small: one 3 x 3
convolution at each of three levels (16 x 32, 8 x 16, 4 x 8 samples), then two
dense layers; about 1.25 M multiply-adds per cluster and 81 k parameters.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _torch():
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        from .train import TrainingError

        raise TrainingError(
            "training the CNN verifier needs PyTorch: pip install -e '.[train-cnn]'") from exc
    return torch


def make_net(width: int = 16):
    """The crop classifier as a ``torch.nn.Module`` returning P(paint) as (N, 2)."""
    torch = _torch()
    nn = torch.nn
    from .cluster import CROP_ACROSS, CROP_ALONG, CROP_CHANNELS, CROP_SCALARS

    nc, ns = len(CROP_CHANNELS), len(CROP_SCALARS)
    flat = 2 * width * (CROP_ACROSS // 4) * (CROP_ALONG // 4)

    class CropNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.features = nn.Sequential(
                nn.Conv2d(nc, width, 3, padding=1), nn.ReLU(),
                nn.MaxPool2d(2),
                nn.Conv2d(width, 2 * width, 3, padding=1), nn.ReLU(),
                nn.MaxPool2d(2),
                nn.Conv2d(2 * width, 2 * width, 3, padding=1), nn.ReLU(),
                nn.Flatten(),
            )
            self.head = nn.Sequential(
                nn.Linear(flat + ns, 64), nn.ReLU(),
                nn.Linear(64, 1),
            )

        def logit(self, crops, scalars):
            return self.head(torch.cat([self.features(crops), scalars], 1))

        def forward(self, crops, scalars):
            p = torch.sigmoid(self.logit(crops, scalars))
            return torch.cat([1 - p, p], 1)

    return CropNet()


def _augment(torch, crops, gen):
    """Random flips across and along (a cluster's axis has no sign), contrast, blur, noise."""
    n = crops.shape[0]
    fa = torch.rand(n, generator=gen) < 0.5
    fl = torch.rand(n, generator=gen) < 0.5
    crops = crops.clone()
    crops[fa] = crops[fa].flip(2)
    crops[fl] = crops[fl].flip(3)
    gain = 0.4 + 1.2 * torch.rand(n, 1, 1, generator=gen)
    crops[:, 0] *= gain
    crops[:, 1] *= gain
    # a third blurred (real imagery is softer than renders), noise on all
    blur = torch.rand(n, generator=gen) < 0.33
    if blur.any():
        k = torch.tensor([0.25, 0.5, 0.25])
        k = (k[:, None] * k[None, :])[None, None].repeat(2, 1, 1, 1)
        x = torch.nn.functional.pad(crops[blur, :2], (1, 1, 1, 1), mode="replicate")
        crops[blur, :2] = torch.nn.functional.conv2d(x, k, groups=2)
    crops[:, :2] += 0.03 * torch.randn(crops[:, :2].shape, generator=gen)
    crops[:, :2] *= crops[:, 3:4]
    return crops


def fit_cnn(crops: np.ndarray, scalars: np.ndarray, y: np.ndarray, epochs: int = 12,
            batch: int = 256, lr: float = 2e-3, seed: int = 0, width: int = 16,
            threads: int | None = None, progress: bool = False):
    """Fit the crop classifier; returns the trained module (eval mode) and the history.

    A tenth of the clusters (chosen by ``seed``) is held out to report accuracy
    each epoch; everything is deterministic for a given seed and thread count.
    """
    torch = _torch()
    from .train import TrainingError

    y = np.asarray(y, bool)
    if y.sum() < 50 or (~y).sum() < 50:
        raise TrainingError(f"too few clusters to train a verifier: {int(y.sum())} paint, "
                            f"{int((~y).sum())} other (need 50 of each)")
    torch.manual_seed(seed)
    if threads:
        torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    hold = rng.random(len(y)) < 0.1
    C = torch.from_numpy(np.asarray(crops, np.float32))
    S = torch.from_numpy(np.asarray(scalars, np.float32))
    Y = torch.from_numpy(y.astype(np.float32))[:, None]
    tr = torch.from_numpy(np.flatnonzero(~hold))
    te = torch.from_numpy(np.flatnonzero(hold))
    net = make_net(width)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * ((len(tr) + batch - 1) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    history = []
    for epoch in range(epochs):
        net.train()
        perm = tr[torch.randperm(len(tr), generator=gen)]
        total = 0.0
        for i in range(0, len(perm), batch):
            b = perm[i:i + batch]
            loss = loss_fn(net.logit(_augment(torch, C[b], gen), S[b]), Y[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(b)
        net.eval()
        with torch.no_grad():
            p = torch.cat([net(C[te[i:i + 2048]], S[te[i:i + 2048]])[:, 1]
                           for i in range(0, len(te), 2048)]) if len(te) else torch.zeros(0)
        acc = float(((p > 0.5) == Y[te, 0].bool()).float().mean()) if len(te) else float("nan")
        history.append({"epoch": epoch + 1, "loss": total / max(len(tr), 1), "held_out_acc": acc})
        if progress:
            log.info("epoch %d: loss %.4f, held-out accuracy %.4f", epoch + 1,
                     history[-1]["loss"], acc)
    net.eval()
    return net, history


def export_cnn_onnx(net, path: str | Path, metadata: dict | None = None) -> Path:
    """Write the crop classifier as ONNX: ``crops``, ``scalars`` → ``probabilities`` (N, 2)."""
    torch = _torch()
    import onnx

    from .cluster import (CROP_ACROSS, CROP_ALONG, CROP_CHANNELS, CROP_SCALARS, CROP_STEP_M,
                          CROP_VERSION)
    from .train import _save_onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    c = torch.zeros(2, len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG)
    s = torch.zeros(2, len(CROP_SCALARS))
    tmp = path.with_suffix(".tmp.onnx")
    net.eval()
    torch.onnx.export(net, (c, s), str(tmp), input_names=["crops", "scalars"],
                      output_names=["probabilities"],
                      dynamic_axes={"crops": {0: "n"}, "scalars": {0: "n"},
                                    "probabilities": {0: "n"}},
                      opset_version=17, dynamo=False)
    onx = onnx.load(str(tmp))
    tmp.unlink()
    del onx.metadata_props[:]
    meta = {
        "lanemap.kind": "marking-cluster-cnn",
        "lanemap.model": "CNN on oriented crops around each cluster",
        "lanemap.crop_version": CROP_VERSION,
        "lanemap.crop_channels": ",".join(CROP_CHANNELS),
        "lanemap.crop_scalars": ",".join(CROP_SCALARS),
        "lanemap.crop_shape": f"{CROP_ACROSS}x{CROP_ALONG}@{CROP_STEP_M}m",
    }
    return _save_onnx(onx, path, meta, metadata)


def torch_predict(net, crops: np.ndarray, scalars: np.ndarray) -> np.ndarray:
    """P(paint) of the torch module, (N,) float32 (to compare with the exported file)."""
    torch = _torch()
    with torch.no_grad():
        out = net(torch.from_numpy(np.asarray(crops, np.float32)),
                  torch.from_numpy(np.asarray(scalars, np.float32)))
    return out[:, 1].numpy().astype(np.float32)

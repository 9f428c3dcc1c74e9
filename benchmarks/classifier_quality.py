"""Quality and speed of the marking classifier.

Held-out synthetic renders (seeds and Karlsruhe map areas never used for the
default model) at 10 cm, plus the real USGS crop:

* pixel level: precision (a predicted pixel within 1 px of a painted one) and
  recall (painted, visible pixels predicted) at probability 0.5;
* marking level, through the pipeline's clustering
  (:func:`mapbuilder.cluster.detect_markings`): a detection matches a discrete
  true marking (dash, stop line, short stall line) when the centroids are
  within 0.3 m; a piece of a continuous line (solid line, long stall line) is
  found when a detection's axis passes within 0.3 m of its centroid, and a
  detection on such a line is correct when its centroid lies within 0.3 m of
  the line — pieces of a solid line are cut at arbitrary places, so their
  centroids cannot be compared. Markings less than 90 % visible (under cars,
  trees) or within 2 m of the image border do not count against recall;
* centroid RMSE of the matched discrete markings;
* on the USGS crop: share of the high-probability pixels near the four visible
  stall lines, and how much of each line lights up;
* classifier speed (features + model) on a 2048 x 2048 window, single thread.

Run: ``.venv/bin/python benchmarks/classifier_quality.py [--model M.onnx] [--n 12]``.
Writes PNG overlays to ``benchmarks/out/``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from mapbuilder.classify import load_model
from mapbuilder.cluster import ClusterParams, detect_markings
from mapbuilder.lanelet2 import read_lanelet2
from mapbuilder.synth import lanelet_scene, procedural_scene, render

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "benchmarks" / "out"
USGS = DATA / "usgs-hro-colorado" / "201404_13SED190110_201404_0x1500m_CL_1.tif"
KARLSRUHE = DATA / "karlsruhe-lanelet2" / "mapping_example.osm"

#: The four stall lines visible in the USGS crop (EPSG:26913), located by hand
#: on an enlarged view: pixel columns 131, 150, 170, 190, rows 74–110
#: (a fifth one lies under the tree canopy east of them).
USGS_STALLS_X = (519487.2, 519490.0, 519493.0, 519496.0)
USGS_STALLS_Y = (4311653.2, 4311658.6)

#: First seed of the held-out renders (the default model trains on 1000–1999).
HELDOUT_SEED = 9000


def heldout_scenes(n: int, lmap=None, size_m: float = 80.0):
    """Procedural scenes and (with ``lmap``) Karlsruhe crops from the east half of the map."""
    out = []
    rng = np.random.default_rng(HELDOUT_SEED)
    east = []
    if lmap is not None:
        xs = np.array([c[len(c) // 2, 0] for c in lmap.centerlines])
        cut = np.median(xs)  # the default model trains on the west half
        east = [c for c, x in zip(lmap.centerlines, xs) if x >= cut and len(c) > 5]
    for i in range(n):
        seed = HELDOUT_SEED + i
        if east and i % 3 == 2:
            c = east[int(rng.integers(len(east)))]
            x, y = c[len(c) // 2]
            h = size_m / 2
            out.append((f"karlsruhe-{seed}", lanelet_scene(lmap, seed=seed, bounds=(x - h, y - h, x + h, y + h))))
        else:
            out.append((f"procedural-{seed}", procedural_scene((size_m, size_m), seed=seed)))
    return out


def pixel_scores(prob: np.ndarray, label: np.ndarray, valid: np.ndarray, thr: float = 0.5):
    """(true positives for precision, predicted, true positives for recall, labelled)."""
    pred = (prob > thr) & valid
    near = ndimage.binary_dilation(label, iterations=1)
    return int((pred & near).sum()), int(pred.sum()), int((pred & label).sum()), int((label & valid).sum())


def _seg_dist(px, py, x0, y0, x1, y1):
    """Distance of points (P,) to segments (S,), shape (P, S)."""
    dx, dy = x1 - x0, y1 - y0
    L2 = np.maximum(dx * dx + dy * dy, 1e-12)
    t = np.clip(((px[:, None] - x0) * dx + (py[:, None] - y0) * dy) / L2, 0, 1)
    qx, qy = x0 + t * dx, y0 + t * dy
    return np.hypot(px[:, None] - qx, py[:, None] - qy)


def marking_scores(det, truth, bounds, tol: float = 0.3, border: float = 2.0, min_visible: float = 0.9):
    """Match detections to truth; returns counts and centroid errors.

    Returns dict with tp_det, n_det, tp_truth, n_truth, errors (list of metres).
    """
    xmin, ymin, xmax, ymax = bounds
    inside = lambda x, y: (x > xmin + border) & (x < xmax - border) & (y > ymin + border) & (y < ymax - border)  # noqa: E731
    dx, dy = np.asarray(det.x), np.asarray(det.y)
    keep = inside(dx, dy)
    dx, dy = dx[keep], dy[keep]
    d0 = np.column_stack([det.x0, det.y0, det.x1, det.y1])[keep]
    tx = np.array([m.x for m in truth])
    ty = np.array([m.y for m in truth])
    cont = np.array([bool(m.extra.get("continuous")) for m in truth], bool)
    vis = np.array([float(m.extra.get("visible", 1.0)) for m in truth])
    counted = inside(tx, ty) & (vis >= min_visible) if len(truth) else np.zeros(0, bool)
    det_ok = np.zeros(len(dx), bool)
    found = np.zeros(len(tx), bool)
    errors: list[float] = []
    disc = ~cont
    if len(dx) and disc.any():
        d = np.hypot(dx[:, None] - tx[disc][None], dy[:, None] - ty[disc][None])
        cost = np.where(d <= tol, d, 1e6)
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] <= tol
        det_ok[r[ok]] = True
        idx = np.flatnonzero(disc)[c[ok]]
        found[idx] = True
        errors = list(d[r[ok], c[ok]][counted[idx]])
    if len(dx) and cont.any():
        seg = np.array([[m.x0, m.y0, m.x1, m.y1] for m in np.array(truth, dtype=object)[cont]], float)
        dist = _seg_dist(dx, dy, *seg.T)
        det_ok |= dist.min(axis=1) <= tol
        back = _seg_dist(tx[cont], ty[cont], *d0.T)
        found[np.flatnonzero(cont)] = back.min(axis=1) <= tol
    return {
        "tp_det": int(det_ok.sum()), "n_det": int(len(dx)),
        "tp_truth": int((found & counted).sum()), "n_truth": int(counted.sum()),
        "errors": errors,
    }


def usgs_check(model, plot: bool = True) -> dict:
    with rasterio.open(USGS) as ds:
        rgb = np.moveaxis(ds.read([1, 2, 3]), 0, -1)
        valid = ds.dataset_mask() > 0
        t = ds.transform
    prob = model.predict(rgb, valid, abs(t.a))
    rows, cols = np.nonzero(prob > 0.5)
    x = t.c + (cols + 0.5) * t.a
    y = t.f + (rows + 0.5) * t.e
    dist = np.min(np.abs(x[:, None] - np.array(USGS_STALLS_X)[None]), axis=1)
    near = (dist < 0.45) & (y > USGS_STALLS_Y[0] - 0.45) & (y < USGS_STALLS_Y[1] + 0.45)
    cover = []
    for sx in USGS_STALLS_X:
        ys = np.arange(USGS_STALLS_Y[0] + 0.2, USGS_STALLS_Y[1] - 0.2, 0.15)
        hit = [np.any((np.abs(x - sx) < 0.3) & (np.abs(y - yy) < 0.15)) for yy in ys]
        cover.append(float(np.mean(hit)))
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(18, 6))
        ax[0].imshow(rgb)
        ax[1].imshow(prob, vmin=0, vmax=1, cmap="magma")
        for a in ax:
            a.set_axis_off()
        fig.savefig(OUT / "classifier_usgs.png", dpi=70, bbox_inches="tight")
        plt.close(fig)
    return {"pred_px": int(len(x)), "near_share": float(near.mean()) if len(x) else 0.0, "cover": cover}


def speed(model, size: int = 2048, reps: int = 3) -> float:
    scene = procedural_scene((size * 0.1, size * 0.1), seed=HELDOUT_SEED + 500)
    with tempfile.TemporaryDirectory() as tmp:
        r = render(scene, Path(tmp) / "s.tif", 0.1, seed=1)
        with rasterio.open(r.path) as ds:
            rgb = np.moveaxis(ds.read(), 0, -1)
    valid = np.ones(rgb.shape[:2], bool)
    model.predict(rgb, valid, 0.1)
    t0 = time.perf_counter()
    for _ in range(reps):
        model.predict(rgb, valid, 0.1)
    return rgb.shape[0] * rgb.shape[1] * reps / 1e6 / (time.perf_counter() - t0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    ap.add_argument("--n", type=int, default=12, help="number of held-out renders")
    ap.add_argument("--resolution", type=float, default=0.1)
    ap.add_argument("--no-speed", action="store_true")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    model = load_model(args.model)
    print(f"model: {model.path}")
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average)")
    lmap = read_lanelet2(KARLSRUHE)
    px = np.zeros(4, np.int64)
    mk = {"tp_det": 0, "n_det": 0, "tp_truth": 0, "n_truth": 0, "errors": []}
    params = ClusterParams()
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, scene) in enumerate(heldout_scenes(args.n, lmap)):
            r = render(scene, Path(tmp) / f"{name}.tif", args.resolution, seed=k + 77,
                       jpeg_quality=85 if k % 2 else None, labels_tif=Path(tmp) / f"{name}_lab.tif")
            with rasterio.open(r.path) as ds:
                rgb = np.moveaxis(ds.read([1, 2, 3]), 0, -1)
                valid = ds.dataset_mask() > 0
                b = ds.bounds
            with rasterio.open(Path(tmp) / f"{name}_lab.tif") as ds:
                label = ds.read(1) > 0
            prob = model.predict(rgb, valid, args.resolution)
            s = pixel_scores(prob, label, valid)
            px += s
            det = detect_markings(prob, valid, r.transform, params)
            m = marking_scores(det, r.markings, (b.left, b.bottom, b.right, b.top))
            for key in ("tp_det", "n_det", "tp_truth", "n_truth"):
                mk[key] += m[key]
            mk["errors"] += m["errors"]
            print(f"  {name:18} px P {s[0] / max(s[1], 1):.3f} R {s[2] / max(s[3], 1):.3f} | "
                  f"markings P {m['tp_det'] / max(m['n_det'], 1):.3f} ({m['n_det']}) "
                  f"R {m['tp_truth'] / max(m['n_truth'], 1):.3f} ({m['n_truth']})")
            if k < 2:
                _plot(rgb, prob, label, det, r.transform, OUT / f"classifier_{name}.png")
    err = np.array(mk["errors"])
    print(f"pixels   @0.5: precision {px[0] / max(px[1], 1):.3f}  recall {px[2] / max(px[3], 1):.3f}")
    print(f"markings @0.3 m: precision {mk['tp_det'] / max(mk['n_det'], 1):.3f} "
          f"({mk['tp_det']}/{mk['n_det']})  recall {mk['tp_truth'] / max(mk['n_truth'], 1):.3f} "
          f"({mk['tp_truth']}/{mk['n_truth']})  centroid RMSE "
          f"{math.sqrt(float(np.mean(err ** 2))) * 100 if len(err) else float('nan'):.1f} cm "
          f"(n={len(err)})")
    u = usgs_check(model)
    print(f"USGS crop: {u['pred_px']} px > 0.5, {u['near_share']:.2f} of them on the stall lines; "
          f"line coverage {', '.join(f'{c:.2f}' for c in u['cover'])}")
    if not args.no_speed:
        print(f"classifier speed: {speed(model):.1f} Mpx/s (one thread, 2048 x 2048 window at 10 cm)")
    return 0


def _plot(rgb, prob, label, det, transform, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(18, 9))
    ax[0].imshow(rgb)
    inv = ~transform
    if len(det):
        c, r = inv * (np.asarray(det.x), np.asarray(det.y))
        ax[0].plot(c, r, "c+", ms=8)
    ax[1].imshow(prob, vmin=0, vmax=1, cmap="magma")
    ax[1].contour(label, levels=[0.5], colors="lime", linewidths=0.4)
    for a in ax:
        a.set_axis_off()
    fig.savefig(path, dpi=60, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())

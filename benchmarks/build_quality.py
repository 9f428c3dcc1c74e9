"""End-to-end quality of ``lanemap build`` on held-out renders at 10 cm and on the USGS crop.

Each held-out scene (procedural seeds from 9000 and crops of the east half of
the Karlsruhe Lanelet2 map; the default model trains on seeds 1000–1999 and
the west half) is rendered to a GeoTIFF, built into a map with
:func:`mapbuilder.build.build_map` (tiles, workers, store), read back from
the store and compared with the renderer's truth by
:func:`mapbuilder.evaluate.evaluate_markings` (as ``lanemap evaluate`` does):

* a detection matches a discrete true marking (dash, stop line, stall line)
  when the centroids are within 0.3 m (one-to-one, Hungarian assignment);
* pieces of continuous lines are cut at arbitrary places, so there a
  detection is correct when its centroid lies within 0.3 m of a true piece's
  axis, and a true piece is found when a detection's axis passes within 0.3 m
  of its centroid. A marking longer than the builder keeps whole
  (``ClusterParams.whole_max_length_m``, 8 m: stop lines across three or more
  lanes of the Karlsruhe map, up to 17 m) is cut into pieces by design and is
  scored the same way;
* precision = correct detections / detections; recall = found / countable
  truth (at least 90 % visible, centroid at least 2 m inside the image);
* centroid RMSE over the matched discrete markings, and the cross-track RMSE
  of detections on continuous lines.

The USGS crop (15 cm, real) is built in its three variants (plain, alpha,
nodata): the figures are the detections on the stall lines and elsewhere.
Overlays of detections on the imagery and the figures go to
``benchmarks/out/build_quality*.{png,json}`` (``build_quality_verified*`` with
``--verify``, which turns the cluster verifier on: the CNN of
``mapbuilder/data/cluster_cnn.onnx`` at pixel threshold 0.2, unless told otherwise).

Usage::

    .venv/bin/python benchmarks/build_quality.py [--n 6] [--size 150] [--model M.onnx] [--verify]
        [--verifier V.onnx] [--threshold T] [--threshold-low T | --no-hysteresis]
        [--verify-threshold T] [--no-continuation | --continuation-min P] [--halves-m M] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio

from mapbuilder.build import BuildParams, build_map, default_threshold_low
from mapbuilder.classify import load_verifier
from mapbuilder.cluster import CNN_PIXEL_THRESHOLD, ClusterParams
from mapbuilder.evaluate import evaluate_markings
from mapbuilder.lanelet2 import read_lanelet2
from mapbuilder.store import Store
from mapbuilder.synth import lanelet_scene, procedural_scene, render

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "benchmarks" / "out"
KARLSRUHE = DATA / "karlsruhe-lanelet2" / "mapping_example.osm"
USGS_DIR = DATA / "usgs-hro-colorado"
USGS_VARIANTS = {
    "plain": USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1.tif",
    "alpha": USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1_alpha.tif",
    "nodata": USGS_DIR / "201404_13SED190110_201404_0x1500m_CL_1_nodata.tif",
}
#: Stall lines of the USGS crop (EPSG:26913) by hand on an enlarged view: x of
#: each line, and the y range they span. Four are clearly visible; a fifth,
#: east of them, is mostly under the tree canopy.
USGS_STALLS_X = (519487.2, 519490.0, 519493.0, 519496.0, 519499.0)
USGS_STALLS_Y = (4311652.5, 4311659.5)
HELDOUT_SEED = 9000
TOL = 0.3


def heldout_scenes(n: int, size_m: float, first_seed: int = HELDOUT_SEED):
    lmap = read_lanelet2(KARLSRUHE)
    xs = np.array([c[len(c) // 2, 0] for c in lmap.centerlines])
    east = [c for c, x in zip(lmap.centerlines, xs) if x >= np.median(xs) and len(c) > 5]
    rng = np.random.default_rng(first_seed)
    for i in range(n):
        seed = first_seed + i
        if i % 3 == 2:
            c = east[int(rng.integers(len(east)))]
            x, y = c[len(c) // 2]
            h = size_m / 2
            yield f"karlsruhe-{seed}", lanelet_scene(lmap, seed=seed,
                                                     bounds=(x - h, y - h, x + h, y + h))
        else:
            yield f"procedural-{seed}", procedural_scene((size_m, size_m), seed=seed)


def overlay(path_png: Path, image: Path, det, kinds, missed, title: str, window=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with rasterio.open(image) as ds:
        rgb = ds.read((1, 2, 3)).transpose(1, 2, 0)
        b = ds.bounds
    fig, ax = plt.subplots(figsize=(10, 10 * rgb.shape[0] / rgb.shape[1] + 0.6))
    ax.imshow(rgb, extent=(b.left, b.right, b.bottom, b.top))
    for m, k in zip(det, kinds):
        ax.plot([m.x0, m.x1], [m.y0, m.y1], "-", color="lime" if k == "tp" else "red", lw=1.5)
        ax.plot(m.x, m.y, "+", color="yellow" if k == "tp" else "red", ms=5)
    for t in missed:
        ax.plot(t.x, t.y, "o", mfc="none", mec="cyan", ms=7)
    if window is not None:
        ax.set_xlim(window[0], window[2])
        ax.set_ylim(window[1], window[3])
    ax.set_title(title + "  (green: correct, red: false, cyan circle: missed)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path_png, dpi=110)
    plt.close(fig)


def run_usgs(store: Store, params: BuildParams, workers: int, tag: str = "") -> dict:
    out = {}
    sx = np.array(USGS_STALLS_X)
    for name, path in USGS_VARIANTS.items():
        map_id = f"usgs-{name}"
        build_map(store, map_id, [path], params, workers=workers, progress=False)
        det = list(store.iter_markings(map_id))
        on_stall = [
            m for m in det
            if np.min(np.abs(sx - m.x)) < 0.4 and USGS_STALLS_Y[0] <= m.y <= USGS_STALLS_Y[1]
        ]
        lines = {int(np.argmin(np.abs(sx - m.x))) for m in on_stall}
        out[name] = {
            "detections": len(det),
            "on_stall_lines": len(on_stall),
            "stall_lines_found": len(lines),
            "elsewhere": len(det) - len(on_stall),
            "stalls": sorted((round(m.x, 2), round(m.y, 2), round(m.length_m, 2),
                              round(m.bearing_deg, 1)) for m in on_stall),
        }
        if name == "plain":
            kinds = np.array(["tp" if m in on_stall else "fp" for m in det], object)
            overlay(OUT / f"build_quality{tag}_usgs.png", path, det, kinds, [],
                    f"USGS crop 15 cm: {len(on_stall)} detections on stall lines, "
                    f"{len(det) - len(on_stall)} elsewhere")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=6, help="held-out scenes")
    ap.add_argument("--size", type=float, default=150.0, help="scene side, metres")
    ap.add_argument("--model", default=None)
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--seed", type=int, default=HELDOUT_SEED,
                    help="first scene seed; tune on others than the held-out 9000+")
    ap.add_argument("--threshold", type=float, default=None,
                    help="pixel threshold (default: 0.5; with --verify and a CNN verifier, "
                    "CNN_PIXEL_THRESHOLD, as lanemap build)")
    ap.add_argument("--min-length", type=float, default=ClusterParams.min_length_m)
    ap.add_argument("--min-area", type=float, default=ClusterParams.min_area_m2)
    ap.add_argument("--link", type=float, default=ClusterParams.link_m)
    ap.add_argument("--threshold-low", type=float, default=None,
                    help="hysteresis threshold (default: as lanemap build, 0.05 with --verify)")
    ap.add_argument("--no-hysteresis", action="store_true", help="no hysteresis threshold")
    ap.add_argument("--join-gap", type=float, default=ClusterParams.join_gap_m)
    ap.add_argument("--verify-threshold", type=float, default=ClusterParams.verify_threshold)
    ap.add_argument("--verify", action="store_true",
                    help="check clusters with the cluster verifier (ClusterParams.verify)")
    ap.add_argument("--verifier", default=None, help="ONNX cluster verifier (default: shipped)")
    ap.add_argument("--no-continuation", action="store_true",
                    help="drop what the verifier rejects even when it continues what it keeps")
    ap.add_argument("--continuation-min", type=float,
                    default=ClusterParams.verify_continuation_min,
                    help="verifier probability a continuation needs to be taken back")
    ap.add_argument("--halves-m", type=float, default=ClusterParams.verify_halves_m,
                    help="check rejected clusters this long again on each half (0: off)")
    ap.add_argument("--usgs-only", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_verified" if args.verify else ""
    if args.threshold is None:
        args.threshold = ClusterParams.threshold
        if args.verify and load_verifier(args.verifier).kind == "crops":
            args.threshold = CNN_PIXEL_THRESHOLD
    if args.no_hysteresis:
        args.threshold_low = None
    elif args.threshold_low is None:
        args.threshold_low = default_threshold_low(args.verify, args.verifier, args.threshold)
    cluster = ClusterParams(threshold=args.threshold, min_length_m=args.min_length,
                            min_area_m2=args.min_area, link_m=args.link,
                            threshold_low=args.threshold_low, join_gap_m=args.join_gap,
                            verify=args.verify, verify_threshold=args.verify_threshold,
                            verify_continuation=not args.no_continuation,
                            verify_continuation_min=args.continuation_min,
                            verify_halves_m=args.halves_m)
    params = BuildParams(model=args.model, cluster=cluster, verifier=args.verifier)
    totals = {k: 0 for k in ("tp_det", "n_det", "tp_truth", "n_truth", "tp_truth_discrete",
                             "n_truth_discrete")}
    errors, cross, per_scene, error_kinds = [], [], [], []
    t_build = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(f"sqlite:///{tmp}/quality.sqlite")
        for i, (name, scene) in enumerate(heldout_scenes(0 if args.usgs_only else args.n,
                                                         args.size, args.seed)):
            tif = Path(tmp) / f"{name}.tif"
            r = render(scene, tif, 0.1, seed=args.seed + 100 + i,
                       jpeg_quality=85 if i % 2 else None)
            t0 = time.perf_counter()
            build_map(store, name, [tif], params, workers=args.workers, progress=False)
            t_build += time.perf_counter() - t0
            det = list(store.iter_markings(name))
            with rasterio.open(tif) as ds:
                bounds = tuple(ds.bounds)
            ev = evaluate_markings(det, r.markings, bounds, tolerance_m=TOL)
            totals["tp_det"] += ev.n_correct
            totals["n_det"] += ev.n_detected
            totals["tp_truth"] += ev.n_found
            totals["n_truth"] += ev.n_true
            totals["tp_truth_discrete"] += int((ev.found & ev.counted & ~ev.is_line).sum())
            totals["n_truth_discrete"] += int((ev.counted & ~ev.is_line).sum())
            errors += list(ev.centroid_errors_m)
            error_kinds += ev.centroid_error_kinds
            cross += list(ev.cross_track_m)
            p = ev.n_correct / max(ev.n_detected, 1)
            rc = ev.n_found / max(ev.n_true, 1)
            per_scene.append((name, ev.n_detected, ev.n_true, round(p, 3), round(rc, 3)))
            print(f"{name:>18}: {ev.n_detected:4d} detections, {ev.n_true:4d} true, "
                  f"precision {p:.3f}, recall {rc:.3f}")
            kinds = np.where(ev.detection_ok, "tp", "fp").astype(object)
            overlay(OUT / f"build_quality{tag}_{name}.png", tif, ev.detected, kinds, ev.missed,
                    f"{name}, 10 cm")
        usgs = run_usgs(store, params, args.workers, tag)
        store.close()
    errors, cross = np.array(errors), np.array(cross)
    error_kinds = np.array(error_kinds, object)
    rmse_by_kind = {str(k): {"n": int((error_kinds == k).sum()), "rmse_m": round(float(
        np.sqrt(np.mean(errors[error_kinds == k] ** 2))), 4)} for k in sorted(set(error_kinds))}
    figures = {
        "first_seed": args.seed,
        "verify": args.verify,
        "cluster": vars(cluster) if hasattr(cluster, "__dict__") else str(cluster),
        "scenes": args.n,
        "scene_side_m": args.size,
        "precision": round(totals["tp_det"] / max(totals["n_det"], 1), 4),
        "recall": round(totals["tp_truth"] / max(totals["n_truth"], 1), 4),
        "recall_discrete": round(
            totals["tp_truth_discrete"] / max(totals["n_truth_discrete"], 1), 4),
        "centroid_rmse_m": round(float(np.sqrt(np.mean(errors**2))), 4) if errors.size else None,
        "cross_track_rmse_m": round(float(np.sqrt(np.mean(cross**2))), 4) if cross.size else None,
        "centroid_rmse_by_kind": rmse_by_kind,
        "detections": totals["n_det"],
        "true_countable": totals["n_truth"],
        "build_seconds": round(t_build, 1),
        "usgs": usgs,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    for k, v in figures.items():
        if k != "usgs":
            print(f"{k:>20}: {v}")
    for name, u in usgs.items():
        print(f"  usgs {name:>6}: {u['stall_lines_found']} stall lines "
              f"({u['on_stall_lines']} detections), {u['elsewhere']} detections elsewhere")
    (OUT / f"build_quality{tag}.json").write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()

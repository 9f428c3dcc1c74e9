"""Localization against a map built from imagery: the whole chain, imagery to pose.

The held-out east half of the Karlsruhe Lanelet2 map (the default pixel model
and cluster verifier were trained on the west half and on procedural scenes)
is rendered to 10 cm GeoTIFFs, one per area with markings, and built into a
map exactly as ``lanemap build`` builds one (verified, hysteresis, default
tiles and workers). Vehicle scenes are then simulated from the *true*
geometry, as in ``localize_paper.py`` (same camera, noise, clutter and
initial errors), with the vehicle and the ground it sees inside the rendered
areas, and localized with the default method against

* **Lanelet2**: the true markings of the same areas, indexed with their kinds
  as after an import (the upper bound a perfect map gives);
* **detected**: the built map, indexed from the store as the service does,
  with the kinds the build gives (``solid`` for the pieces it cut from one
  long cluster, unknown otherwise; a detection of unknown kind cut short or
  run long gets slack along its axis, ``localizer.index.length_slack``);
* **detected, no kinds**: the same markings with every kind unknown (the index
  then infers the pieces of solid lines from their geometry alone);
* **detected, coverage imagery**: the built map with its extent drawn as for a
  map whose ``coverage`` is ``imagery`` (the ground the build's tiles imaged,
  joined to the markings' extent) instead of its markings' hull, which spans
  the unrendered ground between the areas.

The oracle (least squares on the true inliers) is the same for all three.
Also printed: how the build's kinds agree with the truth (detections on a
true solid line that are ``solid``; on a dash or stop line that are not).
An overlay of the detections, coloured by kind, on one area goes to
``benchmarks/out/localize_detected_overlay.png``; tables and figures to
``benchmarks/out/localize_detected.{md,json}``.

Run: ``.venv/bin/python benchmarks/localize_detected.py [--runs 200] [--seed 0] [--workdir DIR]``
(``--workdir`` keeps the renders and the built map and reuses them when run again).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from shapely import STRtree, points
from shapely.geometry import LineString
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))

import localize_paper as lp  # noqa: E402
from _localizer_helpers import CRS, KARLSRUHE_OSM, karlsruhe  # noqa: E402

from localizer import MapIndex, Options, localize  # noqa: E402
from localizer.simulate import Camera, SceneMap, oracle_pose, sample_poses  # noqa: E402
from mapbuilder.build import BuildParams, build_map, default_threshold, default_threshold_low  # noqa: E402
from mapbuilder.cluster import ClusterParams  # noqa: E402
from mapbuilder.lanelet2 import MARKING_TYPES, layout_markings, read_lanelet2  # noqa: E402
from mapbuilder.store import Store  # noqa: E402
from mapbuilder.synth import lanelet_scene, render  # noqa: E402
from service.map_index import index_from_markings  # noqa: E402

OUT = ROOT / "benchmarks" / "out"
MAP_ID = "karlsruhe-east"
#: Rendered around each group of markings, metres: a vehicle 25 m behind its
#: view's far end, and the view's cone, stay inside.
MARGIN_M = 40.0
#: Seeds of the renders (build_quality.py holds out 9000 onwards; these differ).
RENDER_SEED = 9500


def east_areas(lmap) -> list[tuple[float, float, float, float]]:
    """Bounds of the groups of markings in the held-out east half, with a margin."""
    xs = np.array([c[len(c) // 2, 0] for c in lmap.centerlines])
    split = float(np.median(xs))  # the same split as build_quality.py's
    xy = np.array([(m.x, m.y) for m in layout_markings(lmap, phase_m=0.0)])
    xy = xy[xy[:, 0] >= split + MARGIN_M]
    groups = fcluster(linkage(xy, "single"), 2 * MARGIN_M, "distance")
    out = []
    for g in np.unique(groups):
        p = xy[groups == g]
        if len(p) >= 8:
            lo, hi = p.min(0) - MARGIN_M, p.max(0) + MARGIN_M
            out.append((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
    return out


def build(workdir: Path, areas, workers: int) -> tuple[Store, list[Path], float]:
    """Render the areas and build them into one map, as ``lanemap build`` would."""
    db = workdir / "map.sqlite"
    tifs = [workdir / f"area{i}.tif" for i in range(len(areas))]
    store = Store(f"sqlite:///{db}")
    lmap = read_lanelet2(KARLSRUHE_OSM, crs=CRS)
    for i, (b, tif) in enumerate(zip(areas, tifs)):
        if not tif.exists():
            scene = lanelet_scene(lmap, seed=RENDER_SEED + i, bounds=b, phase_m=0.0)
            render(scene, tif, 0.1, seed=RENDER_SEED + 100 + i, jpeg_quality=85 if i % 2 else None)
    cluster = ClusterParams(threshold=default_threshold(True), threshold_low=default_threshold_low(True),
                            verify=True)
    t0 = time.perf_counter()
    build_map(store, MAP_ID, tifs, BuildParams(cluster=cluster), workers=workers, progress=True)
    return store, tifs, time.perf_counter() - t0


def inside(areas, xy: np.ndarray, shrink: float = 0.0) -> np.ndarray:
    xy = np.atleast_2d(xy)
    ok = np.zeros(len(xy), bool)
    for x0, y0, x1, y1 in areas:
        ok |= ((xy[:, 0] >= x0 + shrink) & (xy[:, 0] <= x1 - shrink)
               & (xy[:, 1] >= y0 + shrink) & (xy[:, 1] <= y1 - shrink))
    return ok


def poses_in(areas, smap: SceneMap, cam: Camera, n: int, seed: int) -> np.ndarray:
    """Poses whose whole view (25 m ahead, ±30°) lies inside one rendered area."""
    rng = np.random.default_rng(seed)
    lines = []
    for c in smap.centerlines:
        keep = inside(areas, c, 5.0)
        # runs of consecutive vertices inside
        for run in np.split(np.arange(len(c)), np.flatnonzero(np.diff(keep.astype(int)) != 0) + 1):
            if keep[run[0]] and len(run) >= 2:
                lines.append(c[run])
    sub = SceneMap(smap.marking_xy, smap.marking_kind, smap.solid_lines, smap.curbs, lines)
    out = []
    for pose in sample_poses(sub, 20 * n, rng, cam, min_visible=4):
        ahead = [(pose[0] + r * math.cos(pose[2] + a), pose[1] + r * math.sin(pose[2] + a))
                 for r in (0.0, cam.max_range_m) for a in np.radians((-cam.half_fov_deg, 0.0, cam.half_fov_deg))]
        if inside(areas, np.array(ahead), 2.0).all():
            out.append(pose)
            if len(out) == n:
                break
    return np.array(out)


def kind_agreement(markings, lmap, areas) -> dict:
    """How the build's kinds agree with the truth, over detections on true markings."""
    solid = [LineString(ln.xy) for ln in lmap.lines_of(*MARKING_TYPES)
             if ln.subtype not in ("dashed",) and ln.type != "stop_line"]
    discrete = np.array([(m.x, m.y) for m in layout_markings(lmap, phase_m=0.0) if m.kind != "solid"])
    xy = np.array([(m.x, m.y) for m in markings])
    kinds = np.array([m.kind for m in markings], object)
    tree = STRtree(solid)
    near_solid = np.zeros(len(xy), bool)
    idx = tree.query(points(xy), predicate="dwithin", distance=0.3)
    near_solid[idx[0]] = True
    from scipy.spatial import cKDTree

    d, _ = cKDTree(discrete).query(xy)
    near_discrete = (d <= 0.5) & ~near_solid
    on_solid = kinds[near_solid] == "solid"
    on_discrete = kinds[near_discrete] == "solid"
    return {
        "detections": len(xy),
        "solid": int((kinds == "solid").sum()),
        "on_solid_lines": int(near_solid.sum()),
        "on_solid_lines_marked_solid": float(on_solid.mean()) if on_solid.size else math.nan,
        "on_dashes_or_stop_lines": int(near_discrete.sum()),
        "on_dashes_or_stop_lines_marked_solid": float(on_discrete.mean()) if on_discrete.size else math.nan,
    }


def restricted_truth(areas) -> MapIndex:
    """The Lanelet2 markings of the rendered areas, indexed as after an import."""
    index, _ = karlsruhe(kinds=True)
    return _subset(index, inside(areas, index.xy))


def _subset(index: MapIndex, keep: np.ndarray, kinds=None) -> MapIndex:
    half = index.half_length[keep]
    axis = index.axis[keep]
    if kinds is None:
        kinds = np.where(half > 0, "solid", "dash")
    bearing = np.degrees(np.arctan2(axis[:, 0], axis[:, 1])) % 180.0
    return MapIndex.from_arrays(index.xy[keep, 0], index.xy[keep, 1], index.weight[keep], index.crs,
                                kind=kinds, bearing_deg=bearing, length_m=2 * half)


def overlay(path: Path, tif: Path, markings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rasterio

    with rasterio.open(tif) as ds:
        step = max(1, int(max(ds.width, ds.height) / 2500))
        rgb = ds.read((1, 2, 3), out_shape=(3, ds.height // step, ds.width // step)).transpose(1, 2, 0)
        b = ds.bounds
    fig, ax = plt.subplots(figsize=(11, 11 * rgb.shape[0] / rgb.shape[1] + 0.6))
    ax.imshow(rgb, extent=(b.left, b.right, b.bottom, b.top))
    for m in markings:
        if b.left <= m.x <= b.right and b.bottom <= m.y <= b.top:
            ax.plot([m.x0, m.x1], [m.y0, m.y1], "-", lw=1.6,
                    color="deepskyblue" if m.kind == "solid" else "orangered")
    ax.set_title("detected markings: blue = piece of a line (kind solid), red = kind unknown", fontsize=9)
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200, help="scenes per scenario")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--workdir", type=Path, help="keep renders and map here (reused when present)")
    args = ap.parse_args()
    lmap = read_lanelet2(KARLSRUHE_OSM, crs=CRS)
    areas = east_areas(lmap)
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory()
        workdir = Path(tmp.name)
    else:
        workdir = args.workdir
        workdir.mkdir(parents=True, exist_ok=True)
    store, tifs, t_build = build(workdir, areas, args.workers)
    mpx = 0.0
    import rasterio

    for t in tifs:
        with rasterio.open(t) as ds:
            mpx += ds.width * ds.height / 1e6
    markings = list(store.iter_markings(MAP_ID))
    arrays = store.marking_arrays(MAP_ID)
    imaged = store.imaged_footprint(MAP_ID)
    store.close()
    agree = kind_agreement(markings, lmap, areas)
    print(f"{len(areas)} areas, {mpx:.0f} Mpx at 10 cm, built in {t_build:.0f} s; kinds: {agree}")
    detected = index_from_markings(arrays, CRS)
    by_imagery = index_from_markings(arrays, CRS, "imagery", imaged)
    solid = np.array([k == "solid" for k in arrays.kind])
    arrays.kind[:] = None
    unknown = index_from_markings(arrays, CRS)
    indexes = {"Lanelet2": restricted_truth(areas), "detected": detected, "detected, no kinds": unknown,
               "detected, coverage imagery": by_imagery}
    segs = {k: int((v.half_length > 0).sum()) for k, v in indexes.items()}
    print("markings indexed (line pieces matched as segments): "
          + ", ".join(f"{k} {len(v)} ({segs[k]})" for k, v in indexes.items()))
    slack = int((~solid & (detected.half_length > 0)).sum())
    print(f"detections of unknown kind cut short or run long (slack along the axis): {slack} of {int((~solid).sum())}")

    _, smap = karlsruhe(kinds=True)
    cam = Camera()
    poses = poses_in(areas, smap, cam, args.runs, args.seed)
    print(f"{len(poses)} poses in the rendered areas")
    a = argparse.Namespace(seed=args.seed)
    opts = Options()
    results = {}
    for sc in lp.SCENARIOS:
        rows = []
        for pose, scene, prior in tqdm(lp.cases(a, sc, detected, smap, cam, poses), total=len(poses),
                                       desc=sc.name, leave=False):
            row = {}
            for name, index in indexes.items():
                p = localize(index, scene.observations, prior, options=opts)
                if p.easting is None:
                    row[name] = dict(status=p.status, err=math.inf, herr=math.inf)
                else:
                    row[name] = dict(status=p.status, err=math.hypot(p.easting - pose[0], p.northing - pose[1]),
                                     herr=lp.heading_err_deg(p.yaw_grid_rad, pose[2]), probability=p.probability)
            sig = cam.range_noise_m + cam.range_noise_coeff * np.sum(scene.observations[:, :2] ** 2, 1)
            o = oracle_pose(scene, sig)
            row["oracle"] = (dict(status="failed", err=math.inf, herr=math.inf) if o is None else
                             dict(status="ok", err=math.hypot(o[0] - pose[0], o[1] - pose[1]),
                                  herr=lp.heading_err_deg(o[2], pose[2])))
            rows.append(row)
        results[sc.name] = rows
    names = list(indexes) + ["oracle"]
    lines = ["| scenario | map | success 0.5 m/1° | pose right, any status | confidently wrong "
             "| ambiguous | failed | median error (ok) |", "|---|---|---|---|---|---|---|---|"]
    cw_total = {k: 0 for k in names}
    for sc_name, rows in results.items():
        for name in names:
            r = [x[name] for x in rows]
            ok = np.array([x["status"] == "ok" for x in r])
            e = np.array([x["err"] for x in r])
            h = np.array([x["herr"] for x in r])
            good = (e <= 0.5) & (h <= 1.0)
            cw = ok & (e > 1.0)
            cw_total[name] += int(cw.sum())
            lines.append(
                f"| {sc_name} | {name} | {np.mean(ok & good):.1%} | {np.mean(good):.1%} | {np.mean(cw):.1%} "
                f"| {np.mean([x['status'] == 'ambiguous' for x in r]):.1%} "
                f"| {np.mean([x['status'] == 'failed' for x in r]):.1%} "
                f"| {np.median(e[ok]) if ok.any() else math.nan:.3f} m |")
    tab = "\n".join(lines)
    n = sum(len(r) for r in results.values())
    summary = "confidently wrong over all runs: " + ", ".join(
        f"{k} {cw_total[k]}/{n}" for k in names if k != "oracle")
    print(tab)
    print(summary)
    OUT.mkdir(parents=True, exist_ok=True)
    head = (f"{len(areas)} areas, {mpx:.0f} Mpx, built in {t_build:.0f} s; {len(poses)} poses, "
            f"seed {args.seed}\n\nkinds: {json.dumps(agree)}\n\nindexed: {json.dumps(segs)}\n\n")
    (OUT / "localize_detected.md").write_text(head + tab + "\n\n" + summary + "\n")
    (OUT / "localize_detected.json").write_text(json.dumps(
        {"areas": areas, "mpx": mpx, "build_s": t_build, "kinds": agree, "results": results}, default=float))
    biggest = int(np.argmax([(b[2] - b[0]) * (b[3] - b[1]) for b in areas]))
    overlay(OUT / "localize_detected_overlay.png", tifs[biggest], markings)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()

"""Single frames at a map's edge: the map ends ahead of the vehicle, or behind it.

The camera sees the world; the map holds only part of it. Each scene of
``localize_paper.py``'s kind (the real Karlsruhe geometry, the default
clutter) is localized with the same prior against: the whole map; the map
ending 5-25 m ahead of the vehicle (cut along a line across its heading: a
vehicle driving off the map, or a map that ends where the next begins); the
map beginning 4-20 m ahead (a vehicle driving onto the map: the nearest
markings it sees are not in it); the map beginning 0-20 m behind it (a
vehicle that has just driven onto it: everything in view is mapped); the
map less 60 m of road (80 m wide) beginning 5-25 m ahead, the markings
beyond it kept (a stretch left out of a map whose world goes on there,
inside the hull of what the map holds). Each of these by the default extent
(the markings' hull), with the localizer's defaults and without the edge
check (``Options.edge_share=None``, the behaviour before it). Then, with
the extent drawn by the markings themselves (``extent="markings"``), the
map with the stretch left out and the whole map (the Karlsruhe map is
seven separate parts, whose simulated world ends where they do); and with
the extent of a map built from imagery (the markings' extent joined to the
ground the imagery shows, as a server draws it for ``coverage: imagery``):
imagery of the whole map (its markings' bounding box and 100 m around it),
less the stretch left out where it is.

What the camera sees beyond the cut matches nothing at the true pose, while
a pose one dash period away matches it to the map's own dashes: without the
check, such a pose wins surely (status ``ok``) and wrongly.

Printed per prior and map: success (``ok`` within 0.5 m and 1°), confidently
wrong (``ok``, more than 1 m off), ambiguous, failed, and the share of the
ambiguous answers whose true position lies in the 95 % ellipse of their
``mixture_covariance``.

``--drives``: drives instead of single frames (``--frames`` frames 1.5 m apart
along the lanelets, as ``localize_track.py``'s, with its odometry noise),
streamed through :func:`localizer.track.localize_sequence` against the map
ending 15-35 m ahead of the first frame (the vehicle drives up to the edge,
and past it by the last frames) or beginning 4-20 m ahead of it (the vehicle
drives onto the map), and against the map less 60 m of road beginning 15-35 m
ahead of the first frame, by either extent. The same figures, over every
frame of every drive, and at the last frame.

Run: ``.venv/bin/python benchmarks/localize_edge.py [--runs 200] [--seed 0] [--only TEXT]``,
``.venv/bin/python benchmarks/localize_edge.py --drives [--runs 100] [--frames 12] [--seed 0] [--only TEXT]``
(``--only imagery``: only the maps whose name holds the text)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _localizer_helpers import KarlsruheMarkings, karlsruhe  # noqa: E402
from localize_track import grade as track_grade  # noqa: E402
from localize_track import noisy, prior_at  # noqa: E402

from localizer import Options, localize  # noqa: E402
from localizer.simulate import (  # noqa: E402
    Camera,
    Clutter,
    odometry,
    perturb,
    sample_poses,
    sample_trajectories,
    simulate_scene,
)
from localizer.track import Frame, localize_sequence  # noqa: E402

OUT = ROOT / "benchmarks" / "out"

#: ``(name, initial error range m, heading error ±deg, prior sigma m, prior heading sigma deg)``,
#: as the rows of ``localize_paper.py``.
PRIORS = [
    ("0.5-2m/±15°", (0.5, 2.0), 15.0, 1.0, 9.0),
    ("8-10m/±15°", (8.0, 10.0), 15.0, 6.5, 9.0),
    ("20m/±30°", (20.0, 20.0), 30.0, 14.0, 17.0),
]
MAPS = ("whole map", "ends 5-25 m ahead", "begins 4-20 m ahead", "began 0-20 m behind",
        "60 m left out 5-25 m ahead", "60 m left out 5-25 m ahead, extent by markings",
        "whole map, extent by markings", "60 m left out 5-25 m ahead, extent by imagery",
        "whole map, extent by imagery")
DRIVE_MAPS = ("ends 15-35 m ahead", "begins 4-20 m ahead", "60 m left out 15-35 m ahead",
              "60 m left out 15-35 m ahead, extent by markings", "60 m left out 15-35 m ahead, extent by imagery")
#: Maps whose extent is drawn by the markings (``extent="markings"``), or by them and the ground
#: imaged: without the check they answer as their hull's twin above, so only the check runs.
BY_MARKINGS = {m for m in MAPS + DRIVE_MAPS if m.endswith(("extent by markings", "extent by imagery"))}
#: The 95 % quantile of chi-square with 2 degrees of freedom: a position's 95 % ellipse.
CHI2_95 = 5.991
VARIANTS = {"default": None, "no edge check": Options(edge_share=None)}


def run(args) -> dict:
    whole, smap = karlsruhe()
    marks = KarlsruheMarkings()
    frame = whole.frame
    cam = Camera()
    rng = np.random.default_rng(args.seed)
    poses = sample_poses(smap, args.runs, rng, cam, min_visible=4)
    results = {p[0]: {m: {v: [] for v in VARIANTS if m not in BY_MARKINGS or VARIANTS[v] is None}
                      for m in MAPS if args.only in m} for p in PRIORS}  # fmt: skip
    whole_by_markings = marks.index(extent="markings")
    whole_by_imagery = marks.index(extent="markings", extent_area=marks.imaged())
    with tqdm(total=len(PRIORS) * len(poses), unit="scene", desc="edge scenes") as bar:
        for name, dist, heading, sigma, sigma_deg in PRIORS:
            srng = np.random.default_rng([args.seed, sum(map(ord, name))])
            for i, pose in enumerate(poses):
                scene = simulate_scene(smap, pose, srng, cam, Clutter())
                init = perturb(pose, srng.uniform(*dist), srng.uniform(-heading, heading), srng)
                prior = prior_at(frame, init, sigma, sigma_deg)
                maps = (whole, marks.cut(pose, ends_m=srng.uniform(5.0, 25.0)),
                        marks.cut(pose, begins_m=srng.uniform(4.0, 20.0)),
                        marks.cut(pose, begins_m=-srng.uniform(0.0, 20.0)))  # fmt: skip
                # its own stream, so that the rows above draw what they drew before
                gap = np.random.default_rng([args.seed, i, 60]).uniform(5.0, 25.0)
                maps += (marks.gap(pose, gap), marks.gap(pose, gap, extent="markings"), whole_by_markings,
                         marks.gap(pose, gap, extent="imagery"), whole_by_imagery)
                for map_name, index in zip(MAPS, maps):
                    if map_name not in results[name]:
                        continue
                    for variant in results[name][map_name]:
                        options = VARIANTS[variant]
                        p = localize(index, scene.observations, prior, options=options)
                        inside = listed = None
                        if p.status == "ambiguous" and p.mixture_covariance is not None:
                            d = np.array([pose[0] - p.easting, pose[1] - p.northing])
                            inside = bool(d @ np.linalg.solve(np.asarray(p.mixture_covariance)[:2, :2], d) <= CHI2_95)
                            if p.hypotheses:  # none where all lie below Options.min_hypothesis_probability
                                listed = bool(d @ np.linalg.solve(listed_mixture(p), d) <= CHI2_95)
                        results[name][map_name][variant].append(
                            {**grade(p, pose), "inside": inside, "listed": listed,
                             "edge": bool(p.reason and "map's edge" in p.reason)})
                bar.update()
    return {"poses": len(poses), "seed": args.seed, "results": results}


def listed_mixture(p) -> np.ndarray:
    """The position block of the mixture over the listed hypotheses alone (what an answer held
    back at the edge reported before the prior's uncertainty was added to it)."""
    w = np.array([h.score for h in p.hypotheses])
    w = w / w.sum()
    out = np.zeros((2, 2))
    for wi, h in zip(w, p.hypotheses):
        d = np.array([h.easting - p.easting, h.northing - p.northing])
        out += wi * (np.asarray(h.covariance)[:2, :2] + np.outer(d, d))
    return out


def grade(p, truth) -> dict:
    """Status, position error (m) and heading error (degrees) of an answer against the truth."""
    status, err, herr = track_grade(p, truth)
    return {"status": status, "err": err, "herr": herr}


def rates(rows: list[dict]) -> tuple[float, float, float, float]:
    """Shares of ``rows`` that are success (``ok`` within 0.5 m and 1°), confidently wrong
    (``ok``, more than 1 m off), ambiguous and failed."""
    n = len(rows)
    ok = [r for r in rows if r["status"] == "ok"]
    return (sum(r["err"] <= 0.5 and r["herr"] <= 1.0 for r in ok) / n, sum(r["err"] > 1.0 for r in ok) / n,
            sum(r["status"] == "ambiguous" for r in rows) / n, sum(r["status"] == "failed" for r in rows) / n)


def run_drives(args) -> dict:
    """Each drive against a map it drives off or onto, with and without the edge check."""
    whole, smap = karlsruhe()
    marks = KarlsruheMarkings()
    frame = whole.frame
    cam = Camera()
    rng = np.random.default_rng(args.seed)
    drives = sample_trajectories(smap, args.runs, args.frames, 1.5, rng, cam, min_visible=4)
    results = {p[0]: {m: {v: [] for v in VARIANTS if m not in BY_MARKINGS or VARIANTS[v] is None}
                      for m in DRIVE_MAPS if args.only in m} for p in PRIORS}  # fmt: skip
    with tqdm(total=len(PRIORS) * len(drives), unit="drive", desc="edge drives") as bar:
        for name, dist, heading, sigma, sigma_deg in PRIORS:
            srng = np.random.default_rng([args.seed, sum(map(ord, name)), 1])
            for i, drive in enumerate(drives):
                frames = []
                for k, pose in enumerate(drive):
                    motion = noisy(odometry(drive[k - 1], pose), srng) if k else (0.0, 0.0, 0.0)
                    frames.append(Frame(simulate_scene(smap, tuple(pose), srng, cam, Clutter()).observations, motion))
                init = perturb(drive[0], srng.uniform(*dist), srng.uniform(-heading, heading), srng)
                prior = prior_at(frame, init, sigma, sigma_deg)
                maps = (marks.cut(drive[0], ends_m=srng.uniform(15.0, 35.0)),
                        marks.cut(drive[0], begins_m=srng.uniform(4.0, 20.0)))
                gap = np.random.default_rng([args.seed, i, 60]).uniform(15.0, 35.0)
                maps += (marks.gap(drive[0], gap), marks.gap(drive[0], gap, extent="markings"),
                         marks.gap(drive[0], gap, extent="imagery"))
                for map_name, index in zip(DRIVE_MAPS, maps):
                    if map_name not in results[name]:
                        continue
                    for variant in results[name][map_name]:
                        options = VARIANTS[variant]
                        r = localize_sequence(index, frames, prior, options=options)
                        results[name][map_name][variant].append([grade(p, t) for p, t in zip(r.poses, drive)])
                bar.update()
    return {"drives": len(drives), "frames": args.frames, "seed": args.seed, "results": results}


def drive_table(results: dict) -> str:
    lines = ["| prior | map | variant | success, all frames | confidently wrong, all frames | ambiguous, all frames "
             "| success, last frame | confidently wrong, last frame |",
             "|---|---|---|---|---|---|---|---|"]
    for name, maps in results.items():
        for map_name, variants in maps.items():
            for variant, drives in variants.items():
                s_all, cw_all, amb_all, _ = rates([g for d in drives for g in d])
                s_last, cw_last, _, _ = rates([d[-1] for d in drives])
                lines.append(f"| {name} | {map_name} | {variant} | {s_all:.1%} | {cw_all:.1%} | {amb_all:.1%} "
                             f"| {s_last:.1%} | {cw_last:.1%} |")
    return "\n".join(lines)


def table(results: dict) -> str:
    lines = ["| prior | map | variant | success | confidently wrong | ambiguous | failed "
             "| ambiguous: truth in the 95 % ellipse of `mixture_covariance` |",
             "|---|---|---|---|---|---|---|---|"]
    for name, maps in results.items():
        for map_name, variants in maps.items():
            for variant, rows in variants.items():
                succ, cw, amb, fail = rates(rows)
                held = [r for r in rows if r.get("inside") is not None]
                at_edge = [r for r in held if r["edge"]]
                cover = f"{np.mean([r['inside'] for r in held]):.1%}" if held else "–"
                if at_edge:
                    listed = [r["listed"] for r in at_edge if r["listed"] is not None]
                    cover += (f"; held at the edge {np.mean([r['inside'] for r in at_edge]):.1%} "
                              f"({np.mean(listed):.1%} over the listed hypotheses)")
                lines.append(f"| {name} | {map_name} | {variant} | {succ:.1%} | {cw:.1%} | {amb:.1%} | {fail:.1%} "
                             f"| {cover} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="scenes (200) or drives (100) per prior")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drives", action="store_true", help="drives onto and off the map instead of single frames")
    ap.add_argument("--frames", type=int, default=12, help="frames per drive")
    ap.add_argument("--only", default="", help="only the maps whose name holds this text, e.g. 'imagery'")
    args = ap.parse_args()
    if args.drives:
        args.runs = args.runs or 100
        out = run_drives(args)
        tab, name = drive_table(out["results"]), f"localize_edge_drives_seed{args.seed}"
        print(f"{out['drives']} drives of {args.frames} frames, seed {args.seed}")
    else:
        args.runs = args.runs or 200
        out = run(args)
        tab, name = table(out["results"]), f"localize_edge_seed{args.seed}"
        print(f"{out['poses']} poses, seed {args.seed}")
    print(tab)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{name}.md").write_text(tab + "\n")
    (OUT / f"{name}.json").write_text(json.dumps(out, default=float))


if __name__ == "__main__":
    main()

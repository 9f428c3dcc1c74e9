"""How many benchmark scenes are ambiguous in the map itself (an upper bound on success).

For each scene of a ``localize_paper.py`` scenario, the default method's
refined hypotheses more than 1 m from the truth are compared with the truth by
what the camera would see there: the map's markings (point-like ones, and
solid lines sampled every 0.5 m) inside the camera's field of view, in the
vehicle frame. A hypothesis whose view differs from the true view by no sample
farther than 0.7 m is indistinguishable from the truth by any observation; only
the GPS prior can then pick, and with a 6.5 m sigma against a 9 m dash period it
cannot reach 95 %. Prints the share of scenes with such a rival (and with rivals
differing by at most 2, 4, 8 samples, i.e. 1-4 m of line), overall and among
the ``ambiguous`` answers.

With ``--ideal`` it measures the same bound another way: every scene is
observed by an exact camera (no noise, no pitch error, no missed markings,
no clutter) and scored by a default method that trusts it (temperature 1,
miss probabilities 0.001 / 0.01, 3 cm noise, 40 candidates). What such an
answer still leaves ``ambiguous`` no single frame can settle; its success
rate is an upper bound for any honest single-frame method on these scenes.

Run: ``.venv/bin/python benchmarks/localize_ambiguity.py [--scenario 3] [--runs 200] [--ideal]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from localize_paper import SCENARIOS, cases, heading_err_deg, karlsruhe, scene_poses  # noqa: E402

from localizer import Options, localize  # noqa: E402
from localizer.simulate import NONE, Camera, _in_view, _to_vehicle, simulate_scene  # noqa: E402


def map_samples(index) -> np.ndarray:
    pts = []
    for i in range(len(index)):
        h = index.half_length[i]
        if h == 0:
            pts.append(index.xy[i][None])
        else:
            t = np.arange(-h, h + 1e-9, 0.5)
            pts.append(index.xy[i] + t[:, None] * index.axis[i])
    return np.concatenate(pts)


EXACT = Camera(pitch_sigma_deg=0.0, range_noise_m=0.0, range_noise_coeff=0.0, bearing_noise_rad=0.0,
               miss_probability=0.0)
TRUSTING = Options(temperature=1.0, miss_probability=0.001, solid_miss_probability=0.01, noise_m=0.03,
                   noise_range_coeff=0.0, bearing_noise_rad=0.0, candidates=40)


def ideal_bound(args, index, smap, cam: Camera, poses) -> None:
    """Success of a trusting scorer on exact observations of the scenario's scenes and priors."""
    sc = SCENARIOS[args.scenario]
    counts = {"ok": 0, "ok but off": 0, "ambiguous": 0, "ambiguous (truth listed)": 0, "failed": 0}
    for k, (pose, _, prior) in enumerate(tqdm(cases(args, sc, index, smap, cam, poses), total=len(poses),
                                             desc=sc.name, leave=False)):
        scene = simulate_scene(smap, pose, np.random.default_rng([args.seed, k]), EXACT, NONE)
        p = localize(index, scene.observations, prior, options=TRUSTING)
        if p.status == "failed":
            counts["failed"] += 1
            continue
        e = math.hypot(p.easting - pose[0], p.northing - pose[1])
        h = heading_err_deg(p.yaw_grid_rad, pose[2])
        if p.status == "ok":
            counts["ok" if e <= 0.5 and h <= 1.0 else "ok but off"] += 1
        else:
            counts["ambiguous"] += 1
            counts["ambiguous (truth listed)"] += any(
                math.hypot(hy.easting - pose[0], hy.northing - pose[1]) <= 0.5 for hy in p.hypotheses)
    n = len(poses)
    print(f"{sc.name}, seed {args.seed}, {n} scenes, exact observations, trusting scorer")
    print("| answer | share of scenes |")
    print("|---|---|")
    for name, c in counts.items():
        print(f"| {name} | {c / n:.1%} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", type=int, default=3, help="index into localize_paper.SCENARIOS")
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--intersections", action="store_true")
    ap.add_argument("--ideal", action="store_true",
                    help="exact observations and a scorer that trusts them: the bound as a success rate")
    args = ap.parse_args()
    index, smap = karlsruhe()
    cam = Camera()
    poses = scene_poses(args, smap, cam)
    if args.ideal:
        ideal_bound(args, index, smap, cam, poses)
        return
    pts = map_samples(index)

    def view(pose):
        v = _to_vehicle(pose, pts)
        return v[_in_view(v, cam)]

    sc = SCENARIOS[args.scenario]
    status, diff = [], []
    for pose, scene, prior in tqdm(cases(args, sc, index, smap, cam, poses), total=len(poses),
                                  desc=sc.name, leave=False):
        p = localize(index, scene.observations, prior, options=Options(record_candidates=True))
        truth = view(pose)
        best = math.inf
        for cd in p.diagnostics.get("candidates", []):
            q = cd["pose"]
            if math.hypot(q[0] - pose[0], q[1] - pose[1]) < 1.0 or not len(truth):
                continue
            other = view(q)
            if not len(other):
                continue
            d = int((cKDTree(truth).query(other)[0] > 0.7).sum()
                    + (cKDTree(other).query(truth)[0] > 0.7).sum())
            best = min(best, d)
        status.append(p.status)
        diff.append(best)
    status, diff = np.array(status), np.array(diff)
    amb = status == "ambiguous"
    print(f"{sc.name}, seed {args.seed}, {len(status)} scenes, {amb.sum()} answered ambiguous")
    print("| rival's view differs from the truth's by | share of scenes | share of ambiguous answers |")
    print("|---|---|---|")
    for k in (0, 2, 4, 8):
        print(f"| ≤ {k} samples ({k * 0.5:g} m of line) | {np.mean(diff <= k):.1%} | "
              f"{np.mean(diff[amb] <= k) if amb.any() else math.nan:.1%} |")


if __name__ == "__main__":
    main()

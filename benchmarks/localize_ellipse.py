"""What a GPS fix's error ellipse is worth against a single sigma, on simulated Karlsruhe scenes.

GNSS errors are rarely round: in a street canyon the satellites in view line
up along the street and the fix is worst across it; a receiver with lane-level
corrections, or a fix carried by odometry with a good heading, is sure across
the road and not along it. Receivers report the ellipse (NMEA GST); a client
that sends only ``position_sigma_m`` must choose one number. On the same
scenes (``localize_paper.py``'s camera and paper-like clutter), GPS errors are
drawn from an ellipse aligned with the road, and the default method is given:

* ``ellipse``: that ellipse (``Prior.position_ellipse``);
* ``circle, major``: one sigma, the ellipse's major axis (safe, says less);
* ``circle, rms``: one sigma, the root mean square of the two axes (what
  ``position_sigma_m``, per axis, would hold of a receiver's total error;
  too sure along the major axis).

Success: status ``ok`` within 0.5 m and 1°; confidently wrong: ``ok`` more
than 1 m off; pose right: the answer's pose within 0.5 m and 1° whatever its
status.

Run: ``.venv/bin/python benchmarks/localize_ellipse.py [--runs 200] [--seed 0]``
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _localizer_helpers import karlsruhe  # noqa: E402
from localize_track import grade  # noqa: E402

from localizer import ErrorEllipse, Prior, localize  # noqa: E402
from localizer.simulate import Camera, Clutter, sample_poses, simulate_scene  # noqa: E402

# name, sigma along the road (m), sigma across it (m), heading sigma (deg)
SHAPES = [
    ("street canyon: 1.5 m along, 6 m across", 1.5, 6.0, 5.0),
    ("lane-level: 6 m along, 0.5 m across", 6.0, 0.5, 5.0),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    index, smap = karlsruhe()
    frame = index.frame
    cam = Camera()
    poses = sample_poses(smap, args.runs, np.random.default_rng(args.seed), cam, min_visible=4)
    print(f"{len(poses)} scenes, seed {args.seed}, paper-like clutter; GPS error drawn from the ellipse")
    print("| GPS error | prior sent | success 0.5 m/1° | confidently wrong | ambiguous | pose right | ms p50 |")
    print("|---|---|---|---|---|---|---|")
    for name, along, across, hdg in SHAPES:
        rng = np.random.default_rng([args.seed, sum(map(ord, name))])
        results: dict[str, list] = {"ellipse": [], "circle, major": [], "circle, rms": []}
        times: dict[str, list] = {k: [] for k in results}
        for pose in tqdm(poses, desc=name[:14], leave=False):
            scene = simulate_scene(smap, tuple(pose), rng, cam, Clutter())
            c, s = math.cos(pose[2]), math.sin(pose[2])
            e_along, e_across = rng.normal(0, along), rng.normal(0, across)
            x, y = pose[0] + c * e_along - s * e_across, pose[1] + s * e_along + c * e_across
            lon, lat = frame.to_lonlat(x, y)
            heading = float(frame.grid_yaw_to_heading(pose[2] + math.radians(rng.normal(0, hdg)), lon, lat))
            road = float(frame.grid_yaw_to_heading(pose[2], lon, lat))
            major, minor = max(along, across), min(along, across)
            base = Prior(lat=lat, lon=lon, heading_deg=heading % 360.0, heading_sigma_deg=hdg)
            priors = {
                "ellipse": replace(base, position_ellipse=ErrorEllipse(
                    major, minor, (road if along >= across else road + 90.0) % 360.0)),
                "circle, major": replace(base, position_sigma_m=major),
                "circle, rms": replace(base, position_sigma_m=math.sqrt((along**2 + across**2) / 2)),
            }
            for key, prior in priors.items():
                t0 = time.process_time()
                r = localize(index, scene.observations, prior)
                times[key].append(1000 * (time.process_time() - t0))
                results[key].append(grade(r, pose))
        for key, res in results.items():
            st = np.array([r[0] for r in res])
            e = np.array([r[1] for r in res])
            h = np.array([r[2] for r in res])
            right = (e <= 0.5) & (h <= 1.0)
            print(f"| {name} | {key} | {np.mean((st == 'ok') & right):.1%} | {np.mean((st == 'ok') & (e > 1.0)):.1%} | "
                  f"{np.mean(st == 'ambiguous'):.1%} | {np.mean(right):.1%} | {np.median(times[key]):.1f} |")


if __name__ == "__main__":
    main()

"""Calibrate the default method's temperature, ambiguity threshold and covariance scale.

Runs the scenarios of ``localize_paper.py`` once, keeps every scored
hypothesis, and re-evaluates the posterior with other temperatures offline:
the chosen temperature is the smallest whose confidently-wrong rate (status ok,
error > 1 m) stays ≤ 0.5% over all scenarios. Also prints the coverage of the
95% covariance ellipse as a function of an inflation factor.

Run: ``.venv/bin/python benchmarks/localize_calibrate.py [--runs 150]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from localize_paper import SCENARIOS, cases, karlsruhe, scene_poses  # noqa: E402

from localizer import Options, localize  # noqa: E402
from localizer.simulate import Camera  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=150)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--intersections", action="store_true")
    args = ap.parse_args()
    index, smap = karlsruhe()
    cam = Camera()
    poses = scene_poses(args, smap, cam)
    opts = Options()
    T0 = opts.temperature
    runs = []
    for sc in SCENARIOS:
        for pose, scene, prior in tqdm(cases(args, sc, index, smap, cam, poses), total=len(poses),
                                      desc=sc.name, leave=False):
            p = localize(index, scene.observations, prior, options=opts)
            cands = p.diagnostics.get("candidates", [])
            errs = [math.hypot(c["pose"][0] - pose[0], c["pose"][1] - pose[1]) for c in cands]
            data = np.array([(c["score"] - c["prior"]) * T0 for c in cands])
            pri = np.array([c["prior"] for c in cands])
            maha = math.inf
            if p.covariance is not None and p.easting is not None:
                dx = np.array([p.easting - pose[0], p.northing - pose[1]])
                maha = float(dx @ np.linalg.solve(p.covariance[:2, :2], dx))
            runs.append(dict(scn=sc.name, failed=p.status == "failed", errs=np.array(errs),
                             data=data, prior=pri, maha=maha,
                             err=errs[0] if errs else math.inf))
    print("T     thr   conf.wrong  ambiguous  ok&right")
    for T in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0):
        for thr in (0.9, 0.95, 0.99):
            cw = amb = good = 0
            for r in runs:
                if r["failed"] or not len(r["data"]):
                    continue
                s = r["data"] / T + r["prior"]
                b = int(np.argmax(s))
                pr = np.exp(s - s.max())
                pr /= pr.sum()
                if pr[b] >= thr:
                    if r["errs"][b] > 1.0:
                        cw += 1
                    elif r["errs"][b] <= 0.5:
                        good += 1
                else:
                    amb += 1
            n = len(runs)
            print(f"{T:4.1f}  {thr:.2f}  {cw / n:9.2%}  {amb / n:9.2%}  {good / n:8.2%}")
    print(f"per scenario at T={T0}, threshold {opts.ambiguity_probability}: "
          "confidently wrong (truth among candidates or not) / ambiguous")
    for sc in SCENARIOS:
        rs = [r for r in runs if r["scn"] == sc.name and not r["failed"] and len(r["data"])]
        cw_in = cw_out = amb = 0
        for r in rs:
            s = r["data"] / T0 + r["prior"]
            pr = np.exp(s - s.max())
            pr /= pr.sum()
            b = int(np.argmax(s))
            if pr[b] < opts.ambiguity_probability:
                amb += 1
            elif r["errs"][b] > 1.0:
                if (r["errs"] < 0.5).any():
                    cw_in += 1
                else:
                    cw_out += 1
        print(f"  {sc.name:22s} {cw_in:3d} {cw_out:3d} / {amb:3d} of {len(runs) // len(SCENARIOS)}")
    maha = np.array([r["maha"] for r in runs if not r["failed"] and r["err"] <= 1.0])
    for k in (1.0, 1.5, 2.0, 3.0, 4.0):
        print(f"inflation {k}: 95% ellipse coverage {np.mean(maha / k <= 5.991):.1%}, "
              f"2-sigma {np.mean(maha / k <= 4.0):.1%}")


if __name__ == "__main__":
    main()

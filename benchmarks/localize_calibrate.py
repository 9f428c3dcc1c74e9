"""Calibrate the default method's hypothesis scoring on scenes of another seed.

Runs the scenarios of ``localize_paper.py`` (seed 7 by default, so the
benchmark's seed 0 stays unseen), keeps every scored hypothesis with its parts
(positive evidence, missed point markings, missed solid-line clusters, prior)
and re-evaluates the posterior offline for other miss probabilities,
temperatures and ``ok`` thresholds. Prints, per setting, the confidently-wrong
rate (status ok, error > 1 m) over all scenarios, and success / ambiguous rates
from 0.5-2 m and from 8-10 m, plus the coverage of the 95 % covariance ellipse
as a function of an inflation factor, and the log-loss of the answers'
probability (lower: sharper and more honest). Choose the setting with the
lowest log-loss whose confidently-wrong rate stays well under 1 % (the
miss probabilities 0.3 were chosen so on seeds 3, 5, 7 and 11, all poses and
intersections, on 2026-12-03, with a temperature of 1.35; the temperature
was re-fitted to 1.0 on 2026-12-05 on the same seeds after observations that
crowd together came to share their weight). A second table scales the
"none of these" score with the prior's volume (an Occam factor: a chance
match is likelier inside a wider prior), at several reference priors; on
2026-12-07 that made the log-loss worse on seeds 3, 5, 7 and 11 and at
their intersections, so the score stays the same for every prior.

Run: ``.venv/bin/python benchmarks/localize_calibrate.py [--runs 120] [--seed 7] [--intersections] [--save F]``;
``--load F1 F2 ...`` evaluates several saved seeds together.
"""

from __future__ import annotations

import argparse
import itertools
import math
import pickle
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from localize_paper import SCENARIOS, cases, heading_err_deg, karlsruhe, scene_poses  # noqa: E402

from localizer import Options, localize  # noqa: E402
from localizer.simulate import Camera  # noqa: E402


def collect(args, opts: Options) -> list[dict]:
    index, smap = karlsruhe()
    cam = Camera()
    poses = scene_poses(args, smap, cam)
    runs = []
    for sc in SCENARIOS:
        for pose, scene, prior in tqdm(cases(args, sc, index, smap, cam, poses), total=len(poses),
                                      desc=sc.name, leave=False):
            p = localize(index, scene.observations, prior, options=opts)
            cands = p.diagnostics.get("candidates", [])
            maha = math.inf
            if p.covariance is not None and p.easting is not None:
                dx = np.array([p.easting - pose[0], p.northing - pose[1]])
                maha = float(dx @ np.linalg.solve(p.covariance[:2, :2], dx))
            runs.append(dict(
                scn=sc.name, failed=p.status == "failed", maha=maha,
                log_volume=prior_log_volume(sc.sigma_m, sc.sigma_deg),
                err=np.array([math.hypot(c["pose"][0] - pose[0], c["pose"][1] - pose[1]) for c in cands]),
                herr=np.array([heading_err_deg(c["pose"][2], pose[2]) for c in cands]),
                pos=np.array([c["positive"] for c in cands]),
                npt=np.array([c["missed_points"] for c in cands]),
                nsol=np.array([c["missed_solid"] for c in cands]),
                prior=np.array([c["prior"] for c in cands]),
            ))
    return runs


def prior_log_volume(sigma_m: float, sigma_deg: float) -> float:
    """Log of the prior's 1-sigma volume, m² rad (an isotropic position)."""
    return math.log(sigma_m**2 * math.radians(sigma_deg))


def evaluate(runs, mp: float, ms: float, T: float, thr: float, null: float = 0.0,
             null_reference: float | None = None) -> dict:
    """Confidently wrong, near / far success and ambiguity, and the log-loss of the answers' probability.

    The log-loss (mean ``-log p`` of the answer being right within 1 m / 2°,
    ``-log(1 - p)`` when it is not) is a proper score: it is lowest for
    probabilities that are both sharp and honest.
    """
    out = {"cw": 0, "near": [0, 0, 0], "far": [0, 0, 0], "logloss": 0.0, "scored": 0}
    for r in runs:
        if r["failed"] or not len(r["pos"]):
            continue
        data = r["pos"] - r["npt"] * math.log(1 / mp) - r["nsol"] * math.log(1 / ms)
        s = data / T + r["prior"]
        b = int(np.argmax(s))
        nl = null if null_reference is None else null + r["log_volume"] - null_reference
        top = max(s.max(), nl)
        pr = np.exp(s - top)
        pr /= pr.sum() + math.exp(nl - top)
        ok = pr[b] >= thr
        if ok and r["err"][b] > 1.0:
            out["cw"] += 1
        right = r["err"][b] <= 1.0 and r["herr"][b] <= 2.0
        p = min(max(float(pr[b]), 1e-6), 1 - 1e-6)
        out["logloss"] -= math.log(p if right else 1 - p)
        out["scored"] += 1
        group = "near" if r["scn"].startswith("0.5-2m") else "far" if r["scn"].startswith("8-10m") else None
        if group:
            out[group][2] += 1
            if ok and r["err"][b] <= 0.5 and r["herr"][b] <= 1.0:
                out[group][0] += 1
            elif not ok:
                out[group][1] += 1
    return out


def outcome(e: dict, n: int) -> str:
    """A table row's results: confidently wrong, near and far ok / ambiguous, log-loss."""
    nr, fr = e["near"], e["far"]
    return (f"{e['cw'] / n:9.2%}  {nr[0] / max(nr[2], 1):6.1%} / {nr[1] / max(nr[2], 1):5.1%}  "
            f"{fr[0] / max(fr[2], 1):6.1%} / {fr[1] / max(fr[2], 1):5.1%}  "
            f"{e['logloss'] / max(e['scored'], 1):8.4f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=120)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--intersections", action="store_true")
    ap.add_argument("--save", type=Path, help="pickle the collected runs to this file")
    ap.add_argument("--load", type=Path, nargs="+",
                    help="evaluate runs pickled by --save (e.g. several seeds together) instead of collecting")
    args = ap.parse_args()
    opts = Options(record_candidates=True)
    if args.load:
        runs = [r for path in args.load for r in pickle.loads(path.read_bytes())]
        what = f"loaded from {len(args.load)} file(s)"
    else:
        runs = collect(args, opts)
        what = f"seed {args.seed}" + (", intersections" if args.intersections else "")
        if args.save:
            args.save.write_bytes(pickle.dumps(runs))
    n = len(runs)
    print(f"{n} runs, {what}; near: 0.5-2 m/±15° (+heavy), far: 8-10 m/±15° (+heavy)")
    print(f"ok threshold {opts.ambiguity_probability}")
    print("p_miss  p_miss_solid  T     null   conf.wrong  near ok / amb   far ok / amb   log-loss")
    rows = []
    for mp, ms, T, null in itertools.product((0.1, 0.2, 0.3), (0.1, 0.2, 0.3), (0.9, 1.0, 1.1, 1.25, 1.35, 1.5),
                                            (0.0, -1.0, -2.0, -3.0, -math.inf)):
        e = evaluate(runs, mp, ms, T, opts.ambiguity_probability, null)
        rows.append((mp, ms, T, null, e))
    for mp, ms, T, null, e in rows:
        mark = " <- current" if (mp, ms, T, null) == (opts.miss_probability, opts.solid_miss_probability,
                                                     opts.temperature, opts.null_score) else ""
        print(f"{mp:6.2f}  {ms:12.2f}  {T:4.2f}  {null:5.1f}  {outcome(e, n)}{mark}")
    print("\nthe none-of-these score scaled with the prior's volume (sigma_m, sigma_deg of the reference prior"
          " at which it is `null`), current miss probabilities and temperature:")
    print("reference       null   conf.wrong  near ok / amb   far ok / amb   log-loss")
    for ref, null in itertools.product((None, (1.0, 9.0), (5.0, 10.0), (6.5, 9.0), (14.0, 17.0)),
                                       (0.0, -1.0, -2.0, -3.0)):
        e = evaluate(runs, opts.miss_probability, opts.solid_miss_probability, opts.temperature,
                     opts.ambiguity_probability, null, None if ref is None else prior_log_volume(*ref))
        print(f"{'off' if ref is None else f'{ref[0]:g} m, {ref[1]:g}°':12s}  {null:5.1f}  {outcome(e, n)}")
    print("\nok threshold (min_probability) at the current scoring: confidently wrong, near / far success")
    cur = (opts.miss_probability, opts.solid_miss_probability, opts.temperature, opts.null_score)
    for thr in (0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 0.98):
        e = evaluate(runs, *cur[:3], thr, cur[3])
        nr, fr = e["near"], e["far"]
        print(f"  {thr:4.2f}: {e['cw']:4d} ({e['cw'] / n:6.2%})  near {nr[0] / max(nr[2], 1):6.1%}  "
              f"far {fr[0] / max(fr[2], 1):6.1%}")
    maha = np.array([r["maha"] for r in runs if not r["failed"] and len(r["err"]) and r["err"][0] <= 1.0])
    for k in (1.0, 1.5, 2.0):
        print(f"inflation {k}: 95% ellipse coverage {np.mean(maha / k <= 5.991):.1%}, "
              f"2-sigma {np.mean(maha / k <= 4.0):.1%}")


if __name__ == "__main__":
    main()

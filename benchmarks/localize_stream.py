"""A long drive streamed frame by frame, against a window of frames resent with every request.

A vehicle asking for its pose at every frame can either resend the last
``--window`` frames with every request (the filter then restarts from the GPS
fix at the window's first frame: each request costs ``window`` frames of
localization and forgets what came before), or send each frame once with the
``state`` of the previous answer (:class:`localizer.TrackState`: each request
costs one frame and the filter remembers the whole drive). Both clients run
here on the same drives of ``--frames`` frames ``--step`` metres apart along
Karlsruhe centrelines, with the scenes, odometry noise and GPS errors of
``localize_track.py``; the GPS fix is the first frame's, carried along by the
odometry (the windowed client starts each window from it, carried as the
filter carries its own, :func:`localizer.carry_prior`, as
``localize_track.py``'s single frames).

Printed per client: CPU time per request (p50 / p99), the success rate (``ok``
within 0.5 m / 1°) and confidently wrong rate (``ok``, more than 1 m off) over
all frames from the ``--window``-th on, and at the last frame. Also checks
that the streamed poses equal those of one call over all frames, and plots
the success after each frame (``benchmarks/out/localize_stream.png``).

Run: ``.venv/bin/python benchmarks/localize_stream.py [--runs 50] [--frames 40] [--window 10] [--seed 0]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _localizer_helpers import karlsruhe  # noqa: E402
from localize_track import SCENARIOS, carried_prior, grade, noisy, plot_success, prior_at  # noqa: E402

from localizer.simulate import Camera, odometry, perturb, sample_trajectories, simulate_scene  # noqa: E402
from localizer.track import Frame, localize_sequence  # noqa: E402

OUT = ROOT / "benchmarks" / "out"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--step", type=float, default=1.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="8-10m/±15°", help="the scenarios whose name contains this")
    args = ap.parse_args()
    index, smap = karlsruhe()
    cam = Camera()
    drives = sample_trajectories(smap, args.runs, args.frames, args.step, np.random.default_rng(args.seed), cam,
                                 min_visible=4)  # fmt: skip
    rows, curves, mismatches = [], {}, 0
    for name, dist, hdg, sig_m, sig_deg, clutter in SCENARIOS:
        if args.only not in name:
            continue
        rng = np.random.default_rng([args.seed, sum(map(ord, name))])
        graded = {"streamed": [], f"window of {args.window}": []}
        cpu = {k: [] for k in graded}
        for drive in tqdm(drives, desc=name, leave=False):
            scenes = [simulate_scene(smap, tuple(p), rng, cam, clutter) for p in drive]
            motions = [(0.0, 0.0, 0.0)] + [noisy(odometry(drive[k - 1], drive[k]), rng)
                                           for k in range(1, len(drive))]  # fmt: skip
            frames = [Frame(s.observations, m) for s, m in zip(scenes, motions)]
            start = perturb(drive[0], rng.uniform(*dist), rng.uniform(-hdg, hdg), rng)
            prior = prior_at(index.frame, start, sig_m, sig_deg)
            state, streamed, windowed = None, [], []
            for k, frame in enumerate(frames):
                t0 = time.process_time()
                part = localize_sequence(index, [frame], prior if state is None else None, state=state)
                cpu["streamed"].append(1000 * (time.process_time() - t0))
                state = part.state
                streamed.append(part.pose)
                a = max(0, k + 1 - args.window)
                window = [Frame(frames[a].observations)] + frames[a + 1:k + 1]
                t0 = time.process_time()
                r = localize_sequence(index, window, carried_prior(index, start, motions[1:a + 1],
                                                                   sig_m, sig_deg))  # fmt: skip
                cpu[f"window of {args.window}"].append(1000 * (time.process_time() - t0))
                windowed.append(r.pose)
            whole = localize_sequence(index, frames, prior).poses
            mismatches += [p.to_dict() for p in streamed] != [p.to_dict() for p in whole]
            graded["streamed"].append([grade(p, t) for p, t in zip(streamed, drive)])
            graded[f"window of {args.window}"].append([grade(p, t) for p, t in zip(windowed, drive)])
        for client, runs in graded.items():
            st = np.array([[g[0] for g in run] for run in runs])
            e = np.array([[g[1] for g in run] for run in runs])
            h = np.array([[g[2] for g in run] for run in runs])
            good = (st == "ok") & (e <= 0.5) & (h <= 1.0)
            wrong = (st == "ok") & (e > 1.0)
            curves[f"{name}, {client}"] = good.mean(axis=0)
            late = slice(args.window - 1, None)
            c = np.array(cpu[client])
            rows.append(f"| {name} | {client} | {np.median(c):.1f} / {np.percentile(c, 99):.1f} | "
                        f"{good[:, late].mean():.1%} | {wrong[:, late].mean():.2%} | {good[:, -1].mean():.1%} | "
                        f"{wrong[:, -1].mean():.1%} |")  # fmt: skip
    print(f"{len(drives)} drives of {args.frames} frames, {args.step} m apart, seed {args.seed}; "
          f"streamed poses equal to one call's in {len(drives) * len(curves) // 2 - mismatches} of "
          f"{len(drives) * len(curves) // 2} drives")  # fmt: skip
    print(f"| scenario | client | CPU ms per request p50 / p99 | success, frames {args.window}–{args.frames} "
          f"| confidently wrong, frames {args.window}–{args.frames} | success, last frame "
          "| confidently wrong, last frame |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))

    png = OUT / "localize_stream.png"
    plot_success(curves, args.step, "a drive streamed with its state, against a window resent per request", png,
                 ms=3)
    print(f"plot: {png}")

if __name__ == "__main__":
    main()

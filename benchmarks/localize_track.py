"""Localization over a drive: the multi-hypothesis filter against one frame at a time.

Drives of ``--frames`` frames ``--step`` metres apart (1.5 m: 10 Hz at 54 km/h)
follow lanelet centrelines of the Karlsruhe map; each frame is a camera scene
of ``localizer/simulate.py`` with paper-like clutter, and the odometry between
frames has noise (2 % of the distance along, 1 % across, 0.1° per frame). The
GPS fix of the first frame is off by the scenario's initial error and carries
the sigmas of ``localize_paper.py``.

Compared at the last frame, on the same scenes:

* ``single frame``: :func:`localizer.localize` on the last frame alone, with
  the first frame's GPS fix carried to it by the same noisy odometry (the same
  information about GPS as the filter has);
* ``sequence``: :func:`localizer.track.localize_sequence` over all frames;
* ``oracle``: weighted least squares on the last frame's true inliers (the
  single-frame noise floor of ``localize_paper.py``).

Success: status ``ok`` within 0.5 m and 1°; confidently wrong: ``ok`` off by
more than 1 m. Also the success rate after each frame (a PNG), the time per
frame, and the log-loss of the sequence's probability over frames 2 to the
last (the answer right within 1 m and 2°; ``--evidence-scale`` sets
:attr:`localizer.track.TrackOptions.evidence_scale`, chosen by it on seed 7).

Run: ``.venv/bin/python benchmarks/localize_track.py [--runs 200] [--frames 10] [--seed 0] [--only 8-10m --tag _20]
[--evidence-scale 6] [--set NAME=VALUE ...] [--track-set NAME=VALUE ...]``. ``--set`` changes a field
of the ``localizer.Options`` both the single frame and the sequence run with, ``--track-set`` one of
``TrackOptions`` (as ``localize_paper.py --set``; give such runs a ``--tag``). Every drive's grades
at the last frame are written to ``benchmarks/out/localize_track{TAG}.json``, to compare two runs
drive by drive.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _localizer_helpers import karlsruhe  # noqa: E402
from localize_paper import field_value  # noqa: E402

from localizer import Options, Prior, carry_prior, localize  # noqa: E402
from localizer.simulate import (  # noqa: E402
    HEAVY,
    Camera,
    Clutter,
    odometry,
    oracle_pose,
    perturb,
    sample_trajectories,
    simulate_scene,
)
from localizer.track import Frame, TrackOptions, localize_sequence  # noqa: E402

OUT = ROOT / "benchmarks" / "out"

# name, initial distance (m), heading (±deg), prior sigma m, prior sigma deg, clutter
SCENARIOS = [
    ("0.5-2m/±15°", (0.5, 2.0), 15.0, 1.0, 9.0, Clutter()),
    ("8-10m/±15°", (8.0, 10.0), 15.0, 6.5, 9.0, Clutter()),
    ("20m/±30°", (20.0, 20.0), 30.0, 14.0, 17.0, Clutter()),
    ("8-10m/±15° heavy", (8.0, 10.0), 15.0, 6.5, 9.0, HEAVY),
]


def heading_err_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


def noisy(motion, rng) -> tuple[float, float, float]:
    dx, dy, dyaw = motion
    d = math.hypot(dx, dy)
    return (dx + rng.normal(0, 0.02 * d), dy + rng.normal(0, 0.01 * d), dyaw + math.radians(rng.normal(0, 0.1)))


def carried_prior(index, start, motions, sig_m: float, sig_deg: float) -> Prior:
    """The GPS fix at ``start`` carried by ``motions``, as a single frame's prior.

    :func:`localizer.carry_prior`, as the filter carries its fix: a heading
    error of ``sig_deg`` moves the fix across the road by the distance driven
    times the error, so its error ellipse grows across the road only.
    """
    return carry_prior(index, prior_at(index.frame, start, sig_m, sig_deg), motions)


def log_loss_term(p: float, right: bool) -> float:
    """``-log`` of the probability given to what happened (``p`` clipped to [1e-6, 1 - 1e-6])."""
    p = min(max(p, 1e-6), 1 - 1e-6)
    return -math.log(p if right else 1 - p)


def finite(x: float) -> float | None:
    """``x`` as JSON allows it: ``None`` where there is no pose to grade."""
    return float(x) if math.isfinite(x) else None


def grade(p, truth) -> tuple[str, float, float]:
    if p.easting is None:
        return p.status, math.inf, math.inf
    return p.status, math.hypot(p.easting - truth[0], p.northing - truth[1]), heading_err_deg(p.yaw_grid_rad, truth[2])


def prior_at(frame, pose, sig_m, sig_deg) -> Prior:
    lon, lat = frame.to_lonlat(pose[0], pose[1])
    return Prior(lat=lat, lon=lon, heading_deg=float(frame.grid_yaw_to_heading(pose[2], lon, lat)) % 360,
                 position_sigma_m=sig_m, heading_sigma_deg=sig_deg)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--step", type=float, default=1.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="run only the scenarios whose name contains this")
    ap.add_argument("--tag", default="", help="suffix of the plot's file name")
    ap.add_argument("--evidence-scale", type=float, default=TrackOptions().evidence_scale,
                    help="TrackOptions.evidence_scale of the sequence")
    ap.add_argument("--set", action="append", type=field_value(Options), metavar="NAME=VALUE", default=[],
                    help="a localizer.Options field for every frame, its value as JSON (repeatable)")
    ap.add_argument("--track-set", action="append", type=field_value(TrackOptions), metavar="NAME=VALUE",
                    default=[], help="a TrackOptions field, its value as JSON (repeatable)")
    args = ap.parse_args()
    index, smap = karlsruhe()
    cam = Camera()
    drives = sample_trajectories(smap, args.runs, args.frames, args.step, np.random.default_rng(args.seed), cam,
                                 min_visible=4)
    opts = Options(**dict(args.set))
    topt = TrackOptions(**{"evidence_scale": args.evidence_scale, **dict(args.track_set)})
    rows, curves, log_loss, per_drive = [], {}, [], {}
    for name, dist, hdg, sig_m, sig_deg, clutter in SCENARIOS:
        if args.only not in name:
            continue
        rng = np.random.default_rng([args.seed, sum(map(ord, name))])
        single, seq, oracle, per_frame, ms = [], [], [], np.zeros(args.frames), []
        for drive in tqdm(drives, desc=name, leave=False):
            scenes = [simulate_scene(smap, tuple(p), rng, cam, clutter) for p in drive]
            motions = [(0.0, 0.0, 0.0)] + [noisy(odometry(drive[k - 1], drive[k]), rng)
                                           for k in range(1, len(drive))]
            start = perturb(drive[0], rng.uniform(*dist), rng.uniform(-hdg, hdg), rng)
            prior = prior_at(index.frame, start, sig_m, sig_deg)
            last_prior = carried_prior(index, start, motions[1:], sig_m, sig_deg)
            single.append(grade(localize(index, scenes[-1].observations, last_prior, options=opts), drive[-1]))
            last = scenes[-1]
            o = oracle_pose(last, cam.range_noise_m + cam.range_noise_coeff * np.sum(last.observations[:, :2] ** 2, 1))
            oracle.append(("failed", math.inf, math.inf) if o is None else
                          ("ok", math.hypot(o[0] - drive[-1][0], o[1] - drive[-1][1]), heading_err_deg(o[2], drive[-1][2])))
            t0 = time.perf_counter()
            r = localize_sequence(index, [Frame(s.observations, m) for s, m in zip(scenes, motions)], prior,
                                  options=opts, track_options=topt)
            ms.append(1000 * (time.perf_counter() - t0) / len(drive))
            seq.append(grade(r.pose, drive[-1]))
            for k, p in enumerate(r.poses):
                st, e, h = grade(p, drive[k])
                per_frame[k] += st == "ok" and e <= 0.5 and h <= 1.0
                if k > 0 and p.probability is not None:
                    log_loss.append(log_loss_term(p.probability, e <= 1.0 and h <= 2.0))
        curves[name] = per_frame / len(drives)
        per_drive[name] = {"single frame": single, "sequence": seq, "oracle": oracle}
        for method, res in (("oracle", oracle), ("single frame", single), ("sequence", seq)):
            st = np.array([r[0] for r in res])
            e = np.array([r[1] for r in res])
            h = np.array([r[2] for r in res])
            ok = st == "ok"
            rows.append(f"| {name} | {method} | {np.mean(ok & (e <= 0.5) & (h <= 1)):.1%} | "
                        f"{np.mean(ok & (e > 1.0)):.1%} | {np.mean(st == 'ambiguous'):.1%} | "
                        f"{np.mean(st == 'failed'):.1%} | "
                        + (f"{np.median(ms):.1f} / {np.percentile(ms, 99):.1f}" if method == "sequence" else "–")
                        + " |")
    print(f"{len(drives)} drives of {args.frames} frames, {args.step} m apart, seed {args.seed}")
    print("| scenario | method | success 0.5 m/1° | confidently wrong | ambiguous | failed | ms per frame p50 / p99 |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print(f"sequence, frames 2-{args.frames}: log-loss of the answer's probability (right within 1 m / 2°) "
          f"{np.mean(log_loss):.4f} over {len(log_loss)} answers (evidence_scale {args.evidence_scale:g})")

    png = OUT / f"localize_track{args.tag}.png"
    plot_success(curves, args.step, "localize_sequence: success after each frame", png)
    print(f"plot: {png}")
    grades = OUT / f"localize_track{args.tag}.json"
    grades.write_text(json.dumps(
        {"seed": args.seed, "frames": args.frames, "options": dict(args.set), "track_options": dict(args.track_set),
         "drives": {name: {method: [{"status": st, "error_m": finite(e), "heading_error_deg": finite(h)}
                                    for st, e, h in res]
                           for method, res in methods.items()} for name, methods in per_drive.items()}},
        indent=1, ensure_ascii=False))
    print(f"per-drive grades: {grades}")


def plot_success(curves: dict, step: float, title: str, png: Path, **style) -> None:
    """Success after each frame (one line per entry of ``curves``), saved to ``png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    png.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, c in curves.items():
        ax.plot(np.arange(1, len(c) + 1), 100 * c, marker="o", label=name, **style)
    ax.set_xlabel(f"frame ({step} m apart)")
    ax.set_ylabel("success 0.5 m / 1° [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)

if __name__ == "__main__":
    main()

"""Reproduce Pink (2008)'s convergence experiments on simulated Karlsruhe scenes.

Both methods (the paper's ``pink2008`` and the ``default`` global + robust
method) run on the same scenes and initial errors, next to an oracle (weighted
least squares on the true inliers with their true map positions, observations
of solid lines constraining only the distance across the line: the noise
floor). *Success* is status ``ok`` within the tolerance; "pose 0.5m/1°, any
status" counts the answer's pose whatever its status (the paper's method and
the oracle have none). "ambiguous (truth listed)": how often an ambiguous
answer lists a hypothesis within 0.5 m of the truth. The map is indexed with
its markings' kinds, as the service does after a Lanelet2 import;
``--no-kinds`` leaves them out, as for a map detected from imagery (the
index then infers solid-line pieces from their geometry). Prints a table per
scenario and saves error-versus-iteration plots
like the paper's Fig. 8/9 under ``benchmarks/out/``; then, pooled over the
scenarios, how often the default method's answers of each posterior
probability (``Pose.probability``) are right, as a table and a reliability
diagram (``localize_reliability_<tag>.png``), what accepting answers from
other probability thresholds than ``ok``'s 0.95 would give, and how often
an ambiguous answer's truth lies inside the 95 % ellipse of its own
covariance and of its ``mixture_covariance``.

Run: ``.venv/bin/python benchmarks/localize_paper.py [--runs 200] [--seed 0] [--intersections] [--no-kinds]
[--set NAME=VALUE ...] [--tag TAG]`` (``--set`` changes a field of the ``localizer.Options``
both methods run with, e.g. ``--set candidate_margin=1e9``; give such runs a ``--tag``)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _localizer_helpers import karlsruhe  # noqa: E402

from localizer import Options, Prior, localize  # noqa: E402
from localizer.robust import along_across_sigmas  # noqa: E402
from localizer.simulate import (  # noqa: E402
    HEAVY,
    Camera,
    Clutter,
    oracle_pose,
    perturb,
    sample_poses,
    simulate_scene,
)

OUT = ROOT / "benchmarks" / "out"


@dataclass(frozen=True)
class Scenario:
    name: str
    dist_m: tuple[float, float]
    heading_deg: float
    sigma_m: float
    sigma_deg: float
    clutter: Clutter


# The prior's sigmas match the initial errors: per-axis RMS of a uniform 0.5-2 m
# offset is ~1 m (8-10 m: ~6.4 m; 20 m: ~14 m), of a uniform ±15° heading ~8.7°.
# The paper varies position (Fig. 8) and heading (Fig. 9) separately; the
# other scenarios perturb both.
SCENARIOS = [
    Scenario("Fig.8 0.5-2m/0°", (0.5, 2.0), 0.0, 1.0, 2.0, Clutter()),
    Scenario("Fig.9 0m/±15°", (0.0, 0.0), 15.0, 0.5, 9.0, Clutter()),
    Scenario("0.5-2m/±15°", (0.5, 2.0), 15.0, 1.0, 9.0, Clutter()),
    Scenario("8-10m/±15°", (8.0, 10.0), 15.0, 6.5, 9.0, Clutter()),
    Scenario("20m/±30°", (20.0, 20.0), 30.0, 14.0, 17.0, Clutter()),
    Scenario("0.5-2m/±15° heavy", (0.5, 2.0), 15.0, 1.0, 9.0, HEAVY),
    Scenario("8-10m/±15° heavy", (8.0, 10.0), 15.0, 6.5, 9.0, HEAVY),
]


def field_value(cls: type):
    """A parser of ``NAME=VALUE`` for ``--set``: a field of the dataclass ``cls`` and its value as
    JSON (lists become tuples)."""

    def parse(text: str) -> tuple[str, object]:
        name, sep, value = text.partition("=")
        if not sep or name not in cls.__dataclass_fields__:
            raise argparse.ArgumentTypeError(f"expected NAME=VALUE with NAME a field of {cls.__name__}: {text!r}")
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError as exc:
            raise argparse.ArgumentTypeError(f"{name}: VALUE is not JSON: {value!r}") from exc
        return name, tuple(parsed) if isinstance(parsed, list) else parsed

    return parse


def heading_err_deg(a: float, b: float) -> float:
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


def scene_poses(args, smap, cam: Camera) -> np.ndarray:
    """Vehicle poses with at least 4 markings in view (with a stop line if asked)."""
    rng = np.random.default_rng(args.seed)
    if not args.intersections:
        return sample_poses(smap, args.runs, rng, cam, min_visible=4)
    from localizer.simulate import _in_view, _to_vehicle

    stops = smap.marking_xy[smap.marking_kind == "stop_line"]
    keep = [
        pose for pose in sample_poses(smap, args.runs * 20, rng, cam, min_visible=4)
        if _in_view(_to_vehicle(pose, stops), cam).any()
    ]
    return np.array(keep[: args.runs])


def cases(args, sc: Scenario, index, smap, cam: Camera, poses):
    """Yield ``(true pose, scene, prior)`` of one scenario, reproducibly."""
    frame = index.frame
    srng = np.random.default_rng([args.seed, sum(map(ord, sc.name))])
    for pose in poses:
        scene = simulate_scene(smap, pose, srng, cam, sc.clutter)
        d = srng.uniform(*sc.dist_m)
        init = perturb(pose, d, srng.uniform(-sc.heading_deg, sc.heading_deg), srng)
        lon, lat = frame.to_lonlat(init[0], init[1])
        prior = Prior(
            lat=lat, lon=lon, heading_deg=float(frame.grid_yaw_to_heading(init[2], lon, lat)),
            position_sigma_m=sc.sigma_m, heading_sigma_deg=sc.sigma_deg,
        )
        yield pose, scene, prior


def run(args) -> dict:
    index, smap = karlsruhe(kinds=not getattr(args, "no_kinds", False))
    cam = Camera()
    poses = scene_poses(args, smap, cam)
    opts = Options(record_trace=True, **dict(getattr(args, "set", None) or ()))
    results = {}
    traces = {}
    for sc in SCENARIOS:
        rows = []
        tr = {"pink2008": [], "default": []}
        for pose, scene, prior in tqdm(
            cases(args, sc, index, smap, cam, poses), total=len(poses), desc=sc.name, leave=False
        ):
            row = {"n_obs": len(scene.observations), "n_inl": int(scene.inlier.sum())}
            for method in ("pink2008", "default"):
                t0 = time.perf_counter()
                p = localize(index, scene.observations, prior, method=method, options=opts)
                ms = 1000 * (time.perf_counter() - t0)
                if p.easting is None:
                    e = h = math.inf
                    maha = maha_mix = math.inf
                    mix_sigmas = (math.nan, math.nan)
                else:
                    dx = np.array([p.easting - pose[0], p.northing - pose[1]])
                    e = float(np.hypot(*dx))
                    h = heading_err_deg(p.yaw_grid_rad, pose[2])
                    cov = p.covariance
                    maha = float(dx @ np.linalg.solve(cov[:2, :2], dx)) if cov is not None else math.inf
                    mix = p.mixture_covariance
                    maha_mix = float(dx @ np.linalg.solve(mix[:2, :2], dx)) if mix is not None else math.inf
                    mix_sigmas = ((math.nan, math.nan) if mix is None
                                  else along_across_sigmas(mix, p.yaw_grid_rad))
                hit = any(math.hypot(hy.easting - pose[0], hy.northing - pose[1]) <= 0.5
                          for hy in p.hypotheses)
                row[method] = dict(status=p.status, err=e, herr=h, ms=ms, maha=maha, maha_mix=maha_mix,
                                   mix_sigmas=mix_sigmas, it=p.iterations, hyp_hit=hit, prob=p.probability,
                                   edge=p.status == "ambiguous" and p.reason is not None)
                if len(tr[method]) < 60 and p.trace:
                    tr[method].append(
                        [(math.hypot(t[0] - pose[0], t[1] - pose[1]), heading_err_deg(t[2], pose[2]))
                         for t in p.trace]
                    )
            sig = cam.range_noise_m + cam.range_noise_coeff * np.sum(scene.observations[:, :2] ** 2, 1)
            o = oracle_pose(scene, sig)  # solid-line clusters constrain across the line only
            if o is None:
                row["oracle"] = dict(status="failed", err=math.inf, herr=math.inf, ms=0.0, maha=math.inf, it=0)
            else:
                row["oracle"] = dict(
                    status="ok", err=math.hypot(o[0] - pose[0], o[1] - pose[1]),
                    herr=heading_err_deg(o[2], pose[2]), ms=0.0, maha=math.inf, it=1,
                )
            rows.append(row)
        results[sc.name] = rows
        traces[sc.name] = tr
    return {"results": results, "traces": traces, "poses": len(poses)}


def summarize(rows: list[dict], method: str) -> dict:
    r = [x[method] for x in rows]
    n = len(r)
    ok = np.array([x["status"] == "ok" for x in r])
    amb = np.array([x["status"] == "ambiguous" for x in r])
    fail = np.array([x["status"] == "failed" for x in r])
    e = np.array([x["err"] for x in r])
    h = np.array([x["herr"] for x in r])
    ms = np.array([x["ms"] for x in r])
    maha = np.array([x["maha"] for x in r])
    s25 = ok & (e <= 0.25) & (h <= 1.0)
    s50 = ok & (e <= 0.5) & (h <= 1.0)
    any50 = (e <= 0.5) & (h <= 1.0)  # the answer's pose, whatever its status
    fin = np.isfinite(e)
    return {
        "n": n,
        "success_0.25m_1deg": float(s25.mean()),
        "success_0.5m_1deg": float(s50.mean()),
        "pose_0.5m_1deg": float(any50.mean()),
        "median_err_m": float(np.median(e[ok])) if ok.any() else math.nan,
        "median_err_all_m": float(np.median(e[fin])) if fin.any() else math.nan,
        "median_herr_deg": float(np.median(h[ok])) if ok.any() else math.nan,
        "confidently_wrong": float((ok & (e > 1.0)).mean()),
        "ambiguous": float(amb.mean()),
        "ambiguous_truth_listed": float(
            sum(x.get("hyp_hit", False) for x in r) / max(amb.sum(), 1)),
        "failed": float(fail.mean()),
        "ms_p50": float(np.median(ms)),
        "ms_p95": float(np.percentile(ms, 95)),
        "cov95": float(np.mean(maha[ok & (e <= 1.0)] <= 5.991)) if (ok & (e <= 1.0)).any() else math.nan,
        "cov2sigma": float(np.mean(maha[ok & (e <= 1.0)] <= 4.0)) if (ok & (e <= 1.0)).any() else math.nan,
    }


def mixture_cover_table(all_rows: dict) -> str:
    """Ambiguous answers: how often the truth lies inside the 95 % ellipse of the answer's own
    covariance and of its ``mixture_covariance`` (the hypotheses' spread about the answer)."""
    lines = ["| scenario | ambiguous | truth in the answer's 95 % ellipse | in the mixture's 95 % ellipse "
             "| mixture: median sigma along / across the heading |", "|---|---|---|---|---|"]
    for name, rows in all_rows.items():
        r = [x["default"] for x in rows if x["default"]["status"] == "ambiguous"]
        if not r:
            continue
        own = np.mean([x["maha"] <= 5.991 for x in r])
        mix = np.mean([x["maha_mix"] <= 5.991 for x in r])
        # NaN where an answer has no mixture (no hypothesis listed)
        along = np.nanmedian([x["mix_sigmas"][0] for x in r])
        across = np.nanmedian([x["mix_sigmas"][1] for x in r])
        lines.append(f"| {name} | {len(r)} | {own:.1%} | {mix:.1%} | {along:.2f} / {across:.2f} m |")
    return "\n".join(lines)


#: Bins of the default method's posterior probability for the reliability table.
PROB_BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 0.999, 1.0)


def reliability(all_rows: dict) -> list[dict]:
    """How often answers of each posterior probability are right, over all scenarios.

    Per bin of ``Pose.probability`` (default method, ``ok`` and ``ambiguous``
    answers): how many, their mean probability, and the share within 1 m and
    2° of the truth and within 0.5 m and 1° (the success criterion). A
    calibrated posterior has the first share close to the mean probability.
    """
    r = [x["default"] for rows in all_rows.values() for x in rows
         if x["default"]["status"] != "failed" and x["default"].get("prob") is not None]
    p = np.array([x["prob"] for x in r])
    near = np.array([x["err"] <= 1.0 and x["herr"] <= 2.0 for x in r])
    good = np.array([x["err"] <= 0.5 and x["herr"] <= 1.0 for x in r])
    out = []
    for k, (lo, hi) in enumerate(zip(PROB_BINS[:-1], PROB_BINS[1:])):
        m = (p >= lo) & ((p < hi) if k < len(PROB_BINS) - 2 else (p <= hi))
        if m.any():
            out.append(dict(lo=lo, hi=hi, n=int(m.sum()), mean_p=float(p[m].mean()),
                            within_1m=float(near[m].mean()), within_05m=float(good[m].mean())))
    return out


def reliability_table(bins: list[dict]) -> str:
    lines = ["| probability | answers | mean probability | within 1 m / 2° | within 0.5 m / 1° |",
             "|---|---|---|---|---|"]
    for b in bins:
        lines.append(f"| {b['lo']:g}–{b['hi']:g} | {b['n']} | {b['mean_p']:.3f} | {b['within_1m']:.1%} "
                     f"| {b['within_05m']:.1%} |")
    return "\n".join(lines)


#: Thresholds on ``Pose.probability`` a client might accept answers from.
THRESHOLDS = (0.9, 0.95, 0.99, 0.999)


def threshold_table(all_rows: dict) -> str:
    """Success per scenario and confidently wrong overall, had answers been accepted from each threshold.

    An answer (``ok`` or ``ambiguous``: the pose fields are the best
    hypothesis) counts as accepted when its probability reaches the threshold,
    unless the map's edge holds it back whatever its probability
    (``Options.edge_share``); 0.95 reproduces the ``ok`` status.
    """
    names = list(all_rows)
    lines = ["| accept from | " + " | ".join(names) + " | confidently wrong |",
             "|---|" + "---|" * (len(names) + 1)]
    for thr in THRESHOLDS:
        cells, cw, n = [], 0, 0
        for name in names:
            r = [x["default"] for x in all_rows[name]]
            acc = [x["status"] != "failed" and x.get("prob") is not None and x["prob"] >= thr
                   and not x.get("edge") for x in r]
            good = [a and x["err"] <= 0.5 and x["herr"] <= 1.0 for a, x in zip(acc, r)]
            cw += sum(a and x["err"] > 1.0 for a, x in zip(acc, r))
            n += len(r)
            cells.append(f"{np.mean(good):.1%}")
        lines.append(f"| {thr:g} | " + " | ".join(cells) + f" | {cw / max(n, 1):.2%} ({cw}) |")
    return "\n".join(lines)


def reliability_plot(bins: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 5))
    mp = [b["mean_p"] for b in bins]
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="calibrated")
    ax.plot(mp, [b["within_1m"] for b in bins], "o-", label="within 1 m / 2°")
    ax.plot(mp, [b["within_05m"] for b in bins], "s-", ms=4, label="within 0.5 m / 1°")
    for b in bins:
        ax.annotate(str(b["n"]), (b["mean_p"], b["within_1m"]), textcoords="offset points",
                    xytext=(4, -12), fontsize=7, color="0.3")
    ax.axvline(0.95, color="tab:red", lw=0.8, ls=":", label="ok threshold")
    ax.set_xlabel("posterior probability of the answer (Pose.probability)")
    ax.set_ylabel("share of answers that are right")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.set_title("default method: calibration of the posterior")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plots(traces: dict, suffix: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(parents=True, exist_ok=True)
    for name, tr in traces.items():
        fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
        for col, method in enumerate(("pink2008", "default")):
            for t in tr[method]:
                t = np.array(t)
                axes[0, col].plot(np.arange(len(t)), t[:, 0], lw=0.7)
                axes[1, col].plot(np.arange(len(t)), t[:, 1], lw=0.7)
            axes[0, col].set_title(f"{method}: {name}")
            axes[0, col].set_ylabel("position error [m]")
            axes[1, col].set_ylabel("heading error [°]")
            axes[1, col].set_xlabel("iteration" + (" (0: prior, 1: global search)" if method == "default" else ""))
            axes[0, col].set_yscale("symlog", linthresh=1.0)
            axes[1, col].set_yscale("symlog", linthresh=1.0)
        fig.tight_layout()
        safe = name.replace("/", "_").replace("±", "pm").replace("°", "deg").replace(" ", "_")
        fig.savefig(OUT / f"localize_iterations_{safe}{suffix}.png", dpi=110)
        plt.close(fig)


def table(all_rows: dict) -> str:
    lines = [
        "| scenario | method | succ 0.25m/1° | succ 0.5m/1° | pose 0.5m/1°, any status | median err (ok) "
        "| conf. wrong | ambiguous (truth listed) | failed | p50 ms | 95% ellipse cover | 2σ ellipse cover |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in all_rows.items():
        for method in ("oracle", "pink2008", "default"):
            s = summarize(rows, method)
            lines.append(
                f"| {name} | {method} | {s['success_0.25m_1deg']:.1%} | {s['success_0.5m_1deg']:.1%} | "
                f"{s['pose_0.5m_1deg']:.1%} | "
                f"{s['median_err_m']:.3f} m | {s['confidently_wrong']:.1%} | {s['ambiguous']:.1%}"
                + (f" ({s['ambiguous_truth_listed']:.0%})" if s["ambiguous"] else "") + " | "
                f"{s['failed']:.1%} | {s['ms_p50']:.1f} | "
                + ("– | –" if method == "oracle" else f"{s['cov95']:.1%} | {s['cov2sigma']:.1%}")
                + " |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200, help="scenes per scenario")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--intersections", action="store_true",
                    help="only poses with a stop line in view (like the paper's intersection)")
    ap.add_argument("--no-kinds", action="store_true",
                    help="index the map without its markings' kinds, as a map detected from imagery")
    ap.add_argument("--tag", default="")
    ap.add_argument("--set", action="append", type=field_value(Options), metavar="NAME=VALUE",
                    help="a localizer.Options field (repeatable; VALUE as JSON)")
    args = ap.parse_args()
    out = run(args)
    tab = table(out["results"])
    print(f"{out['poses']} poses, seed {args.seed}, intersections={args.intersections}, "
          f"kinds={not args.no_kinds}")
    print(tab)
    cw = [
        r[m]["status"] == "ok" and r[m]["err"] > 1.0
        for rows in out["results"].values() for r in rows for m in ("default",)
    ]
    print(f"default: confidently wrong over all runs: {np.mean(cw):.2%} ({sum(cw)}/{len(cw)})")
    bins = reliability(out["results"])
    rel = reliability_table(bins)
    print("default: how often answers of each posterior probability are right (all scenarios)")
    print(rel)
    thr = threshold_table(out["results"])
    print("default: success and confidently wrong had answers been accepted from a probability threshold")
    print(thr)
    mixc = mixture_cover_table(out["results"])
    print("default, ambiguous answers: the truth inside the 95 % ellipse of the answer's covariance and of "
          "its mixture_covariance (all hypotheses)")
    print(mixc)
    OUT.mkdir(parents=True, exist_ok=True)
    # Seed 0's untagged plots are the ones kept in the repository; other runs write beside them.
    seed = f"_seed{args.seed}" if args.seed != 0 else ""
    suffix = (("_intersections" if args.intersections else "") + ("_nokinds" if args.no_kinds else "") + seed
              + (f"_{args.tag}" if args.tag else ""))
    tag = args.tag or ("intersections" if args.intersections else "all") + ("_nokinds" if args.no_kinds else "") + seed
    (OUT / f"localize_paper_{tag}.md").write_text(tab + "\n\n" + rel + "\n\n" + thr + "\n\n" + mixc + "\n")
    reliability_plot(bins, OUT / f"localize_reliability_{tag}.png")
    (OUT / f"localize_paper_{tag}.json").write_text(json.dumps(out["results"], default=float))
    plots(out["traces"], suffix)


if __name__ == "__main__":
    main()

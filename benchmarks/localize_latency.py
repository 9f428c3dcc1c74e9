"""Latency of the localizer on this machine.

* ``MapIndex.from_arrays`` for maps of 2,000 to 200,000 markings;
* local refinement (the default method's robust IRLS, and the paper's ICP)
  for 30 observations against a 2,000-marking neighbourhood;
* the full default method (global search + refinement + scoring) with default
  options: typical requests with the API's default prior (5 m / 10°, the fix
  off by about 5 m / 10°) and ~30 observations, on a dense synthetic
  neighbourhood and on Karlsruhe scenes with paper-like clutter; and from a
  tight 1 m / 9° prior, a GPS-like 1.5 m / 2° one and the widest prior of
  ``localize_paper.py`` (14 m / 17°, the fix 20 m / ±30° off); and the load test's own
  frames (``benchmarks/load_localize.py``: a wider camera, 24–40 observations,
  GPS-like prior);
* the costliest request the API accepts (any heading, a 1 km position sigma,
  500 observations out to 148 m), within the coarse search's budget and
  without it; and the costliest drive request (``LANEMAP_MAX_DRIVE_OBSERVATIONS``
  spread over frames of 500 clutter observations each, which no pose explains,
  so that every frame searches around the fix again); the same clutter on
  the Karlsruhe map, where nothing matches and every candidate's refinement
  runs its iterations out.

All localize rows reuse one MapIndex (built once per map, as the service does).
Each call is timed in CPU time (``time.process_time``, what throughput on a
shared machine depends on) and in wall-clock time (which follows the
machine's load).

Run: ``.venv/bin/python benchmarks/localize_latency.py`` (report ``uptime`` load with it).
"""

from __future__ import annotations

import math
import os
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _localizer_helpers import karlsruhe  # noqa: E402

from localizer import Frame, MapIndex, Options, Prior, localize, localize_sequence  # noqa: E402
from localizer.geometry import LocalMap  # noqa: E402
from localizer.pink2008 import pink2008_icp  # noqa: E402
from localizer.robust import data_weights, noise_sigma, robust_refine  # noqa: E402
from localizer.simulate import Camera, Clutter, SceneMap, perturb, sample_poses, simulate_scene  # noqa: E402
from service.settings import ServiceSettings  # noqa: E402  (the drive limit the API enforces)

ORIGIN = np.array([458000.0, 5428000.0])


def timeit(fn, repeat: int) -> np.ndarray:
    """``(repeat, 2)`` milliseconds per call: CPU time, wall-clock time."""
    out = []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        out.append((1000 * (time.process_time() - c0), 1000 * (time.perf_counter() - t0)))
    return np.array(out)


def line(name: str, ms: np.ndarray) -> str:
    cpu, wall = ms[:, 0], ms[:, 1]
    return (f"| {name} | {np.median(cpu):.2f} | {np.percentile(cpu, 95):.2f} | "
            f"{np.percentile(cpu, 99):.2f} | {np.median(wall):.2f} | {np.percentile(wall, 99):.2f} | "
            f"{len(ms)} |")


def main() -> None:
    load0 = os.getloadavg()[0]
    rows = ["| operation | CPU p50 ms | CPU p95 ms | CPU p99 ms | wall p50 ms | wall p99 ms | calls |",
            "|---|---|---|---|---|---|---|"]
    rng = np.random.default_rng(0)
    for n in (2_000, 20_000, 200_000):
        side = math.sqrt(n / 0.05)  # 0.05 markings per m², a dense urban map
        xy = ORIGIN + rng.uniform(0, side, (n, 2))
        ms = timeit(lambda: MapIndex.from_arrays(xy[:, 0], xy[:, 1], np.ones(n), "EPSG:25832"), 5)
        rows.append(line(f"MapIndex.from_arrays, {n:,} markings", ms))
    # A map built from imagery: detections with axes and lengths, some cut short
    # or run long (slack along the axis, :func:`localizer.index.length_slack`).
    drng = np.random.default_rng(1)
    n = 200_000
    xy = ORIGIN + drng.uniform(0, math.sqrt(n / 0.05), (n, 2))
    length = drng.choice([3.0, 3.0, 3.0, 3.0, 1.2, 5.5], n)
    bearing = drng.uniform(0, 180, n)
    ms = timeit(lambda: MapIndex.from_arrays(xy[:, 0], xy[:, 1], np.ones(n), "EPSG:25832", bearing_deg=bearing,
                                             length_m=length, measured=np.ones(n, bool)), 5)
    rows.append(line(f"MapIndex.from_arrays, {n:,} detections (lengths, slack)", ms))

    # About 2,000 markings within the 45 m neighbourhood of one request.
    xy = ORIGIN + rng.uniform(-60, 60, (4_550, 2))
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, "EPSG:25832")
    pose = (ORIGIN[0], ORIGIN[1], 0.3)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = xy - ORIGIN
    v = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    r = np.hypot(*v.T)
    vis = np.flatnonzero((r > 4) & (r < 25) & (np.abs(np.arctan2(v[:, 1], v[:, 0])) < math.radians(30)))
    obs = v[rng.choice(vis, 30, replace=False)] + rng.normal(0, 0.05, (30, 2))
    gamma = rng.uniform(20, 200, 30)
    opts = Options()
    local = LocalMap(index, ORIGIN, 45.0)
    init = (0.4, -0.3, pose[2] + math.radians(2))
    w, sig = data_weights(gamma), noise_sigma(obs, opts)
    rows.append(line(f"LocalMap (neighbourhood of {len(local)} markings)",
                     timeit(lambda: LocalMap(index, ORIGIN, 45.0), 200)))
    rows.append(line("robust refinement, 30 obs, 2,000 markings",
                     timeit(lambda: robust_refine(local, obs, w, sig, [init], opts), 200)))
    rows.append(line("pink2008 ICP, 30 obs, 2,000 markings",
                     timeit(lambda: pink2008_icp(local, obs, gamma, init, opts), 200)))

    # The full default method on the same 30 observations (prior 5 m / 10° off by 4 m / 6°).
    lon, lat = index.frame.to_lonlat(ORIGIN[0] + 3.0, ORIGIN[1] - 2.6)
    prior = Prior(lat, lon, float(index.frame.grid_yaw_to_heading(pose[2] + 0.1, lon, lat)))
    dense_obs = np.column_stack([obs, gamma])
    rows.append(line("localize default, 30 obs, 2,000-marking neighbourhood, prior 5 m/10°",
                     timeit(lambda: localize(index, dense_obs, prior), 100)))

    index, smap = karlsruhe()
    poses = sample_poses(smap, 200, np.random.default_rng(1), min_visible=4)
    srng = np.random.default_rng(2)
    scenes = [simulate_scene(smap, p, srng, Camera(), Clutter()) for p in poses]
    # Typical requests: the scenes with 20-40 observations (paper-like clutter).
    typical = [(p, sc) for p, sc in zip(poses, scenes) if 20 <= len(sc.observations) <= 40]
    frame = index.frame
    # (label, scenes, prior sigma m, prior sigma deg, position error m, heading error bound deg)
    for label, sel, sigma_m, sigma_deg, dist, head in (
        ("typical (20-40 obs)", typical, 5.0, 10.0, 5.0, 10.0),
        ("all scenes", list(zip(poses, scenes)), 5.0, 10.0, 5.0, 10.0),
        ("all scenes", list(zip(poses, scenes)), 1.0, 9.0, 1.5, 10.0),
        # A GPS-like prior, as in the service's load test.
        ("all scenes", list(zip(poses, scenes)), 1.5, 2.0, 1.5, 2.0),
        # The widest prior of the accuracy benchmark (20 m / ±30° off): the
        # largest search volume a request is likely to ask for.
        ("all scenes", list(zip(poses, scenes)), 14.0, 17.0, 20.0, 30.0),
    ):
        for method in ("default", "pink2008"):
            ms = []
            n_obs = []
            for p, sc in tqdm(sel, desc=f"{method} {sigma_m} m", leave=False):
                init = perturb(p, dist, srng.uniform(-head, head), srng)
                lon, lat = frame.to_lonlat(init[0], init[1])
                prior = Prior(lat, lon, float(frame.grid_yaw_to_heading(init[2], lon, lat)),
                              sigma_m, sigma_deg)
                ms.append(timeit(lambda: localize(index, sc.observations, prior, method=method), 1)[0])
                n_obs.append(len(sc.observations))
            rows.append(line(
                f"localize {method}, Karlsruhe {label}, prior {sigma_m:g} m/{sigma_deg:g}° "
                f"({np.median(n_obs):.0f} obs median)", np.array(ms)))
    # The load test's frames, as the service receives them (JSON bodies).
    from load_localize import load_frames

    frames = load_frames(200, 7, 1.5, 2.0)
    for method in ("default", "pink2008"):
        ms = np.concatenate([timeit(lambda: localize(index, o, p, method=method), 1)
                             for _ in range(2) for o, p in frames])  # fmt: skip
        rows.append(line(
            f"localize {method}, load-test frames (200 × 2, "
            f"{np.median([len(o) for o, _ in frames]):.0f} obs median), prior 1.5 m/2°", ms))
    # The costliest request the API accepts: any heading, a 1 km position sigma
    # (the 45 m search radius), 500 observations out to 148 m of a wide camera.
    # The coarse search's budget (Options.max_search_cells / max_search_work)
    # bounds it; the unbounded row shows what it would cost without.
    wrng = np.random.default_rng(21)
    wxy = ORIGIN + wrng.uniform(-200.0, 200.0, (3_600, 2))
    windex = MapIndex.from_arrays(wxy[:, 0], wxy[:, 1], wrng.uniform(20, 200, 3_600), "EPSG:25832")
    wpose = (ORIGIN[0] + 6.0, ORIGIN[1] - 3.0, 1.1)
    wide = Camera(min_range_m=4.0, max_range_m=148.0, half_fov_deg=60.0)
    wobs = simulate_scene(SceneMap(marking_xy=wxy, marking_kind=np.full(len(wxy), "dash", object)),
                          wpose, wrng, wide, Clutter()).observations
    wobs = wobs[np.hypot(wobs[:, 0], wobs[:, 1]) < 149.0]  # the range noise reaches past the camera's
    wobs = wobs[wrng.permutation(len(wobs))[:500]]
    lon, lat = windex.frame.to_lonlat(ORIGIN[0], ORIGIN[1])
    wprior = Prior(lat, lon, 0.0, 1000.0, 180.0)
    unbounded = Options(max_search_cells=10**12, max_search_work=10**15)
    for label, o in (("within the search budget", opts), ("unbounded search", unbounded)):
        ms = timeit(lambda: localize(windex, wobs, wprior, options=o), 5)
        tracemalloc.start()
        localize(windex, wobs, wprior, options=o)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        rows.append(line(f"localize default, API limits: {len(wobs)} obs to "
                         f"{np.hypot(wobs[:, 0], wobs[:, 1]).max():.0f} m, any heading, 1 km sigma, {label} "
                         f"(peak {peak:.0f} MiB allocated)", ms))
    n_frames = ServiceSettings().max_drive_observations // 500
    crng = np.random.default_rng(22)
    clutter = []
    for _ in range(n_frames):
        r, b = np.sqrt(crng.uniform(4.0**2, 148.0**2, 500)), crng.uniform(-1.0, 1.0, 500)
        clutter.append(Frame(np.column_stack([r * np.cos(b), r * np.sin(b), crng.uniform(20, 200, 500)]),
                             (1.5, 0.0, 0.0)))
    ms = timeit(lambda: localize_sequence(windex, clutter, wprior), 3)
    rows.append(line(f"localize_sequence, drive at the API's limit: {n_frames} frames of 500 clutter "
                     "observations to 148 m, any heading, 1 km sigma", ms))
    # The same clutter on the real map: nothing matches, so the refinements of the
    # candidates run their iterations out over all 500 observations.
    kx, ky = smap.marking_xy[250]
    klon, klat = index.frame.to_lonlat(float(kx), float(ky))
    kprior = Prior(klat, klon, 100.0, 1000.0, 180.0)
    rows.append(line("localize default, Karlsruhe map, 500 clutter observations to 148 m, any heading, 1 km sigma",
                     timeit(lambda: localize(index, clutter[0].observations, kprior), 3)))
    rows.append(line("localize_sequence, Karlsruhe map, 4 such frames (an API server localizes a drive a frame "
                     "at a time, other requests in between)",
                     timeit(lambda: localize_sequence(index, clutter[:4], kprior), 2)))
    print(f"load average {load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end, "
          f"{os.cpu_count()} cores")
    print("\n".join(rows))
    out = ROOT / "benchmarks" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "localize_latency.md").write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()

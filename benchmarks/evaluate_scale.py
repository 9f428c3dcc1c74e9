"""Time and memory of scoring a city-sized map (``mapbuilder.evaluate.evaluate_markings``).

N true markings spread over a square (dashes, and 40 % pieces of solid lines),
and N detections of them with 5 cm of noise; prints the wall time, the peak
memory of the process and the figures (precision and recall 1 by design).

Run: ``.venv/bin/python benchmarks/evaluate_scale.py [--n 200000] [--side 5000]``
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from mapbuilder.evaluate import evaluate_markings
from mapbuilder.model import Marking


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200_000, help="true markings (and as many detections)")
    ap.add_argument("--side", type=float, default=5000.0, help="side of the square, metres")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, args.side, (args.n, 2))
    bearing = rng.uniform(0, 180, args.n)
    solid = rng.random(args.n) < 0.4
    truth = [Marking(x=x, y=y, length_m=3.0, bearing_deg=b, kind="solid" if s else "dash")
             for (x, y), b, s in zip(xy, bearing, solid)]  # fmt: skip
    noise = rng.normal(0, 0.05, (args.n, 2))
    detected = [Marking(x=m.x + dx, y=m.y + dy, length_m=3.0, bearing_deg=m.bearing_deg)
                for m, (dx, dy) in zip(truth, noise)]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    ev = evaluate_markings(detected, truth, (0.0, 0.0, args.side, args.side), border_m=0.0)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{args.n} true markings against {args.n} detections over {args.side:.0f} m: "
          f"{wall:.1f} s, peak RSS {peak:.0f} MB ({before:.0f} MB with the markings built); "
          f"precision {ev.precision:.4f}, recall {ev.recall:.4f}")


if __name__ == "__main__":
    main()

"""Bounding-box query speed of the map store with 1,000,000 markings in one map.

Loads a synthetic map (1,000,000 markings spread over 10 km x 10 km of UTM 32N,
about 10 per 1,000 m²), then times bbox queries that each return about 1,000
markings. Prints p50/p95/max latency, and how long a summary of the map
(``Store.summary``: counts by status, source and kind, the review's scores)
takes. The markings are unreviewed detections with scores, as a build leaves
them. SQLite by default; pass ``--url`` for PostgreSQL.

    .venv/bin/python benchmarks/store_bbox.py [--n 1000000] [--url URL] [--queries 200]
"""

from __future__ import annotations

import argparse
import math
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapbuilder.model import Marking
from mapbuilder.store import Store

E0, N0 = 455000.0, 5425000.0
SIDE = 10_000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--url", default=None, help="database URL (default: a temporary SQLite file)")
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--target", type=int, default=1000, help="markings per query box")
    ap.add_argument("--reuse", action="store_true", help="keep an already loaded map 'bench' at --url")
    args = ap.parse_args()

    tmp = tempfile.TemporaryDirectory()
    url = args.url or f"sqlite:///{Path(tmp.name) / 'bench.sqlite'}"
    store = Store(url)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, SIDE, size=(args.n, 2))
    scores = rng.uniform(0, 1, size=args.n).round(3)
    loaded = [m for m in store.list_maps() if m.id == "bench"]
    reuse = args.reuse and loaded and loaded[0].count == args.n
    if not reuse:
        if loaded:
            store.delete_map("bench")
        store.create_map("bench", crs="EPSG:25832")
    t0 = time.perf_counter()
    chunk = 50_000
    with tqdm(total=0 if reuse else args.n, unit="marking", desc="loading") as bar:
        for s in range(0, 0 if reuse else args.n, chunk):
            part = pts[s : s + chunk]
            store.bulk_load(
                "bench",
                (Marking(x=E0 + a, y=N0 + b, length_m=3, width_m=0.12, weight=36, source="detected",
                         score=float(sc)) for (a, b), sc in zip(part, scores[s : s + chunk])),
            )
            bar.update(len(part))
    load_s = time.perf_counter() - t0

    side = math.sqrt(args.target / args.n) * SIDE  # box side for ~target markings
    lat, counts = [], []
    for _ in range(args.queries):
        x0, y0 = rng.uniform(0, SIDE - side, 2)
        t = time.perf_counter()
        got = store.query_bbox("bench", E0 + x0, N0 + y0, E0 + x0 + side, N0 + y0 + side)
        lat.append((time.perf_counter() - t) * 1000)
        counts.append(len(got))
    lat = np.array(lat)
    print(f"database      {store.dialect} ({'temporary file' if not args.url else 'given URL'})")
    print(f"machine       {platform.machine()}, {__import__('os').cpu_count()} cores, Python {platform.python_version()}")
    if not reuse:
        print(f"markings      {args.n:,} loaded in {load_s:.1f} s ({args.n / load_s:,.0f}/s)")
    print(f"query box     {side:.1f} m x {side:.1f} m, {np.mean(counts):.0f} markings on average")
    print(f"bbox query    p50 {np.percentile(lat, 50):.1f} ms, p95 {np.percentile(lat, 95):.1f} ms, max {lat.max():.1f} ms over {args.queries} queries (full Marking objects)")
    scans, kept = [], []
    for _ in range(5):
        store._summaries.clear()  # the scan itself, as at the map's first summary after a change
        t = time.perf_counter()
        sm = store.summary("bench")
        scans.append(time.perf_counter() - t)
        t = time.perf_counter()
        store.summary("bench")  # then kept until the map's revision moves on
        kept.append(time.perf_counter() - t)
    assert sm.count == args.n
    print(f"summary       median {np.median(scans) * 1000:.0f} ms, max {max(scans) * 1000:.0f} ms over 5 scans "
          f"(counts of {sm.count:,} markings and the histogram of {sum(sm.unreviewed_scores):,} scores); "
          f"{np.median(kept) * 1000:.1f} ms while the map is unchanged")


if __name__ == "__main__":
    main()

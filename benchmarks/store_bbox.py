"""Bounding-box query speed of the map store with 1,000,000 markings in one map.

Loads a synthetic map (1,000,000 markings spread over 10 km x 10 km of UTM 32N,
about 10 per 1,000 m²), then times bbox queries that each return about 1,000
markings. Prints p50/p95/max latency, and how long a summary of the map
(``Store.summary``: counts by status, source and kind, the review's scores)
takes: of the whole map (the kept counts), of a hundredth of it and of the
whole map counted from its markings (a box around it); and pages of boxes over 3 %,
10 %, 30 % and 95 % of the map (the API's ``/items?bbox=``; a box's count is read for its first
page and kept for the rest) and of their review queues. The markings are unreviewed detections with scores, as a build leaves
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
    info = store.get_map("bench")
    w, s_, e, n = info.bounds_wgs84()
    district = (w, s_, w + (e - w) / 10, s_ + (n - s_) / 10)  # a hundredth of the map
    whole, part = [], []
    for _ in range(5):
        t = time.perf_counter()
        sm = store.summary("bench")
        whole.append(time.perf_counter() - t)
        t = time.perf_counter()
        store.summary("bench", lonlat_box=district)
        part.append(time.perf_counter() - t)
    t = time.perf_counter()
    counted = store.summary("bench", lonlat_box=(w, s_, e, n))  # just around the map: counted
    scan = time.perf_counter() - t
    assert sm.count == args.n and counted == sm
    print(f"summary       {np.median(whole) * 1000:.1f} ms (the counts every write keeps, of {sm.count:,} markings "
          f"and the histogram of {sum(sm.unreviewed_scores):,} scores; median of 5); a hundredth of the map, "
          f"counted: {np.median(part) * 1000:.0f} ms; the whole map counted: {scan:.2f} s")
    for share in (0.03, 0.1, 0.3, 0.95):  # boxes, centred: WIDE_BOX_SHARE picks how they are read
        k = math.sqrt(share) / 2
        cx, cy = (w + e) / 2, (s_ + n) / 2
        box = (cx - k * (e - w), cy - k * (n - s_), cx + k * (e - w), cy + k * (n - s_))
        t = time.perf_counter()
        _, total = store.query_lonlat_box("bench", box, limit=1000)  # its count read, then kept
        first = (time.perf_counter() - t) * 1000
        pages = []
        for page in range(1, 10):
            t = time.perf_counter()
            store.query_lonlat_box("bench", box, limit=1000, offset=1000 * page)
            pages.append((time.perf_counter() - t) * 1000)
        t = time.perf_counter()
        store.query_lonlat_box("bench", box, limit=1000, offset=total // 2)
        half = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        queue, queued = store.review_queue("bench", lonlat_box=box, limit=500)  # its count read, then kept
        q_first = (time.perf_counter() - t) * 1000
        for _ in range(20):
            queue, _ = store.review_queue("bench", lonlat_box=box, limit=500, after=(queue[-1].score, queue[-1].id))
        t = time.perf_counter()
        store.review_queue("bench", lonlat_box=box, limit=500, after=(queue[-1].score, queue[-1].id))
        q_21 = (time.perf_counter() - t) * 1000
        print(f"box           {share:.0%} of the map ({total:,} markings): a page of 1,000 with its count "
              f"{first:.0f} ms, pages 2-10 {np.median(pages):.0f} ms (median), half-way {half:.0f} ms; "
              f"its review queue ({queued:,}), a page of 500 with its count {q_first:.0f} ms, the 21st {q_21:.0f} ms")

if __name__ == "__main__":
    main()

"""What starting a review of a city's detections costs the web editor, against a real ``lanemap serve``.

A map of N unreviewed detections with scores spread evenly over 0-1 (a 5 km
square near Karlsruhe, SQLite) is served by one uvicorn worker. One client
then times, over HTTP:

* the whole queue read as the editor read it before it came a page at a
  time: every page of ``GET .../items?status=unreviewed&limit=10000``;
* the queue's first page as the editor reads it now
  (``GET .../review/queue?limit=500``), and a page in the middle of the
  queue (from a ``next`` link's ``after``), each 20 times (p50 and max);
* after a review by score of a fifth of the map, what an editor open
  meanwhile reads: the change feed whole (pages of 5,000), as it did before,
  and its first page alone, which counts the changes: past 5,000 the editor
  reads its view again instead.

It prints the wall time and the bytes of each.

Usage::

    .venv/bin/python benchmarks/review_queue.py [--n 200000]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mapbuilder.store import Store
from review_by_score import scored_detections
from tests._api_helpers import start_server


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    url = f"sqlite:///{tmp / 'bench.sqlite'}"
    store = Store(url)
    store.create_map("city", crs="EPSG:25832")
    scores = scored_detections(store, "city", args.n)
    store.close()
    print(f"map           {args.n:,} unreviewed detections, SQLite")
    print(f"machine       {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    server = start_server(url, tmp / "data")
    try:
        with httpx.Client(base_url=server.base_url, timeout=600) as c:
            t, size, pages = time.perf_counter(), 0, 0
            nxt = "/collections/city/items?status=unreviewed&limit=10000"
            while nxt:
                r = c.get(nxt)
                r.raise_for_status()
                size, pages = size + len(r.content), pages + 1
                links = [ln["href"] for ln in r.json()["links"] if ln["rel"] == "next"]
                nxt = links[0] if links else None
            print(f"all at once   {time.perf_counter() - t:.2f} s, {pages} pages, {size / 1e6:.1f} MB")
            first, middle = [], []
            mid = float(np.sort(scores)[args.n // 2])
            for _ in range(20):
                t = time.perf_counter()
                r = c.get("/collections/city/review/queue?limit=500")
                first.append(time.perf_counter() - t)
                r.raise_for_status()
                t = time.perf_counter()
                r2 = c.get(f"/collections/city/review/queue?limit=500&after={mid!r},1")
                middle.append(time.perf_counter() - t)
                r2.raise_for_status()
            body = r.json()
            assert body["numberMatched"] == args.n and body["numberReturned"] == 500
            print(f"first page    p50 {np.median(first) * 1e3:.0f} ms, max {max(first) * 1e3:.0f} ms, "
                  f"{len(r.content) / 1e3:.0f} kB")
            print(f"middle page   p50 {np.median(middle) * 1e3:.0f} ms, max {max(middle) * 1e3:.0f} ms")
            # an editor open meanwhile follows a review by score of a fifth of the map
            rev = c.get("/collections/city").json()["revision"]
            r = c.post("/collections/city/review", json={"accept_from": 0.9, "reject_below": 0.1},
                       headers={"Authorization": f"Bearer {server.token}"})  # fmt: skip
            r.raise_for_status()
            t, size, pages, total = time.perf_counter(), 0, 0, None
            nxt = f"/collections/city/changes?since={rev}&limit=5000"
            while nxt:
                r = c.get(nxt)
                r.raise_for_status()
                size, pages = size + len(r.content), pages + 1
                total = r.json().get("numberMatched", total)
                links = [ln["href"] for ln in r.json()["links"] if ln["rel"] == "next"]
                nxt = links[0] if links else None
            print(f"feed whole    {time.perf_counter() - t:.2f} s for {total:,} changes, {pages} pages, "
                  f"{size / 1e6:.1f} MB")
            t = time.perf_counter()
            c.get(f"/collections/city/changes?since={rev}&limit=5000").raise_for_status()
            print(f"feed counted  {(time.perf_counter() - t) * 1e3:.0f} ms (its first page, then the view read again)")
    finally:
        server.stop()


if __name__ == "__main__":
    main()

"""How long a review by score takes on a large map (``Store.review_by_score``, ``lanemap review``).

A map of N unreviewed detections with scores spread evenly over 0-1 (a 5 km
square near Karlsruhe) is counted (a dry run), then the detections scoring at
least 0.9 are accepted and those below 0.1 rejected in one changeset (a fifth
of the map), and that changeset is reverted. Prints the wall time of each on
the database given (a fresh SQLite file by default). Last, changesets of 20
updates of markings anywhere in the map are timed, as an editor's bulk edit.

Run: ``.venv/bin/python benchmarks/review_by_score.py [--n 200000] [--url postgresql://...]``
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from mapbuilder.model import Marking
from mapbuilder.store import Change, Store

E0, N0 = 455000.0, 5425000.0  # EPSG:25832, Karlsruhe


def scored_detections(store: Store, map_id: str, n: int) -> np.ndarray:
    """Load ``n`` unreviewed detections, scores spread evenly over 0-1, over a 5 km square into
    ``map_id`` (EPSG:25832); their scores."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 5000, size=(n, 2))
    scores = rng.uniform(0, 1, n).round(3)
    store.bulk_load(map_id, (Marking(x=E0 + a, y=N0 + b, length_m=3, width_m=0.12, weight=36, source="detected",
                                     score=float(s)) for (a, b), s in zip(xy, scores)))  # fmt: skip
    return scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--url", default=None, help="database URL (default: a temporary SQLite file)")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory()
    store = Store(args.url or f"sqlite:///{Path(tmp.name) / 'bench.sqlite'}")
    if any(m.id == "review" for m in store.list_maps()):
        store.delete_map("review")
    store.create_map("review", crs="EPSG:25832")
    t = time.perf_counter()
    scored_detections(store, "review", args.n)
    loaded = time.perf_counter() - t
    print(f"database      {store.dialect}, {args.n:,} unreviewed detections")
    print(f"machine       {platform.machine()}, {__import__('os').cpu_count()} cores, Python {platform.python_version()}")
    print(f"load          {loaded:.2f} s (Store.bulk_load)")
    t = time.perf_counter()
    dry = store.review_by_score("review", accept_from=0.9, reject_below=0.1, who="bench", dry_run=True)
    print(f"dry run       {time.perf_counter() - t:.2f} s: {dry.accepted:,} to accept, {dry.rejected:,} to reject")
    t = time.perf_counter()
    res = store.review_by_score("review", accept_from=0.9, reject_below=0.1, who="bench")
    print(f"review        {time.perf_counter() - t:.2f} s: {res.accepted + res.rejected:,} markings in changeset "
          f"{res.changeset_id}")
    t = time.perf_counter()
    store.revert_changeset("review", res.changeset_id, who="bench")
    print(f"revert        {time.perf_counter() - t:.2f} s")
    assert store.summary("review").detections["unreviewed"] == args.n
    ids = store.marking_arrays("review", ["unreviewed"]).id
    rng = np.random.default_rng(1)
    took = []
    for _ in range(10):
        pick = rng.choice(ids, 20, replace=False)
        t = time.perf_counter()
        store.apply_changeset("review", [Change("update", id=int(i), fields={"status": "accepted"}) for i in pick],
                              who="bench")  # fmt: skip
        took.append(time.perf_counter() - t)
    print(f"changeset     {1000 * float(np.median(took)):.0f} ms: 20 updates, median of 10")
    store.delete_map("review")


if __name__ == "__main__":
    main()

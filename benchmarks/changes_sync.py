"""How long a copy of a large map takes to follow it through the change feed (``Store.changes``).

A map of N markings (a 5 km square near Karlsruhe) is read whole from
``since=0`` in pages, as a fleet starting from nothing would; then a day of
editing (changesets of updates, deletes and creates, and a rebuilt tile) is
read as the changes since the copy's revision. Prints the wall time and the
rate of each, on the database given (a fresh SQLite file by default).

Run: ``.venv/bin/python benchmarks/changes_sync.py [--n 200000] [--page 10000] [--url postgresql://...]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mapbuilder.model import Marking
from mapbuilder.store import Change, Store

E0, N0 = 455000.0, 5425000.0  # EPSG:25832, Karlsruhe


def follow(store: Store, map_id: str, since: int, page: int) -> tuple[dict[int, int], int, int, int]:
    """Apply every page since ``since`` to a dict of id -> version; (copy, revision, changes, pages)."""
    copy, after, n, pages = {}, None, 0, 0
    while True:
        p = store.changes(map_id, since, after=after, limit=page)
        for _, i in p.removed:
            copy[i] = None
        for _, m in p.changed:
            copy[m.id] = m.version
        n += len(p.changed) + len(p.removed)
        pages += 1
        if not p.more:
            return copy, p.revision, n, pages
        after = p.after


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200_000, help="markings in the map")
    ap.add_argument("--page", type=int, default=10_000, help="changes per page (the API's largest by default)")
    ap.add_argument("--url", help="database URL (default: a fresh SQLite file)")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory()
    url = args.url or f"sqlite:///{Path(tmp.name) / 'changes.sqlite'}"
    store = Store(url)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 5000, (args.n, 2))
    store.create_map("big", crs="EPSG:25832")
    t0 = time.perf_counter()
    store.bulk_load("big", (Marking(x=E0 + x, y=N0 + y, length_m=3.0, width_m=0.15, bearing_deg=90.0, weight=50.0,
                                   kind="dash", source="imported") for x, y in xy))  # fmt: skip
    print(f"{args.n} markings stored in {time.perf_counter() - t0:.1f} s ({store.dialect})")

    t0 = time.perf_counter()
    copy, rev, n, pages = follow(store, "big", 0, args.page)
    wall = time.perf_counter() - t0
    print(f"a copy from nothing: {n} changes in {pages} pages of up to {args.page}, {wall:.2f} s "
          f"({n / wall:,.0f} markings/s)")

    ids = np.array(sorted(copy))
    t0 = time.perf_counter()
    for k in range(100):
        pick = rng.choice(ids, 12, replace=False)
        changes = [Change("update", id=int(i), fields={"status": "accepted"}) for i in pick[:10]]
        changes.append(Change("delete", id=int(pick[10])))
        changes.append(Change("create", marking=Marking(x=E0 + 10 + k, y=N0 + 10, length_m=3.0, weight=40.0)))
        ids = ids[~np.isin(ids, pick[10:11])]
        store.apply_changeset("big", changes, who="bench")
    store.replace_detected("big", "tile-0", [Marking(x=E0 + 20 + k * 0.5, y=N0 + 20, length_m=3.0, weight=30.0)
                                             for k in range(500)])  # fmt: skip
    store.replace_detected("big", "tile-0", [Marking(x=E0 + 20.1 + k * 0.5, y=N0 + 20, length_m=3.0, weight=30.0)
                                             for k in range(500)])  # fmt: skip
    print(f"a day of editing: 100 changesets and a tile built twice in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    delta, rev2, n2, pages2 = follow(store, "big", rev, args.page)
    wall = time.perf_counter() - t0
    copy.update(delta)
    live = {m.id: m.version for m in store.iter_markings("big")}
    same = {k: v for k, v in copy.items() if v is not None} == live
    print(f"the changes since revision {rev}: {n2} in {pages2} page(s), {wall * 1000:.0f} ms; "
          f"the copy at revision {rev2} equals the map: {same}")
    store.close()


if __name__ == "__main__":
    main()

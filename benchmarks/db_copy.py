"""How long ``lanemap db copy`` takes for a large map (``mapbuilder.dbcopy.copy_database``).

A map of N markings with an edit log is stored in a fresh SQLite file, copied
to the PostgreSQL database given (moving a deployment), and copied back from
there to a new SQLite file (a backup). Prints the wall time and rate of each.

Run: ``.venv/bin/python benchmarks/db_copy.py --pg postgresql://user:password@host/empty_db [--n 200000]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mapbuilder.dbcopy import copy_database
from mapbuilder.model import Marking
from mapbuilder.store import Change, Store

E0, N0 = 455000.0, 5425000.0  # EPSG:25832, Karlsruhe


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200_000, help="markings in the map")
    ap.add_argument("--pg", required=True, help="URL of an empty PostgreSQL database")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    live = Store(f"sqlite:///{tmp / 'live.sqlite'}")
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 5000, (args.n, 2))
    live.create_map("big", crs="EPSG:25832")
    live.bulk_load("big", (Marking(x=E0 + x, y=N0 + y, length_m=3.0, width_m=0.15, bearing_deg=90.0, weight=50.0)
                           for x, y in xy))  # fmt: skip
    ids = [m.id for m in live.list_markings("big", limit=1000)[0]]
    for k in range(0, 1000, 10):
        live.apply_changeset("big", [Change("update", id=i, fields={"status": "accepted"}) for i in ids[k:k + 10]],
                             who="bench")  # fmt: skip
    for name, src, dst in (("SQLite -> PostgreSQL", live, Store(args.pg)),
                           ("PostgreSQL -> SQLite", Store(args.pg), Store(f"sqlite:///{tmp / 'backup.sqlite'}"))):
        t0 = time.perf_counter()
        report = copy_database(src, dst)
        wall = time.perf_counter() - t0
        rows = sum(report.rows.values())
        print(f"{name}: {report.rows['markings']} markings, {report.rows['edits']} edits, {rows} rows in all, "
              f"{wall:.1f} s ({rows / wall:,.0f} rows/s)")


if __name__ == "__main__":
    main()

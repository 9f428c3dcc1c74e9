"""Concurrent conditional edits: 20 clients editing the same features for 60 s, no lost update.

Starts ``lanemap serve`` on a fresh SQLite file (and/or a fresh PostgreSQL
database), creates a few features, and lets ``--clients`` threads edit them
for ``--duration`` seconds: each reads a feature and writes its ``weight + 1``
with ``If-Match`` (PATCH or PUT) or as a versioned changeset of two features.
Then it checks, from the server's history (see ``tests/_edit_race.py``):

* no lost update: the final state of every feature equals the replay of the
  accepted edits of its history, its weight went up by exactly the number of
  accepted increments, and the history holds exactly the writes the clients
  were told were accepted, each with the version it was answered;
* every rejected write was answered 412 (If-Match) or 409 (changeset).

It prints the counts (accepted, 412, 409, other) per kind of write, the
throughput, and the verdict; the exit code is 1 when an invariant broke.

Usage::

    .venv/bin/python benchmarks/concurrent_edits.py [--clients 20] [--duration 60] [--features 4]
        [--db sqlite postgresql] [--workers 1]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests._api_helpers import TOKEN, fresh_postgres_db, start_server  # noqa: E402
from tests._edit_race import create_features, race, verify  # noqa: E402


def run_one(db: str, args) -> bool:
    tmp = Path(tempfile.mkdtemp(prefix="lanemap-edits-"))
    drop = None
    if db == "postgresql":
        url, drop = fresh_postgres_db()
    else:
        url = f"sqlite:///{tmp / 'lanemap.sqlite'}"
    server = start_server(url, tmp / "data", args=("--workers", str(args.workers), "--log-level", "warning"))
    try:
        map_id = server.new_map(prefix="edits")
        with server.client(headers=server.auth) as c:
            ids = create_features(c, map_id, args.features)
        load0 = os.getloadavg()
        res = race(server.base_url, TOKEN, map_id, ids, clients=args.clients, duration=args.duration,
                   seed=args.seed, think_s=args.think_ms / 1000.0)  # fmt: skip
        load1 = os.getloadavg()
        t0 = time.monotonic()
        problems = verify(server.base_url, map_id, ids, res)
        print(f"\n{db}, lanemap serve --workers {args.workers}: {args.clients} clients on {args.features} "
              f"features for {res.seconds:.1f} s (verified in {time.monotonic() - t0:.1f} s)")  # fmt: skip
        print(f"  {'write':10s} {'sent':>7s} {'accepted':>8s} {'412':>6s} {'409':>6s} {'other':>6s}")
        ok_status = {"patch": "200", "put": "200", "changeset": "201"}
        for kind in ("patch", "put", "changeset"):
            sent = sum(n for (k, _), n in res.answers.items() if k == kind)
            acc = res.answers.get((kind, ok_status[kind]), 0)
            n412, n409 = res.answers.get((kind, "412"), 0), res.answers.get((kind, "409"), 0)
            print(f"  {kind:10s} {sent:7d} {acc:8d} {n412:6d} {n409:6d} {sent - acc - n412 - n409:6d}")
        other = res.unexpected()
        print(f"  {'total':10s} {res.writes:7d} {len({(a.writer) for a in res.accepted}):8d} "
              f"{res.count('412'):6d} {res.count('409'):6d} {sum(other.values()):6d}"
              f"   ({res.writes / res.seconds:.0f} writes/s, {len(res.accepted)} feature versions written)")  # fmt: skip
        if other:
            print(f"  other answers: {other}")
        print(f"  load average before/after: {load0[0]:.2f}/{load1[0]:.2f}")
        if "Traceback" in server.log():
            problems.append("the server log has a traceback")
        if problems:
            print("  VERDICT: FAILED")
            for p in problems[:40]:
                print(f"    - {p}")
        else:
            print("  VERDICT: no lost update; every rejected write was answered 412/409")
        return not problems
    finally:
        server.stop()
        if drop is not None:
            drop()
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of editing per database")
    ap.add_argument("--features", type=int, default=4, help="features all clients edit")
    ap.add_argument("--db", nargs="+", default=["sqlite", "postgresql"], choices=["sqlite", "postgresql"])
    ap.add_argument("--workers", type=int, default=1, help="server processes")
    ap.add_argument("--think-ms", type=float, default=5.0, help="most a client waits between read and write")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(f"concurrent edits, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores")
    ok = all([run_one(db, args) for db in args.db])
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()

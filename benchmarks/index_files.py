"""What a kept index (``LANEMAP_INDEX_DIR``) saves a process that needs a city's map.

The map: the Karlsruhe Lanelet2 example (819 markings, where the vehicle is)
plus ``--markings`` filler markings of a jittered street grid 13 km east of
it (``localize_during_edits.py``), in a fresh SQLite store.

* *CLI*: ``lanemap localize`` of ``docs/examples/frame.json``, for each
  coverage: the first call (it builds the index and keeps it), the next
  (it reads it) and one after a marking was moved (it reads the kept index,
  updates it with the edit and keeps that), wall clock, CPU and peak memory
  of the process.
* *Server*: ``lanemap serve --workers N`` started with ``LANEMAP_INDEX_DIR=off``
  (every worker builds its own), then with no kept index (one builds and
  keeps it, the others wait for it and read it), then started again with
  the one that start kept: seconds from the launch
  until the server answers, until the first localization is answered, and
  until ``--settle`` answers in a row come back within 100 ms (every worker
  ready), and how many builds and file reads the workers' logs show.

Usage::

    .venv/bin/python benchmarks/index_files.py [--markings 1000000] [--coverage hull markings] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from load_localize import MAP_ID, make_bodies  # noqa: E402
from localize_during_edits import city_arguments, city_map, header, load_average  # noqa: E402
from tests._api_helpers import start_server  # noqa: E402

FRAME = REPO / "docs" / "examples" / "frame.json"
LANEMAP = str(Path(sys.executable).with_name("lanemap"))


def cli_call(env: dict, coverage: str, tmp: Path) -> tuple[float, float, float, str]:
    """One ``lanemap localize``: wall s, CPU s, peak RSS MB, the answer's status."""
    out_path, err_path = tmp / "cli.out", tmp / "cli.err"
    t = time.perf_counter()
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen([LANEMAP, "localize", MAP_ID, "--lat", "49.0051049", "--lon", "8.4152842",
                                 "--heading", "102.87", "--observations", str(FRAME), "--coverage", coverage],
                                env=env, stdout=out, stderr=err)  # fmt: skip
        _, code, usage = os.wait4(proc.pid, 0)  # this process's own peak memory, not the largest child's
        proc.returncode = os.waitstatus_to_exitcode(code)
    wall = time.perf_counter() - t
    status = re.search(r'"status": "(\w+)"', out_path.read_text())
    if status is None:
        raise RuntimeError(f"lanemap localize failed ({proc.returncode}): {err_path.read_text()}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, status.group(1)


def move_one(url: str, marking_id: int) -> None:
    """Move a filler marking by 10 cm: the next call updates the kept index with it."""
    from mapbuilder.store import Change, Store

    store = Store(url)
    try:
        x = store.get_marking(MAP_ID, marking_id).x
        store.apply_changeset(MAP_ID, [Change("update", id=marking_id, fields={"x": x + 0.1})], who="benchmark")
    finally:
        store.close()


def server_start(url: str, data: Path, env: dict, workers: int, bodies: list[bytes], settle: int) -> dict:
    launched = time.monotonic()
    server = start_server(url, data, env=env, args=("--workers", str(workers), "--log-level", "info"), timeout=600)
    out = {"answers": time.monotonic() - launched}
    try:
        url_loc = f"{server.base_url}/collections/{MAP_ID}/localize"
        in_row, k = 0, 0
        with httpx.Client(timeout=600) as client:
            while in_row < settle and time.monotonic() - launched < 600:
                t = time.monotonic()
                r = client.post(url_loc, content=bodies[k % len(bodies)], headers={"Content-Type": "application/json"})
                k += 1
                r.raise_for_status()
                out.setdefault("first", time.monotonic() - launched)
                in_row = in_row + 1 if time.monotonic() - t < 0.1 else 0
        out["settled"] = time.monotonic() - launched
        log = server.log()
        out["builds"] = len(re.findall(rf"map {MAP_ID}: spatial index of \d+ markings at revision \d+ \(coverage: "
                                       r"\w+\) in ", log))  # fmt: skip
        out["reads"] = log.count("read from")
    finally:
        server.stop()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    city_arguments(ap, 1_000_000)
    ap.add_argument("--workers", type=int, default=2, help="server worker processes")
    ap.add_argument("--settle", type=int, default=20, help="answers in a row within 100 ms that end a start")
    ap.add_argument("--no-cli", action="store_true", help="the server's starts only")
    args = ap.parse_args()

    print(header("kept indexes"))
    tmp = Path(tempfile.mkdtemp(prefix="lanemap-kept-"))
    url = f"sqlite:///{tmp / 'lanemap.sqlite'}"
    kept = tmp / "data" / "indexes"
    try:
        ids, loaded = city_map(url, args.markings)
        print(f"{loaded}\n")
        base_env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
        base_env.update(LANEMAP_DATABASE_URL=url, LANEMAP_DATA_DIR=str(tmp / "data"))
        subprocess.run([LANEMAP, "maps", "list"], env=base_env, capture_output=True, check=True)  # compiled, warm
        print("lanemap localize docs/examples/frame.json   wall s   CPU s   peak MB   status")
        for coverage in [] if args.no_cli else args.coverage:
            shutil.rmtree(kept, ignore_errors=True)
            for label in ("builds, keeps", "reads the kept", "after an edit"):
                if label == "after an edit":
                    move_one(url, ids[0])
                wall, cpu, rss, status = cli_call(base_env, coverage, tmp)
                print(f"  {coverage:9s} {label:22s} {wall:8.2f} {cpu:7.2f} {rss:9.0f}   {status}")
            size = sum(p.stat().st_size for p in kept.glob("*.index"))
            print(f"  {coverage:9s} kept file: {size / 1e6:.0f} MB")

        bodies = make_bodies(50, 7, 1.5, 2.0)
        print(f"\nlanemap serve --workers {args.workers} (seconds from the launch)   answers   first localization"
              f"   {args.settle} in a row < 100 ms   builds / file reads in the log")
        for coverage in args.coverage:
            shutil.rmtree(kept, ignore_errors=True)
            for label, extra in (("off", {"LANEMAP_INDEX_DIR": "off"}), ("no kept index", {}), ("kept index", {})):
                env = {"LANEMAP_MAP_COVERAGE": coverage, **extra}
                r = server_start(url, tmp / "data", env, args.workers, bodies, args.settle)
                print(f"  {coverage:9s} {label:14s} {r['answers']:8.1f} {r['first']:12.1f} {r['settled']:14.1f}"
                      f"        {r['builds']} / {r['reads']}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average at the end: {load_average()}")


if __name__ == "__main__":
    main()

"""Localization latency on a large map while people edit it.

Every edit moves a map's revision on, and a localization answers from the
map's index at a revision. This script measures what a fleet sees while a map
of a city's size is corrected in the editor: the Karlsruhe Lanelet2 example
(819 markings, where the vehicle is) plus ``--markings`` filler markings of a
synthetic street grid 13 km east of it (two solid edge lines and a dashed
centre line per street, as a build leaves them, jittered by 5 cm), in a fresh
SQLite store, served by ``lanemap serve`` (one worker, the map's coverage
``--coverage``).

Phases, each ``--duration`` seconds of one closed-loop vehicle (the next
frame as soon as the answer comes; the frames of ``load_localize.py``, a
GPS-like prior):

* *cold*: the first request after the server starts, which waits for the
  map's index to be built (the server is started with
  ``LANEMAP_INDEX_PRELOAD=0``, so the build is the request's own);
* *quiet*: nobody edits;
* *editing*: an editor changes one filler marking's weight (or, with
  ``--edit move``, moves it by about 10 cm) every ``--edit-every`` seconds
  (a PATCH, as the web editor sends).

Per phase it prints the answers' p50 / p99 / max latency, how many took over
250 ms, and how far behind the map's revision the answers were
(``X-Map-Revision`` against the revision of the last edit made before the
request was sent), and saves the editing phases' answers over time as a PNG
(``--png``, by default ``benchmarks/out/localize_during_edits.png``).

Usage::

    .venv/bin/python benchmarks/localize_during_edits.py [--markings 200000] [--coverage hull markings]
        [--duration 20] [--edit-every 1.0]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from load_localize import MAP_ID, load_map, make_bodies  # noqa: E402
from mapbuilder.model import Marking  # noqa: E402
from mapbuilder.store import Store  # noqa: E402
from tests._api_helpers import TOKEN, start_server  # noqa: E402

#: Where the filler city starts (EPSG:25832), 13 km east of the Karlsruhe example.
FILLER_E0, FILLER_N0 = 470_000.0, 5_425_000.0
STREET_SPACING_M = 80.0
SLOW_MS = 250.0


def filler_markings(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` x, y, bearing (degrees clockwise from north) of a jittered street grid."""
    # A street of length L holds 2 L / 3 solid pieces and L / 9 dashes.
    side = float(np.sqrt(n * STREET_SPACING_M / (2 * (2 / 3 + 1 / 9))))
    rows = []
    for c in np.arange(0.0, side, STREET_SPACING_M):
        for off, step in ((-3.5, 3.0), (3.5, 3.0), (0.0, 9.0)):
            t = np.arange(0.0, side, step)
            rows.append(np.c_[t, np.full_like(t, c + off), np.full_like(t, 90.0)])  # east-west
            rows.append(np.c_[np.full_like(t, c + off), t, np.zeros_like(t)])  # north-south
    pts = np.vstack(rows)
    rng = np.random.default_rng(seed)
    pts = pts[rng.permutation(len(pts))[:n]]
    pts[:, :2] += rng.normal(0.0, 0.05, (len(pts), 2)) + (FILLER_E0, FILLER_N0)
    return pts


def fill(url: str, n: int) -> list[int]:
    """Add ``n`` filler markings to the map; the ids of the first 1,000."""
    store = Store(url)
    try:
        pts = filler_markings(n)
        for s in range(0, n, 50_000):
            store.bulk_load(MAP_ID, (Marking(x=x, y=y, bearing_deg=b, length_m=3.0, width_m=0.12, weight=36,
                                             source="detected", score=0.9) for x, y, b in pts[s:s + 50_000]))
        page = store.query_bbox(MAP_ID, FILLER_E0 - 10, FILLER_N0 - 10, FILLER_E0 + 400, FILLER_N0 + 400)
        return [m.id for m in page[:1000]]
    finally:
        store.close()


#: Each edit sets a weight no edit set before: an edit that changes nothing moves no revision on.
_WEIGHTS = itertools.count(37)


def index_work(metrics: str) -> str:
    """The server's index builds and updates so far, from its ``/metrics``."""
    out = []
    for what, name in (("builds", "build"), ("updates", "update")):
        got = {k: float(v) for k, v in re.findall(rf"lanemap_index_{name}_duration_seconds_(count|sum) (\S+)", metrics)}
        n = int(got.get("count", 0))
        out.append(f"{n} {what}" + (f" (mean {got['sum'] / n:.2f} s)" if n else ""))
    return ", ".join(out)


class Editor(threading.Thread):
    """Changes a filler marking every ``every`` seconds: its weight, or (``move``) its place, by
    about 10 cm to and fro; keeps the revision of each edit."""

    def __init__(self, base: str, ids: list[int], every: float, move: bool = False):
        super().__init__(daemon=True)
        self.base, self.ids, self.every, self.move = base, ids, every, move
        self.stop = threading.Event()
        self.revisions: list[tuple[float, int]] = []  # (monotonic time answered, map revision after)
        self.errors = 0

    def run(self) -> None:
        headers = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/merge-patch+json"}
        with httpx.Client(base_url=self.base, timeout=30) as c:
            k = 0
            while not self.stop.wait(self.every):
                fid = self.ids[k % len(self.ids)]
                if self.move:
                    lon, lat = c.get(f"/collections/{MAP_ID}/items/{fid}").json()["geometry"]["coordinates"]
                    step = 1.4e-6 * (1 if (k // len(self.ids)) % 2 == 0 else -1)
                    change = {"geometry": {"type": "Point", "coordinates": [lon + step, lat]}}
                else:
                    change = {"properties": {"weight": next(_WEIGHTS)}}
                r = c.patch(f"/collections/{MAP_ID}/items/{fid}", headers=headers, content=json.dumps(change))
                if r.status_code != 200:
                    self.errors += 1
                    continue
                head = c.get(f"/collections/{MAP_ID}")
                self.revisions.append((time.monotonic(), int(head.json()["revision"])))
                k += 1

    def revision_before(self, t: float) -> int | None:
        before = [rev for at, rev in self.revisions if at <= t]
        return before[-1] if before else None


def drive(base: str, bodies: list[bytes], seconds: float, editor: Editor | None = None, timeline=None):
    """Closed loop for ``seconds``: latencies (ms), lags behind the last edit (revisions), statuses.

    ``timeline``, a list, gets ``(seconds since the start, latency ms, lag)`` of every answer.
    """
    lat, lags, statuses = [], [], {}
    start = time.monotonic()
    end = start + seconds
    k = 0
    with httpx.Client(base_url=base, timeout=120) as c:
        while time.monotonic() < end:
            sent = time.monotonic()
            r = c.post(f"/collections/{MAP_ID}/localize", content=bodies[k % len(bodies)],
                       headers={"Content-Type": "application/json"})
            lat.append((time.monotonic() - sent) * 1e3)
            key = str(r.status_code) if r.status_code != 200 else r.json()["status"]
            statuses[key] = statuses.get(key, 0) + 1
            lag = 0
            if editor is not None and r.status_code == 200:
                last = editor.revision_before(sent)
                if last is not None:
                    lag = max(0, last - int(r.headers["X-Map-Revision"]))
                    lags.append(lag)
            if timeline is not None:
                timeline.append((sent - start, lat[-1], lag))
            k += 1
    return np.array(lat), np.array(lags), statuses


def plot(runs: dict, png: Path) -> None:
    """Each coverage's editing phase: every answer's latency over time, coloured by how many edits it
    was behind, and the edits as vertical lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(runs), 1, figsize=(10, 3.2 * len(runs)), squeeze=False, sharex=True)
    for ax, (coverage, (timeline, edits)) in zip(axes[:, 0], runs.items()):
        t, ms, lag = np.array(timeline).T
        for at in edits:
            ax.axvline(at, color="0.85", lw=0.8, zorder=0)
        sc = ax.scatter(t, ms, c=lag, s=4, cmap="viridis", vmin=0, vmax=max(1, lag.max()))
        ax.set_yscale("log")
        ax.set_ylabel("answer latency, ms")
        ax.set_title(f"coverage {coverage}: an edit every grey line; p99 {np.percentile(ms, 99):.1f} ms, "
                     f"max {ms.max():.0f} ms", fontsize=10)
        fig.colorbar(sc, ax=ax, label="edits behind")
    axes[-1, 0].set_xlabel("seconds into the editing phase")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def report(name: str, lat: np.ndarray, lags: np.ndarray, statuses: dict, extra: str = "") -> None:
    lag = (f"; behind the last edit: {np.mean(lags > 0) * 100:.1f} % of answers, at most {lags.max()} revisions"
           if len(lags) else "")
    print(f"  {name:8s} {len(lat):5d} answers ({', '.join(f'{v} {k}' for k, v in sorted(statuses.items()))}): "
          f"p50 {np.percentile(lat, 50):.1f} ms, p99 {np.percentile(lat, 99):.1f} ms, max {lat.max():.0f} ms, "
          f"{int((lat > SLOW_MS).sum())} over {SLOW_MS:.0f} ms{lag}{extra}")


def city_map(url: str, markings: int) -> tuple[list[int], str]:
    """Load the Karlsruhe map and ``markings`` filler ones: the ids of the first 1,000 filler
    markings, and a line that says what was loaded and how long it took."""
    n = load_map(url)
    t = time.perf_counter()
    ids = fill(url, markings)
    return ids, (f"map {MAP_ID}: {n} Karlsruhe markings + {markings:,} filler ones "
                 f"(loaded in {time.perf_counter() - t:.0f} s)")


def city_arguments(ap: argparse.ArgumentParser, markings: int) -> None:
    """The options of the benchmarks on the filler city: its size and the coverages to run."""
    ap.add_argument("--markings", type=int, default=markings, help="filler markings beside the Karlsruhe ones")
    ap.add_argument("--coverage", nargs="+", default=["hull", "markings"], choices=("hull", "markings"))


def load_average() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg())


def header(title: str) -> str:
    """A run's first line: what, when, on how many cores, under what load."""
    return (f"lanemap {title}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
            f"load average {load_average()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    city_arguments(ap, 200_000)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per phase")
    ap.add_argument("--edit-every", type=float, default=1.0, help="seconds between the editor's edits")
    ap.add_argument("--edit", choices=("weight", "move"), default="weight",
                    help="what each edit changes: a marking's weight, or its place (about 10 cm)")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE", help="server settings")
    ap.add_argument("--png", type=Path, default=REPO / "benchmarks" / "out" / "localize_during_edits.png",
                    help="where the editing phases' latency timeline is saved")
    args = ap.parse_args()

    print(header("localization during edits"))
    bodies = make_bodies(args.frames, 7, 1.5, 2.0)
    tmp = Path(tempfile.mkdtemp(prefix="lanemap-edits-"))
    url = f"sqlite:///{tmp / 'lanemap.sqlite'}"
    try:
        ids, loaded = city_map(url, args.markings)
        print(f"{loaded}; an edit every {args.edit_every:g} s")
        runs: dict = {}
        for coverage in args.coverage:
            env = {"LANEMAP_MAP_COVERAGE": coverage, "LANEMAP_INDEX_PRELOAD": "0",
                   **dict(kv.split("=", 1) for kv in args.env)}
            server = start_server(url, tmp / "data", env=env, args=("--log-level", "warning"))
            try:
                print(f"\ncoverage {coverage} ({' '.join(f'{k}={v}' for k, v in env.items())})")
                t = time.monotonic()
                r = httpx.post(f"{server.base_url}/collections/{MAP_ID}/localize", content=bodies[0],
                               headers={"Content-Type": "application/json"}, timeout=300)
                print(f"  cold     first answer ({r.json()['status']}) after {(time.monotonic() - t) * 1e3:.0f} ms")
                report("quiet", *drive(server.base_url, bodies, args.duration))
                editor = Editor(server.base_url, ids, args.edit_every, move=args.edit == "move")
                timeline: list = []
                began = time.monotonic()
                editor.start()
                result = drive(server.base_url, bodies, args.duration, editor, timeline)
                editor.stop.set()
                editor.join()
                runs[coverage] = (timeline, [at - began for at, _ in editor.revisions])
                report("editing", *result, extra=f"; {len(editor.revisions)} edits ({editor.errors} refused)")
                print(f"  index    {index_work(httpx.get(f'{server.base_url}/metrics').text)}")
                if "Traceback" in server.log():
                    print("  server log has a traceback:\n" + server.log()[-3000:])
            finally:
                server.stop()
        plot(runs, args.png)
        print(f"\nplot: {args.png}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average at the end: {load_average()}")


if __name__ == "__main__":
    main()

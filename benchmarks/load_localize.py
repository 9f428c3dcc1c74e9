"""Load test of ``POST /collections/{mapId}/localize`` over loopback, at rising concurrency.

The map is the Karlsruhe Lanelet2 example laid out as lane markings (the
demo map's markings, 819 of them) in a fresh SQLite store (or a fresh
PostgreSQL database with ``--postgres URL``). The requests are camera frames
simulated by :mod:`localizer.simulate` on the same geometry: a forward camera
seeing 4–35 m ahead within ±40°, paper-like clutter (curbs, a preceding
vehicle, random false detections), 24–40 observations per frame (about 30),
and a GPS-like prior: the true pose moved by a random error of
``--gps-sigma`` metres per axis and ``--heading-sigma`` degrees, sent with
those sigmas.

For each server configuration (``--workers 1 2``) the script starts
``lanemap serve`` itself, warms every server process up (each builds its own
map index), and then runs each concurrency level (``--levels``) as a closed
loop: ``c`` clients, each on its own keep-alive connection, send the next
request as soon as the previous answer arrives, for ``--duration`` seconds.
Per level it prints throughput, p50/p90/p99 latency of the answered
localizations, errors (timeouts, resets, any status but 200 and 503), the
503s of the server's load shedding (``LANEMAP_LOCALIZE_MAX_PENDING``; the
client then waits ``Retry-After`` as a vehicle would), the median time the
localizer itself took and the time a request waited for a worker thread (the
server's ``Server-Timing`` header), the load generator's own CPU use, the CPU
seconds of each server process and the clients' connections each held
halfway through the level (how evenly ``--workers`` share the load: each
server process listens on its own ``SO_REUSEPORT`` socket and the kernel
spreads connections over them), and the load average; it marks the first level with errors, the first with
shedding, and the level where throughput stops growing (saturation).

The load generator (``--generator``) is either an asyncio ``httpx`` client in
this process (``python``, the default) or ``wrk`` (``wrk``: a C client, one
thread, with ``benchmarks/wrk_localize.lua`` cycling through the same
pre-generated bodies; Debian package ``wrk``). Both share the machine's cores
with the server; the generator's own CPU share is printed. The Python client
needs about a millisecond of CPU per request, which on 2 cores is capacity the
server loses; wrk needs a few percent of that, so it measures what the server
can do. With wrk, latency percentiles cover all answers (503s included); both
wait ``Retry-After`` after a 503.

Usage::

    .venv/bin/python benchmarks/load_localize.py [--workers 1 2] [--levels 1 2 4 8 16 32 64]
        [--duration 10] [--gps-sigma 1.5] [--heading-sigma 2] [--postgres URL] [--generator wrk]
    .venv/bin/python benchmarks/load_localize.py --prior-sweep   # localizer time vs prior, 1 client
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from localizer import GeoFrame  # noqa: E402
from localizer.simulate import Camera, Clutter, sample_poses, simulate_scene  # noqa: E402
from mapbuilder.lanelet2 import layout_markings, read_lanelet2  # noqa: E402
from mapbuilder.store import Store  # noqa: E402
from service.demo import DEMO_CRS, demo_osm  # noqa: E402
from tests._api_helpers import fresh_postgres_db, start_server  # noqa: E402
from tests._localizer_helpers import karlsruhe  # noqa: E402

MAP_ID = "karlsruhe"
#: A wide forward camera: about 30 markings per frame on the Karlsruhe map.
CAMERA = Camera(max_range_m=35.0, half_fov_deg=40.0)
TARGET_RPS, TARGET_P99_MS = 300.0, 50.0


def load_map(url: str) -> int:
    """Create the map ``karlsruhe`` with the laid-out Lanelet2 markings; their number."""
    store = Store(url)
    try:
        store.create_map(MAP_ID, "Karlsruhe (Lanelet2 example map)", DEMO_CRS)
        items = layout_markings(read_lanelet2(demo_osm(), crs=DEMO_CRS))
        return len(store.add_markings(MAP_ID, items, who="bench", comment="load benchmark"))
    finally:
        store.close()


def make_bodies(n: int, seed: int, gps_sigma: float, heading_sigma: float,
                min_obs: int = 24, max_obs: int = 40) -> list[bytes]:  # fmt: skip
    """``n`` request bodies: simulated frames with ``min_obs``–``max_obs`` observations."""
    _, smap = karlsruhe(str(demo_osm()))
    rng = np.random.default_rng(seed)
    frame = GeoFrame(DEMO_CRS)
    bodies: list[bytes] = []
    while len(bodies) < n:
        for pose in sample_poses(smap, 4 * n, rng, camera=CAMERA, min_visible=8):
            scene = simulate_scene(smap, pose, rng, CAMERA, Clutter())
            if not min_obs <= len(scene.observations) <= max_obs:
                continue
            ex, ey = rng.normal(0.0, gps_sigma, 2)
            lon, lat = frame.to_lonlat(pose[0] + ex, pose[1] + ey)
            yaw = pose[2] + math.radians(rng.normal(0.0, heading_sigma))
            heading = float(frame.grid_yaw_to_heading(yaw, lon, lat)) % 360.0
            body = {
                "gps": {"lat": lat, "lon": lon, "heading_deg": heading,
                        "position_sigma_m": gps_sigma, "heading_sigma_deg": heading_sigma},
                "observations": [{"x": round(float(x), 3), "y": round(float(y), 3), "weight": float(w)}
                                 for x, y, w in scene.observations],
            }  # fmt: skip
            bodies.append(json.dumps(body).encode())
            if len(bodies) == n:
                break
    return bodies


def load_frames(n: int = 200, seed: int = 7, gps_sigma: float = 1.5, heading_sigma: float = 2.0):
    """The bodies of :func:`make_bodies` as the localizer takes them: ``(observations (N, 3), Prior)`` pairs."""
    from localizer import Prior

    frames = []
    for body in make_bodies(n, seed, gps_sigma, heading_sigma):
        d = json.loads(body)
        g = d["gps"]
        frames.append((np.array([[o["x"], o["y"], o["weight"]] for o in d["observations"]]),
                       Prior(g["lat"], g["lon"], g["heading_deg"], g["position_sigma_m"],
                             g["heading_sigma_deg"])))  # fmt: skip
    return frames


@dataclass
class Level:
    concurrency: int
    seconds: float = 0.0
    latencies_ms: list[float] = field(default_factory=list)
    localize_ms: list[float] = field(default_factory=list)
    queue_ms: list[float] = field(default_factory=list)
    shed: int = 0
    statuses: dict[str, int] = field(default_factory=dict)
    errors: int = 0
    error_kinds: dict[str, int] = field(default_factory=dict)
    client_cpu: float = 0.0
    #: CPU seconds each server process used during the level, largest first
    server_cpu: list[float] = field(default_factory=list)
    #: established connections per server process halfway through, most first
    connections: list[int] = field(default_factory=list)
    load: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: with ``--generator wrk``: its latency percentiles (ms, all answers) and 200s
    wrk_pct: dict[float, float] | None = None
    wrk_ok: int = 0

    @property
    def ok(self) -> int:
        return self.wrk_ok if self.wrk_pct is not None else len(self.latencies_ms)

    @property
    def rps(self) -> float:
        return self.ok / self.seconds if self.seconds else 0.0

    def pct(self, q: float) -> float:
        if self.wrk_pct is not None:
            return self.wrk_pct.get(q, float("nan"))
        return float(np.percentile(self.latencies_ms, q)) if self.latencies_ms else float("nan")


def _server_timing(header: str | None) -> dict[str, float]:
    out = {}
    for part in (header or "").split(","):
        name, _, params = part.strip().partition(";")
        for p in params.split(";"):
            k, _, v = p.strip().partition("=")
            if k == "dur":
                out[name] = float(v)
    return out


async def run_level(base_url: str, bodies: list[bytes], c: int, duration: float, timeout: float,
                    server_pid: int | None = None) -> Level:  # fmt: skip
    """``c`` closed-loop clients for ``duration`` seconds.

    With ``server_pid``, the connections each server process holds are counted halfway through.
    """
    lvl = Level(c)
    url = f"{base_url}/collections/{MAP_ID}/localize"
    headers = {"Content-Type": "application/json"}
    limits = httpx.Limits(max_connections=c, max_keepalive_connections=c)
    async with httpx.AsyncClient(limits=limits, timeout=timeout) as client:
        stop = time.perf_counter() + duration

        async def worker(k: int) -> None:
            i = k
            while time.perf_counter() < stop:
                body = bodies[i % len(bodies)]
                i += c
                t0 = time.perf_counter()
                try:
                    r = await client.post(url, content=body, headers=headers)
                except httpx.HTTPError as exc:
                    lvl.errors += 1
                    name = type(exc).__name__
                    lvl.error_kinds[name] = lvl.error_kinds.get(name, 0) + 1
                    continue
                dt = (time.perf_counter() - t0) * 1000.0
                if r.status_code == 503:
                    # shed by the server: a well-behaved client waits as told
                    lvl.shed += 1
                    wait = float(r.headers.get("retry-after", "1"))
                    await asyncio.sleep(max(0.0, min(wait, stop - time.perf_counter())))
                    continue
                if r.status_code != 200:
                    lvl.errors += 1
                    lvl.error_kinds[str(r.status_code)] = lvl.error_kinds.get(str(r.status_code), 0) + 1
                    continue
                lvl.latencies_ms.append(dt)
                st = r.json()["status"]
                lvl.statuses[st] = lvl.statuses.get(st, 0) + 1
                timing = _server_timing(r.headers.get("server-timing"))
                if "localize" in timing:
                    lvl.localize_ms.append(timing["localize"])
                    lvl.queue_ms.append(timing.get("queue", 0.0))

        async def count_connections() -> None:
            await asyncio.sleep(duration / 2)
            port = int(base_url.rsplit(":", 1)[1])
            per_process = await asyncio.to_thread(_connections_by_process, server_pid, port)
            lvl.connections = sorted(per_process.values(), reverse=True)

        cpu0, t0 = time.process_time(), time.perf_counter()
        tasks = [worker(k) for k in range(c)] + ([count_connections()] if server_pid else [])
        await asyncio.gather(*tasks)
        lvl.seconds = time.perf_counter() - t0
        lvl.client_cpu = (time.process_time() - cpu0) / lvl.seconds
    lvl.load = os.getloadavg()
    return lvl


WRK_SCRIPT = REPO / "benchmarks" / "wrk_localize.lua"


def run_level_wrk(base_url: str, bodies_path: Path, c: int, duration: float, timeout: float,
                  server_pid: int | None = None) -> Level:  # fmt: skip
    """``c`` closed-loop connections of ``wrk`` (one thread) for ``duration`` seconds.

    The request bodies are read from ``bodies_path`` (one per line); latency
    percentiles are wrk's, over every answer (below saturation all are 200s).
    After a 503 the connection waits ``Retry-After`` (the script's ``delay()``).
    """
    import subprocess

    lvl = Level(c)
    env = dict(os.environ, LANEMAP_BODIES=str(bodies_path), LANEMAP_PATH=f"/collections/{MAP_ID}/localize")
    cmd = ["wrk", "-t", "1", "-c", str(c), "-d", f"{duration:g}s", "--timeout", f"{timeout:g}s",
           "-s", str(WRK_SCRIPT), base_url]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if server_pid:
        time.sleep(duration / 2)
        per_process = _connections_by_process(server_pid, int(base_url.rsplit(":", 1)[1]))
        lvl.connections = sorted(per_process.values(), reverse=True)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    line = next((ln for ln in out.splitlines() if ln.startswith("RESULT ")), None)
    if line is None:
        raise RuntimeError(f"wrk failed ({proc.returncode}):\n{out}")
    res = json.loads(line[len("RESULT "):])
    lvl.seconds = res["duration_us"] / 1e6
    lvl.client_cpu = (usage.ru_utime + usage.ru_stime) / lvl.seconds
    lvl.wrk_pct = {50: res["p50_us"] / 1e3, 90: res["p90_us"] / 1e3, 99: res["p99_us"] / 1e3}
    statuses = {int(k): v for k, v in res["statuses"].items()}
    lvl.wrk_ok = statuses.pop(200, 0)
    lvl.shed = statuses.pop(503, 0)
    errs = {k: v for k, v in res["errors"].items() if v and k != "status"}
    errs.update({str(k): v for k, v in statuses.items()})
    lvl.error_kinds = errs
    lvl.errors = sum(errs.values())
    if res["localize_p50_ms"] >= 0:
        lvl.localize_ms = [res["localize_p50_ms"]]
    lvl.statuses = {"200": lvl.wrk_ok}
    lvl.load = os.getloadavg()
    return lvl


def _connections_by_process(pid: int, port: int) -> dict[int, int]:
    """Established TCP connections to ``port`` held by each descendant of process ``pid``."""
    import psutil

    out = {}
    try:
        for p in psutil.Process(pid).children(recursive=True):
            try:
                n = sum(1 for k in p.net_connections("tcp")
                        if k.status == psutil.CONN_ESTABLISHED and k.laddr and k.laddr.port == port)  # fmt: skip
            except psutil.Error:
                continue
            if n:
                out[p.pid] = n
    except psutil.Error:
        pass
    return out


def _cpu_by_process(pid: int) -> dict[int, float]:
    """User + system CPU seconds of a process and each of its descendants."""
    import psutil

    out = {}
    try:
        root = psutil.Process(pid)
        for p in [root, *root.children(recursive=True)]:
            try:
                t = p.cpu_times()
                out[p.pid] = t.user + t.system
            except psutil.Error:
                pass
    except psutil.Error:
        pass
    return out


def warm_up(base_url: str, bodies: list[bytes], workers: int) -> None:
    """Every server process builds its map index before timing starts."""
    asyncio.run(run_level(base_url, bodies, max(4, 4 * workers), 3.0 + workers, 60.0))


def print_levels(levels: list[Level], workers: int) -> None:
    print(f"\n  {'clients':>7s} {'req/s':>7s} {'p50 ms':>7s} {'p90 ms':>7s} {'p99 ms':>7s} {'errors':>6s} "
          f"{'503 shed':>8s} {'localizer p50 ms':>16s} {'thread wait p50':>15s} {'client CPU':>10s} "
          f"{'server CPU s':>12s} {'conns':>7s} {'load 1m':>7s}  notes")  # fmt: skip
    best = 0.0
    first_error = first_shed = None
    saturated = None
    for k, lv in enumerate(levels):
        notes = []
        if lv.errors and first_error is None:
            first_error = lv.concurrency
            notes.append(f"ERRORS START {lv.error_kinds}")
        elif lv.errors:
            notes.append(str(lv.error_kinds))
        if lv.shed and first_shed is None:
            first_shed = lv.concurrency
            notes.append("503 load shedding starts")
        if k and saturated is None and lv.rps < 1.05 * max(x.rps for x in levels[:k]):
            saturated = lv.concurrency
            notes.append("saturated (throughput no longer grows)")
        if lv.pct(99) <= TARGET_P99_MS and not lv.errors and not lv.shed:
            best = max(best, lv.rps)
        loc = float(np.median(lv.localize_ms)) if lv.localize_ms else float("nan")
        wait = float(np.median(lv.queue_ms)) if lv.queue_ms else float("nan")
        print(f"  {lv.concurrency:7d} {lv.rps:7.1f} {lv.pct(50):7.1f} {lv.pct(90):7.1f} {lv.pct(99):7.1f} "
              f"{lv.errors:6d} {lv.shed:8d} {loc:16.1f} {wait:15.1f} {100 * lv.client_cpu:9.0f}% "
              f"{'+'.join(f'{x:.1f}' for x in lv.server_cpu[:workers]):>12s} "
              f"{'+'.join(str(x) for x in lv.connections):>7s} "
              f"{lv.load[0]:7.2f}  {'; '.join(notes)}")  # fmt: skip
    statuses: dict[str, int] = {}
    for lv in levels:
        for s, n in lv.statuses.items():
            statuses[s] = statuses.get(s, 0) + n
    print(f"  answers: {statuses}")
    print(f"  errors (timeouts, resets, 4xx/5xx other than 503): "
          f"{'none at any level' if first_error is None else f'from {first_error} clients on'}; "
          f"503 load shedding: {'never' if first_shed is None else f'from {first_shed} clients on'}")
    verdict = "MET" if best >= TARGET_RPS else "NOT MET"
    print(f"  best throughput with p99 <= {TARGET_P99_MS:.0f} ms and no errors: {best:.1f} req/s "
          f"(target {TARGET_RPS:.0f}: {verdict}); peak {max(lv.rps for lv in levels):.1f} req/s "
          f"with {workers} worker(s)")  # fmt: skip


def prior_sweep(base_url: str, n: int, seed: int, duration: float) -> None:
    """One client: how the prior's uncertainty drives the localizer's time."""
    print("\nprior sweep, 1 client (sent sigma = true error sigma):")
    print(f"  {'position σ m':>12s} {'heading σ °':>11s} {'req/s':>7s} {'p50 ms':>7s} {'p99 ms':>7s} "
          f"{'localizer p50 ms':>16s}  answers")  # fmt: skip
    for ps, hs in ((5.0, 10.0), (3.0, 5.0), (1.5, 2.0), (0.5, 1.0)):
        bodies = make_bodies(n, seed, ps, hs)
        lv = asyncio.run(run_level(base_url, bodies, 1, duration, 60.0))
        loc = float(np.median(lv.localize_ms)) if lv.localize_ms else float("nan")
        print(f"  {ps:12.1f} {hs:11.1f} {lv.rps:7.1f} {lv.pct(50):7.1f} {lv.pct(99):7.1f} {loc:16.1f}  "
              f"{lv.statuses}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="server processes, one run each")
    ap.add_argument("--levels", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64], help="concurrent clients")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per level")
    ap.add_argument("--timeout", type=float, default=10.0, help="client timeout per request, seconds")
    ap.add_argument("--frames", type=int, default=200, help="distinct simulated frames, sent in turn")
    ap.add_argument("--gps-sigma", type=float, default=1.5, help="GPS position error sigma per axis, metres")
    ap.add_argument("--heading-sigma", type=float, default=2.0, help="GPS heading error sigma, degrees")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--postgres", default=None, help="use a fresh database on this PostgreSQL server")
    ap.add_argument("--prior-sweep", action="store_true", help="also time 1 client over four priors")
    ap.add_argument("--generator", choices=("python", "wrk"), default="python",
                    help="load generator: this process's asyncio client, or wrk (C, needs the wrk binary)")
    args = ap.parse_args()
    if args.generator == "wrk" and shutil.which("wrk") is None:
        ap.error("--generator wrk: no wrk on PATH (Debian: apt-get install wrk)")

    print(f"lanemap localization load test, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{os.cpu_count()} cores, load average {'/'.join(f'{v:.2f}' for v in os.getloadavg())}")  # fmt: skip
    bodies = make_bodies(args.frames, args.seed, args.gps_sigma, args.heading_sigma)
    nobs = [len(json.loads(b)["observations"]) for b in bodies]
    print(f"{len(bodies)} frames, observations per frame min/median/max {min(nobs)}/{int(np.median(nobs))}/"
          f"{max(nobs)}; prior sigma {args.gps_sigma} m, {args.heading_sigma}°; "
          f"load generator: {args.generator}")  # fmt: skip
    bodies_dir = Path(tempfile.mkdtemp(prefix="lanemap-load-bodies-"))
    bodies_path = bodies_dir / "bodies.jsonl"
    bodies_path.write_bytes(b"\n".join(bodies) + b"\n")
    for workers in args.workers:
        tmp = Path(tempfile.mkdtemp(prefix="lanemap-load-"))
        drop = None
        if args.postgres:
            os.environ["LANEMAP_TEST_POSTGRES_URL"] = args.postgres
            url, drop = fresh_postgres_db()
        else:
            url = f"sqlite:///{tmp / 'lanemap.sqlite'}"
        n = load_map(url)
        server = start_server(url, tmp / "data", args=("--workers", str(workers), "--log-level", "warning"))
        try:
            print(f"\nlanemap serve --workers {workers} ({'PostgreSQL' if args.postgres else 'SQLite'}, "
                  f"{n} markings), {args.duration:g} s per level")  # fmt: skip
            warm_up(server.base_url, bodies, workers)
            levels = []
            for c in args.levels:
                before = _cpu_by_process(server.proc.pid)
                if args.generator == "wrk":
                    levels.append(run_level_wrk(server.base_url, bodies_path, c, args.duration, args.timeout,
                                                server.proc.pid))  # fmt: skip
                else:
                    levels.append(asyncio.run(run_level(server.base_url, bodies, c, args.duration,
                                                        args.timeout, server.proc.pid)))  # fmt: skip
                lv = levels[-1]
                after = _cpu_by_process(server.proc.pid)
                lv.server_cpu = sorted((after[p] - before.get(p, 0.0) for p in after), reverse=True)
                print(f"    {c} clients: {lv.rps:.1f} req/s, p99 {lv.pct(99):.1f} ms, {lv.errors} errors",
                      file=sys.stderr, flush=True)  # fmt: skip
            print_levels(levels, workers)
            if args.prior_sweep and workers == args.workers[0]:
                prior_sweep(server.base_url, min(args.frames, 100), args.seed, args.duration)
            if "Traceback" in server.log():
                print("  server log has a traceback:\n" + server.log()[-3000:])
        finally:
            server.stop()
            if drop is not None:
                drop()
            shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(bodies_dir, ignore_errors=True)
    print(f"\nload average at the end: {'/'.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()

"""Scale of a map build: a ~2 Gpx image on a Dask cluster of two local worker processes.

Rendering 2 Gpx with :mod:`mapbuilder.synth` would take most of an hour on two
cores, so the image is a mosaic (``make_mosaic`` of ``build_throughput.py``):
one procedural scene of 204.8 m x 204.8 m at 10 cm (2048 x 2048 px, roads,
lane markings, parking lots, cars, trees, buildings) rendered once, then
written side by side in its 8 rotations/mirrorings into a tiled,
JPEG-compressed BigTIFF of ``--mpx`` megapixels (default 2,000: 22 x 22 cells,
45,056 px square, 4.5 km x 4.5 km). Every cell has the same content; the script
prints the number of true markings in the image (the cell's true markings
times the cells) beside the number found.

Then, without LocalCluster, the deployment's topology: a ``dask scheduler``
process, two ``dask worker`` processes (``--nthreads``, default 1, each with
its nanny), and ``lanemap build IMAGE --map M --dask ADDRESS`` as a separate
process writing to a fresh SQLite file (or ``--postgres URL``). While it runs,
the resident memory of each worker process (and of its nanny), of the
scheduler and of the build client is sampled with psutil. It prints the wall
time, Mpx/s, peak memory per process, markings found and the load average.

Usage::

    .venv/bin/python benchmarks/scale_build.py [--mpx 2000] [--nthreads 1] [--postgres URL]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import rasterio

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "out"
BIN = Path(sys.executable).parent


def _throughput_module():
    spec = importlib.util.spec_from_file_location("build_throughput", REPO / "benchmarks" / "build_throughput.py")
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(REPO))
    spec.loader.exec_module(mod)
    return mod


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RSSSampler:
    """Peak resident memory of named processes (and of each one's children), sampled in a thread."""

    def __init__(self, procs: dict[str, psutil.Process], interval: float = 0.25):
        self.procs = procs
        self.interval = interval
        self.peak: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        for name, proc in list(self.procs.items()):
            try:
                kids = proc.children(recursive=True)
                own = proc.memory_info().rss
            except psutil.Error:
                continue
            sizes = []
            for kid in kids:
                try:
                    sizes.append(kid.memory_info().rss)
                except psutil.Error:
                    pass
            for key, v in ((name, own), (f"{name}: largest child", max(sizes, default=0)),
                           (f"{name}: whole tree", own + sum(sizes))):  # fmt: skip
                if v:
                    self.peak[key] = max(self.peak.get(key, 0), v)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            time.sleep(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def wait_for_workers(address: str, n: int, timeout: float = 120.0) -> None:
    from distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(n, timeout=timeout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpx", type=float, default=2000.0, help="image size, megapixels")
    ap.add_argument("--nthreads", type=int, default=1, help="threads per dask worker")
    ap.add_argument("--tile-size", type=int, default=1024)
    ap.add_argument("--postgres", default=None, help="build into a fresh database on this PostgreSQL server")
    ap.add_argument("--keep-image", action="store_true", help="keep the mosaic under benchmarks/out/")
    args = ap.parse_args()

    OUT.mkdir(parents=True, exist_ok=True)
    bt = _throughput_module()
    t0 = time.perf_counter()
    image = bt.make_mosaic(OUT / f"scale_{int(args.mpx)}mpx.tif", args.mpx)
    with rasterio.open(image) as ds:
        width, height = ds.width, ds.height
    cells = (width // bt.CELL_PX) * (height // bt.CELL_PX)
    truth_file = OUT / "throughput_cell.truth.geojson"
    from mapbuilder.synth import read_truth_geojson

    truth_per_cell = len(read_truth_geojson(truth_file)) if truth_file.exists() else None
    print(f"image {image.name}: {width} x {height} px = {width * height / 1e6:.0f} Mpx "
          f"({image.stat().st_size / 2**20:.0f} MiB JPEG), {cells} copies of one 2048 px cell; "
          f"ready in {time.perf_counter() - t0:.0f} s")  # fmt: skip

    tmp = Path(tempfile.mkdtemp(prefix="lanemap-scale-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    # One thread per worker thread: numeric libraries must not oversubscribe the cores.
    env.update(PYTHONPATH=str(REPO), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               LANEMAP_DATA_DIR=str(tmp / "data"), PYTHONUNBUFFERED="1")  # fmt: skip
    drop = None
    if args.postgres:
        os.environ["LANEMAP_TEST_POSTGRES_URL"] = args.postgres
        sys.path.insert(0, str(REPO))
        from tests._api_helpers import fresh_postgres_db

        env["LANEMAP_DATABASE_URL"], drop = fresh_postgres_db()
    else:
        env["LANEMAP_DATABASE_URL"] = f"sqlite:///{tmp / 'lanemap.sqlite'}"
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []
    logs = {name: open(tmp / f"{name}.log", "wb") for name in ("scheduler", "worker1", "worker2")}
    try:
        procs.append(subprocess.Popen(
            [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            env=env, cwd=tmp, stdout=logs["scheduler"], stderr=subprocess.STDOUT))  # fmt: skip
        time.sleep(2.0)
        for name in ("worker1", "worker2"):
            procs.append(subprocess.Popen(
                [str(BIN / "dask"), "worker", address, "--nthreads", str(args.nthreads), "--nworkers", "1",
                 "--name", name, "--no-dashboard", "--memory-limit", "0", "--local-directory", str(tmp)],
                env=env, cwd=tmp, stdout=logs[name], stderr=subprocess.STDOUT))  # fmt: skip
        wait_for_workers(address, 2)
        print(f"dask scheduler at {address}; 2 dask workers x {args.nthreads} thread(s), each with a nanny")
        watched = {"scheduler": psutil.Process(procs[0].pid), "worker1 nanny": psutil.Process(procs[1].pid),
                   "worker2 nanny": psutil.Process(procs[2].pid)}  # fmt: skip
        cmd = [sys.executable, "-m", "service.cli", "build", str(image), "--map", "scale", "--dask", address,
               "--tile-size", str(args.tile_size)]  # fmt: skip
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        loads = []
        build = subprocess.Popen(cmd, env=env, cwd=tmp, stdout=subprocess.PIPE, text=True)
        watched["lanemap build"] = psutil.Process(build.pid)
        with RSSSampler(watched) as rss:
            while build.poll() is None:
                loads.append(os.getloadavg()[0])
                time.sleep(1.0)
        wall = time.perf_counter() - t0
        out = build.stdout.read()
        if build.returncode != 0:
            raise SystemExit(f"lanemap build failed ({build.returncode}):\n{out}")
        m = re.search(r"(\d+) markings from (\d+) tiles", out)
        markings = int(m.group(1)) if m else -1
        mpx = width * height / 1e6
        print(f"\n{out.strip()}")
        print(f"\nwall time {wall:.0f} s for {mpx:.0f} Mpx: {mpx / wall:.2f} Mpx/s "
              f"(lanemap build process, start to exit)")  # fmt: skip
        print(f"markings found: {markings}"
              + (f"; the image holds {truth_per_cell * cells} true markings ({truth_per_cell} per cell x "
                 f"{cells} cells): {markings / (truth_per_cell * cells):.2f} found per true marking"
                 if truth_per_cell else ""))  # fmt: skip
        print("peak resident memory:")
        for name in sorted(rss.peak):
            label = name.replace("nanny: largest child", "(the worker process)")
            print(f"  {label:34s} {rss.peak[name] / 2**20:8.0f} MiB")
        print(f"load average: before {load0[0]:.2f}, during median {sorted(loads)[len(loads) // 2]:.2f} "
              f"max {max(loads):.2f}; {os.cpu_count()} cores; "
              f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")  # fmt: skip
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for fh in logs.values():
            fh.close()
        if drop is not None:
            drop()
        shutil.rmtree(tmp, ignore_errors=True)
        if not args.keep_image:
            image.unlink(missing_ok=True)


if __name__ == "__main__":
    main()

"""Throughput and memory of ``build_map`` on a large image.

Makes (once, cached under ``benchmarks/out/``) a tiled, JPEG-compressed
GeoTIFF of about ``--mpx`` megapixels at 10 cm by mosaicking a rendered
procedural scene, then measures on the same file:

* a plain windowed read of every tile window (core + halo), one process;
* the end-to-end build (read, classify, cluster, store) on all local cores.

It prints Mpx/s of both, their ratio, the markings found, the peak resident
memory of the whole process tree during the build (parent + workers; and
the parent's and the largest worker's own peaks), and
the machine load. On a machine shared with other work the wall time depends
on that work; the CPU seconds of the workers' tiles and of the parent do
much less, and ``mpx_per_s_on_2_idle_cores`` is what they come to on two
cores of its own (the parent's time included). Usage::

    .venv/bin/python benchmarks/build_throughput.py --mpx 400
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import rasterio
from rasterio.transform import from_origin
from rasterio.windows import Window

from mapbuilder import synth
from mapbuilder.build import BuildParams, build_map, default_threshold, default_threshold_low
from mapbuilder.cluster import ClusterParams
from mapbuilder.raster import inspect_imagery, make_reader
from mapbuilder.store import Store
from mapbuilder.tiling import tile_grid

OUT = Path(__file__).resolve().parent / "out"
CRS = "EPSG:25832"
CELL_PX = 2048


def make_mosaic(path: Path, mpx: float, resolution_m: float = 0.1) -> Path:
    """A ``side`` x ``side`` GeoTIFF tiled from flipped/rotated copies of one render."""
    side = int(round(np.sqrt(mpx * 1e6) / CELL_PX)) * CELL_PX
    if path.exists():
        with rasterio.open(path) as ds:
            if ds.width == side:
                return path
    cell_tif = path.with_name("throughput_cell.tif")
    size_m = CELL_PX * resolution_m
    scene = synth.procedural_scene(size_m=(size_m, size_m), origin=(456000.0, 5430000.0),
                                   seed=5, road_spacing_m=60.0)
    synth.render(scene, cell_tif, resolution_m, seed=5)
    with rasterio.open(cell_tif) as ds:
        cell = ds.read(window=Window(0, 0, CELL_PX, CELL_PX))
    profile = dict(
        driver="GTiff", width=side, height=side, count=3, dtype="uint8", crs=CRS,
        transform=from_origin(456000.0, 5430000.0, resolution_m, resolution_m),
        tiled=True, blockxsize=512, blockysize=512, compress="JPEG", jpeg_quality=90,
        photometric="YCBCR", BIGTIFF="YES",
    )
    n = side // CELL_PX
    tmp = path.with_suffix(".partial.tif")
    with rasterio.open(tmp, "w", **profile) as dst:
        for i in range(n):
            for j in range(n):
                k = (i * n + j) % 8
                block = np.rot90(cell, k % 4, axes=(1, 2))
                if k >= 4:
                    block = block[:, :, ::-1]
                dst.write(np.ascontiguousarray(block),
                          window=Window(j * CELL_PX, i * CELL_PX, CELL_PX, CELL_PX))
    tmp.rename(path)
    return path


def plain_read(path: Path, params: BuildParams) -> tuple[float, float, float]:
    """Seconds, Mpx and CPU seconds of reading every tile window (core + halo) once, one process."""
    info = inspect_imagery(path)
    grid = info.grid
    tiles = tile_grid(grid.width, grid.height, params.tile_px, params.halo_px(grid.resolution_m))
    reader = make_reader(path, grid)
    t0 = time.perf_counter()
    c0 = time.process_time()
    total = 0
    for t in tiles:
        rgb, valid = reader.read(t.read_window)
        total += int(valid.sum() > 0)
    reader.close()
    return time.perf_counter() - t0, grid.width * grid.height / 1e6, time.process_time() - c0


class TreeRSS:
    """Samples the resident memory of this process and all its descendants."""

    def __init__(self, interval: float = 0.1):
        self.interval = interval
        self.peak = 0
        self.peak_parent = 0
        self.peak_child = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        me = psutil.Process()
        while not self._stop.is_set():
            total = 0
            for p in [me, *me.children(recursive=True)]:
                try:
                    rss = p.memory_info().rss
                except psutil.Error:
                    continue
                total += rss
                if p.pid == me.pid:
                    self.peak_parent = max(self.peak_parent, rss)
                else:
                    self.peak_child = max(self.peak_child, rss)
            self.peak = max(self.peak, total)
            time.sleep(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpx", type=float, default=400.0, help="image size, megapixels")
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--tile-size", type=int, default=BuildParams.tile_px)
    ap.add_argument("--model", default=None, help="ONNX model (default: shipped model)")
    ap.add_argument("--threshold", type=float, default=None,
                    help="pixel threshold (default: as lanemap build)")
    ap.add_argument("--verify", action=argparse.BooleanOptionalAction, default=None,
                    help="check clusters with the cluster verifier (default: yes, as lanemap build)")
    ap.add_argument("--verifier", default=None, help="ONNX cluster verifier (default: shipped)")
    ap.add_argument("--hysteresis", action=argparse.BooleanOptionalAction, default=True,
                    help="hysteresis at the build's default low threshold (default: yes)")
    args = ap.parse_args()

    OUT.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    image = make_mosaic(OUT / f"throughput_{int(args.mpx)}mpx.tif", args.mpx)
    print(f"image {image} ready in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    # The defaults of `lanemap build`: verified clusters at the verifier's threshold.
    verify = True if args.verify is None else args.verify
    threshold = args.threshold if args.threshold is not None else default_threshold(verify, args.verifier)
    threshold_low = (default_threshold_low(verify, args.verifier, threshold)
                     if args.hysteresis else None)
    params = BuildParams(tile_px=args.tile_size, model=args.model,
                         cluster=ClusterParams(threshold=threshold, threshold_low=threshold_low,
                                               verify=verify),
                         verifier=args.verifier)

    load_before = os.getloadavg()
    # In a child process, so that its memory does not count against the build.
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=ctx) as pool:
        read_s, mpx, read_cpu = pool.submit(plain_read, image, params).result()
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(f"sqlite:///{tmp}/bench.sqlite")
        with TreeRSS() as rss:
            pc0 = time.process_time()
            result = build_map(store, "bench", [image], params, workers=args.workers)
            parent_cpu = time.process_time() - pc0
        store.close()
    load_after = os.getloadavg()
    figures = {
        "image_mpx": round(mpx, 1),
        "tile_px": args.tile_size,
        "workers": args.workers,
        "plain_read_s": round(read_s, 2),
        "plain_read_mpx_per_s": round(mpx / read_s, 1),
        "plain_read_cpu_s": round(read_cpu, 2),
        "build_s": round(result.seconds, 2),
        "build_mpx_per_s": round(result.mpx_per_s, 2),
        "build_to_read_time_ratio": round(result.seconds / read_s, 1),
        # CPU time does not grow with the load of other work the way wall time does
        "tile_cpu_s": round(result.cpu_seconds, 1),
        "tile_cpu_s_per_mpx": round(result.cpu_seconds / mpx, 4),
        "parent_cpu_s": round(parent_cpu, 1),
        # all the CPU the build used (workers' tiles + the parent's store writes) over two cores
        "mpx_per_s_on_2_idle_cores": round(
            2 * mpx / max(result.cpu_seconds + parent_cpu, 1e-9), 2),
        "markings": result.markings,
        "threshold": params.cluster.threshold,
        "threshold_low": params.cluster.threshold_low,
        "verify": params.cluster.verify,
        "verifier": Path(params.verifier).name if params.verifier else None,
        "tile_cpu_share": {k: round(v / max(sum(result.timings.values()), 1e-9), 3)
                           for k, v in result.timings.items()},
        "classify_mpx_per_s_per_process": round(
            mpx / max(result.timings.get("classify", 0.0), 1e-9), 2),
        "read_mpx_per_s_per_process": round(mpx / max(result.timings.get("read", 0.0), 1e-9), 1),
        "cluster_mpx_per_s_per_process": round(
            mpx / max(result.timings.get("cluster", 0.0), 1e-9), 1),
        "peak_rss_tree_mb": round(rss.peak / 2**20),
        "peak_rss_parent_mb": round(rss.peak_parent / 2**20),
        "peak_rss_largest_worker_mb": round(rss.peak_child / 2**20),
        "load_avg_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
        "cpus": os.cpu_count(),
    }
    for k, v in figures.items():
        print(f"{k:>28}: {v}")
    (OUT / "build_throughput.json").write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()

"""The map-building job: imagery in, detected markings in the store.

:func:`process_tile` is the unit of work: it takes plain data (an image path,
the pixel grid, a tile's windows, the model path and the clustering
parameters), reads one window, classifies it, clusters and measures the
marking pixels, and returns the markings whose centroid lies in the tile's
core. It runs in the calling process, in a local process pool, or on a Dask
distributed cluster; tasks never carry open datasets.

:func:`build_map` plans the tiles of one or more images, runs them, and
writes each tile's markings through :meth:`Store.replace_detected` in the
parent process (one transaction per tile, which also records the tile as done
for the job). Running it again with the same map, images and parameters
resumes the unfinished job and skips the tiles already done; a finished build
run again replaces its detected, unreviewed markings and keeps everything a
person decided on.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections import OrderedDict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
import multiprocessing as mp
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from rasterio.windows import Window
from rasterio.windows import transform as window_transform

from .cluster import ClusterParams, Clusters, detect_markings
from .crs import meridian_convergence_deg, to_wgs84
from .model import Marking
from .raster import (
    GridReader,
    ImageryError,
    PixelGrid,
    default_storage_crs,
    imaged_ground,
    inspect_imagery,
    make_reader,
)
from .tiling import image_tag, tile_grid, tile_key

log = logging.getLogger(__name__)

JOB_KIND = "build"


class BuildError(ValueError):
    """A build cannot start or cannot go on (bad parameters, unusable map or imagery)."""


@dataclass(frozen=True)
class BuildParams:
    """Parameters of a build; a resumed build must use the same ones.

    Attributes
    ----------
    tile_px : int
        Core size of a tile, pixels. 2048 rather than 1024 cuts the share of
        halo pixels read and classified twice from 16 % to 8 % (4 m halo at
        10 cm) and about 12 % of the CPU time of a build; a two-worker build of a
        419 Mpx image then peaked at 1.3 GB for the whole process tree.
    halo_m : float
        Halo read around every core, metres. It must exceed the longest piece
        a marking is cut into (``cluster.max_length_m * cluster.split_factor``)
        so that every marking owned by a tile is seen whole.
    model : str, model object or None
        ONNX model file; None uses the default model shipped with lanemap. An
        object with the ``predict(rgb, valid, resolution_m)`` method of
        :class:`mapbuilder.classify.MarkingModel` is used as is (it must be
        picklable to run in worker processes).
    cluster : ClusterParams
        Thresholding, clustering, splitting and filtering.
    verifier : str or None
        ONNX cluster verifier (:class:`mapbuilder.classify.ClusterVerifier`);
        None uses the one shipped with lanemap. Used when ``cluster.verify``.
    """

    tile_px: int = 2048
    halo_m: float = 4.0
    model: Any = None
    cluster: ClusterParams = field(default_factory=ClusterParams)
    verifier: str | None = None

    def __post_init__(self):
        if self.tile_px < 64:
            raise BuildError(f"tile size must be at least 64 pixels, got {self.tile_px}")
        longest = self.cluster.max_length_m * self.cluster.split_factor
        if self.halo_m <= longest:
            raise BuildError(
                f"halo {self.halo_m} m must exceed the longest marking piece ({longest:.2f} m)"
            )
        if isinstance(self.model, (str, os.PathLike)):
            path = Path(self.model)
            if not path.is_file():
                raise BuildError(f"model file not found: {path}")
            object.__setattr__(self, "model", str(path.resolve()))
        if self.verifier is not None:
            path = Path(self.verifier)
            if not path.is_file():
                raise BuildError(f"verifier file not found: {path}")
            object.__setattr__(self, "verifier", str(path.resolve()))

    def halo_px(self, resolution_m: float) -> int:
        return int(math.ceil(self.halo_m / resolution_m))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form, stored with the job to recognise a resumable build."""
        model = self.model
        if model is not None and not isinstance(model, str):
            model = f"{type(model).__module__}.{type(model).__qualname__}"
        return {
            "tile_px": self.tile_px,
            "halo_m": self.halo_m,
            "model": model,
            "cluster": asdict(self.cluster),
            "verifier": self.verifier if self.cluster.verify else None,
        }


@dataclass(frozen=True)
class TileTask:
    """Everything a worker needs to process one tile (plain, picklable data)."""

    path: str
    grid: PixelGrid
    key: str
    core: tuple[int, int, int, int]
    read: tuple[int, int, int, int]
    model: Any
    cluster: ClusterParams
    verifier: str | None = None

    @property
    def megapixels(self) -> float:
        return self.core[2] * self.core[3] / 1e6


@dataclass
class TileResult:
    """What a worker returns for one tile."""

    key: str
    markings: list[Marking]
    megapixels: float
    seconds: float
    #: Seconds spent reading, classifying, and clustering + measuring.
    timings: dict[str, float] = field(default_factory=dict)
    #: CPU seconds of the worker process on this tile (all its threads).
    cpu_seconds: float = 0.0
    #: The ground the tile's core images, WKB in the map's CRS (:func:`imaged_ground`).
    ground: bytes | None = None


@dataclass
class BuildResult:
    """Summary of a build.

    Attributes
    ----------
    map_id : str
    job_id : int
    images : list of str
    tiles_total : int
        Tiles of all images.
    tiles_skipped : int
        Tiles already done by the interrupted job this build resumed.
    tiles_run : int
        Tiles processed by this run.
    markings : int
        Markings stored by this run (after dropping those a person's decision overrides).
    megapixels : float
        Pixels processed by this run, millions.
    seconds : float
        Wall time of this run, including starting workers.
    resumed : bool
    timings : dict
        Seconds summed over this run's tiles: ``read``, ``classify``, ``cluster``.
    cpu_seconds : float
        CPU seconds the workers spent on this run's tiles; unlike wall time,
        it hardly depends on what else the machine is running.
    verified : bool
        Whether the cluster verifier checked the detections.
    threshold : float or None
        The pixel threshold of the build.
    threshold_low : float or None
        Its hysteresis threshold (pixels above it joined to a marking), if any.
    """

    map_id: str
    job_id: int
    images: list[str]
    tiles_total: int
    tiles_skipped: int
    tiles_run: int
    markings: int
    megapixels: float
    seconds: float
    resumed: bool
    timings: dict[str, float] = field(default_factory=dict)
    cpu_seconds: float = 0.0
    verified: bool = False
    threshold: float | None = None
    threshold_low: float | None = None

    @property
    def mpx_per_s(self) -> float:
        return self.megapixels / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        resumed = f", {self.tiles_skipped} resumed" if self.tiles_skipped else ""
        check = "verified" if self.verified else "not verified"
        at = f" at pixel threshold {self.threshold:g}" if self.threshold is not None else ""
        if at and self.threshold_low is not None:
            at += f" (hysteresis {self.threshold_low:g})"
        return (
            f"map {self.map_id}: {self.markings} markings from {self.tiles_run} tiles"
            f"{resumed} of {len(self.images)} image(s), {self.megapixels:.1f} Mpx in "
            f"{self.seconds:.1f} s ({self.mpx_per_s:.1f} Mpx/s), {check}{at}, job {self.job_id}"
        )


# --------------------------------------------------------------------------- the tile function

_READERS: "OrderedDict[tuple, GridReader]" = OrderedDict()
_MODELS: dict[Any, Any] = {}

#: Most tiles a worker processes in one go (neighbours along a row).
MAX_RUN = 8

#: GDAL block cache per process while building, MB. GDAL's default (5 % of RAM)
#: would let every worker cache most of a large image; tiles are read once.
GDAL_CACHE_MB = 128
_cache_limited = False


def _limit_gdal_cache() -> None:
    """Cap GDAL's block cache in this process, unless the user set GDAL_CACHEMAX."""
    global _cache_limited
    if _cache_limited:
        return
    _cache_limited = True
    if "GDAL_CACHEMAX" not in os.environ:
        from rasterio.env import set_gdal_config

        set_gdal_config("GDAL_CACHEMAX", GDAL_CACHE_MB * 2**20)  # bytes: a bare 128 is 128 bytes


_malloc_tuned = False


def _restore_malloc_thresholds() -> None:
    """Give glibc's allocator back the thresholds a ``MALLOC_TRIM_THRESHOLD_`` took away.

    Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536``
    (its default ``pre-spawn-environ``). Setting that variable turns off glibc's
    adaptive mmap threshold, so each array over 128 KiB is mapped and unmapped
    afresh and its pages faulted in again: the same tiles took 1.7 times the
    CPU on such a worker. This sets the thresholds the adaptive rule would reach
    (the mmap threshold at its 32 MiB ceiling, trimming above twice that).
    """
    global _malloc_tuned
    if _malloc_tuned:
        return
    _malloc_tuned = True
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    libc.mallopt(m_mmap_threshold, 32 * 2**20)
    libc.mallopt(m_trim_threshold, 64 * 2**20)
    log.debug("malloc thresholds restored (MALLOC_TRIM_THRESHOLD_ was %s)",
              os.environ["MALLOC_TRIM_THRESHOLD_"])


def _reader(path: str, grid: PixelGrid) -> GridReader:
    """An open reader, kept per process; a file rewritten since is opened afresh."""
    st = os.stat(path)
    key = (path, st.st_mtime_ns, st.st_size, grid)
    reader = _READERS.get(key)
    if reader is None:
        reader = make_reader(path, grid)
        _READERS[key] = reader
        while len(_READERS) > 4:
            _READERS.popitem(last=False)[1].close()
    else:
        _READERS.move_to_end(key)
    return reader


def _model(spec):
    """The model for a spec: a path (None = the default model) or a model object."""
    if spec is not None and not isinstance(spec, (str, os.PathLike)):
        return spec
    model = _MODELS.get(spec)
    if model is None:
        from .classify import load_model

        model = load_model(spec)
        _MODELS[spec] = model
    return model


def _cnn_verified(verify: bool, verifier: str | os.PathLike | None) -> bool:
    """Whether a CNN verifier (one on crops) checks the clusters of a build."""
    if not verify:
        return False
    from .classify import load_verifier

    return load_verifier(None if verifier is None else str(verifier)).kind == "crops"


def default_threshold(verify: bool, verifier: str | os.PathLike | None = None) -> float:
    """The pixel threshold a build uses unless told otherwise.

    Parameters
    ----------
    verify : bool
        Whether the cluster verifier checks the clusters.
    verifier : path-like or None
        The verifier file (None: the one shipped with lanemap).

    Returns
    -------
    float
        :data:`mapbuilder.cluster.CNN_PIXEL_THRESHOLD` when a CNN verifier
        checks the clusters (it removes what the lower threshold lets in),
        else ``ClusterParams.threshold``.

    Raises
    ------
    mapbuilder.classify.ModelError
        If the verifier file cannot be loaded.
    """
    from .cluster import CNN_PIXEL_THRESHOLD

    return CNN_PIXEL_THRESHOLD if _cnn_verified(verify, verifier) else ClusterParams.threshold


def default_threshold_low(verify: bool, verifier: str | os.PathLike | None = None,
                          threshold: float | None = None) -> float | None:
    """The hysteresis threshold a build uses unless told otherwise.

    ``verify`` and ``verifier`` are those of :func:`default_threshold`;
    ``threshold`` is the build's pixel threshold (None: that function's).
    Returns :data:`mapbuilder.cluster.CNN_PIXEL_THRESHOLD_LOW` when a CNN
    verifier checks the clusters and it lies below ``threshold``, else None
    (no hysteresis): without the verifier nothing checks what faint pixels
    add to a cluster. Raises :class:`mapbuilder.classify.ModelError` if the
    verifier file cannot be loaded.
    """
    from .cluster import CNN_PIXEL_THRESHOLD_LOW

    if not _cnn_verified(verify, verifier):
        return None
    if threshold is None:
        threshold = default_threshold(verify, verifier)
    return CNN_PIXEL_THRESHOLD_LOW if threshold > CNN_PIXEL_THRESHOLD_LOW else None


def _verifier(cluster: ClusterParams, path: str | None):
    """The cluster verifier of a build, or None when verification is off."""
    if not cluster.verify:
        return None
    from .classify import load_verifier

    return load_verifier(path)


def _check_model(spec) -> None:
    """Load a model file once and let it go: the workers load their own."""
    if spec is not None and not isinstance(spec, (str, os.PathLike)):
        return
    from .classify import MarkingModel, default_model_path

    MarkingModel(spec if spec is not None else default_model_path())


def clusters_to_markings(clusters: Clusters, crs: str, key: str | None = None) -> list[Marking]:
    """Turn measured clusters into detected markings with true-north bearings.

    A piece cut from a longer cluster gets ``kind="solid"``: it is part of a
    continuous line, and the localizer then matches it by the distance across
    its line (where a vehicle's camera cuts the line is its own affair). The
    kind of every other detection is left unknown.
    """
    if len(clusters) == 0:
        return []
    lon, lat = to_wgs84(crs).transform(clusters.x, clusters.y)
    conv = meridian_convergence_deg(crs, lon, lat)
    bearing = (clusters.bearing_deg + conv) % 180.0
    out = []
    for i in range(len(clusters)):
        out.append(
            Marking(
                x=float(clusters.x[i]),
                y=float(clusters.y[i]),
                length_m=float(clusters.length_m[i]),
                width_m=float(clusters.width_m[i]),
                bearing_deg=float(bearing[i]),
                weight=float(clusters.weight[i]),
                score=float(clusters.score[i]),
                kind="solid" if clusters.piece[i] else None,
                source="detected",
                status="unreviewed",
                x0=float(clusters.x0[i]),
                y0=float(clusters.y0[i]),
                x1=float(clusters.x1[i]),
                y1=float(clusters.y1[i]),
                tile_key=key,
                lon=float(lon[i]),
                lat=float(lat[i]),
            )
        )
    return out


def detect_window(
    rgb: np.ndarray,
    valid: np.ndarray,
    transform,
    resolution_m: float,
    model,
    cluster: ClusterParams | None = None,
    verifier: str | None = None,
) -> tuple[Clusters, np.ndarray]:
    """Classify, cluster and verify one window already in memory.

    Returns the measured clusters (grid bearings, window pixel coordinates)
    and the probability image. ``verifier`` is a verifier file (None: the
    default one), used when ``cluster.verify``.
    """
    cluster = cluster or ClusterParams()
    if valid.any():
        prob = np.asarray(model.predict(rgb, valid, resolution_m), dtype=np.float32)
    else:
        prob = np.zeros(valid.shape, np.float32)
    clusters = detect_markings(prob, valid, transform, cluster, rgb=rgb,
                               verifier=_verifier(cluster, verifier))
    return clusters, prob


def _predict(model, rgb: np.ndarray, valid: np.ndarray, resolution_m: float,
             origin: tuple[int, int]) -> np.ndarray:
    """The model's probabilities of a window at ``origin`` (row, col) of its image.

    lanemap's own models take the origin, so that tiles agree where they
    overlap; any other object with ``predict(rgb, valid, resolution_m)`` works too.
    """
    from .classify import MarkingModel

    if isinstance(model, MarkingModel):
        return model.predict(rgb, valid, resolution_m, origin=origin)
    return model.predict(rgb, valid, resolution_m)


def process_tile(task: TileTask) -> TileResult:
    """Detect the markings of one tile.

    Reads the tile's window (core + halo), classifies it, clusters and
    measures the marking pixels, and keeps the markings whose centroid lies in
    the core.
    """
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    _limit_gdal_cache()
    _restore_malloc_thresholds()
    reader = _reader(task.path, task.grid)
    window = Window(*task.read)
    rgb, valid = reader.read(window)
    t1 = time.perf_counter()
    if valid.any():
        prob = np.asarray(
            _predict(_model(task.model), rgb, valid, task.grid.resolution_m,
                     origin=(task.read[1], task.read[0])), dtype=np.float32
        )
    else:
        prob = np.zeros(valid.shape, np.float32)
    t2 = time.perf_counter()
    transform = window_transform(window, task.grid.affine)
    clusters = detect_markings(prob, valid, transform, task.cluster, rgb=rgb,
                               verifier=_verifier(task.cluster, task.verifier))
    c0, r0, w, h = task.core
    col = clusters.col + task.read[0]
    row = clusters.row + task.read[1]
    own = (col >= c0) & (col < c0 + w) & (row >= r0) & (row < r0 + h)
    markings = clusters_to_markings(clusters.take(own), task.grid.crs, task.key)
    cr, cc = r0 - task.read[1], c0 - task.read[0]
    ground = imaged_ground(valid[cr: cr + h, cc: cc + w], window_transform(Window(*task.core), task.grid.affine))
    t3 = time.perf_counter()
    timings = {"read": t1 - t0, "classify": t2 - t1, "cluster": t3 - t2}
    return TileResult(task.key, markings, task.megapixels, t3 - t0, timings,
                      time.process_time() - cpu0, ground)


# --------------------------------------------------------------------------- planning


@dataclass
class ImagePlan:
    path: str
    tag: str
    grid: PixelGrid
    tasks: list[TileTask]


def plan_image(path: str | Path, storage_crs: str, params: BuildParams) -> ImagePlan:
    """Validate an image and cut it into tile tasks on its grid in ``storage_crs``."""
    info = inspect_imagery(path, storage_crs)
    grid = info.grid
    tiles = tile_grid(grid.width, grid.height, params.tile_px, params.halo_px(grid.resolution_m))
    tag = image_tag(info.path)
    tasks = [
        TileTask(
            path=info.path,
            grid=grid,
            key=tile_key(tag, tiles, t),
            core=t.core,
            read=t.read,
            model=params.model,
            cluster=params.cluster,
            verifier=params.verifier,
        )
        for t in tiles
    ]
    return ImagePlan(info.path, tag, grid, tasks)


def _file_stamp(path: str) -> dict[str, Any]:
    st = os.stat(path)
    return {"path": path, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


# --------------------------------------------------------------------------- executors


def _init_worker() -> None:
    # Tiles parallelise across processes; one thread per process avoids oversubscription.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    if sys.platform.startswith("linux"):
        # Die with the parent: a killed build leaves no orphaned workers.
        try:
            import ctypes
            import signal

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
        except OSError:
            pass


def process_tiles(tasks: Sequence[TileTask]) -> list[TileResult]:
    """Process a run of tiles one after the other (see :func:`group_runs`)."""
    return [process_tile(t) for t in tasks]


def group_runs(tasks: Sequence[TileTask], run_len: int) -> list[list[TileTask]]:
    """Group tiles into runs of up to ``run_len`` neighbours along a row of one image.

    A worker reads a run's windows in order, so the image blocks shared by
    neighbouring windows (the halo) are decoded once and served from GDAL's
    cache; tile by tile, two workers would each decode them.
    """
    runs: list[list[TileTask]] = []
    for task in tasks:
        last = runs[-1][-1] if runs else None
        if (
            last is not None
            and len(runs[-1]) < run_len
            and last.path == task.path
            and last.core[1] == task.core[1]
            and last.core[0] + last.core[2] == task.core[0]
        ):
            runs[-1].append(task)
        else:
            runs.append([task])
    return runs


def _run_inline(runs: Sequence[list[TileTask]]) -> Iterator[TileResult]:
    for run in runs:
        for task in run:
            yield process_tile(task)


def _run_pool(runs: Sequence[list[TileTask]], workers: int) -> Iterator[TileResult]:
    ctx = mp.get_context("spawn")
    in_flight_max = 2 * workers
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker) as pool:
        pending = set()
        try:
            for run in runs:
                pending.add(pool.submit(process_tiles, run))
                if len(pending) >= in_flight_max:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield from fut.result()
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield from fut.result()
        finally:
            for fut in pending:
                fut.cancel()


def _run_length(n_tiles: int, n_exec: int) -> int:
    """Tiles per run: long enough to share decoded blocks, short enough to keep every
    executor busy to the end (at least 16 runs each: the last run is the idle tail)."""
    return max(1, min(MAX_RUN, n_tiles // (16 * max(1, n_exec))))


def _run_dask(tasks: Sequence[TileTask], address: str, timeout_s: float) -> Iterator[TileResult]:
    """Run ``tasks`` on a Dask cluster, in runs sized by the cluster's threads."""
    from distributed import Client, as_completed

    try:
        client = Client(address, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError) as exc:
        raise BuildError(f"cannot reach Dask scheduler at {address}: {exc}") from exc
    try:
        n_workers = max(1, sum(client.nthreads().values()))
        runs = group_runs(tasks, _run_length(len(tasks), n_workers))
        in_flight_max = 2 * n_workers
        it = iter(runs)
        first = [
            client.submit(process_tiles, r, pure=False) for _, r in zip(range(in_flight_max), it)
        ]
        ac = as_completed(first)
        for fut in ac:
            results = fut.result()
            fut.release()
            nxt = next(it, None)
            if nxt is not None:
                ac.add(client.submit(process_tiles, nxt, pure=False))
            yield from results
    finally:
        client.close()


# --------------------------------------------------------------------------- the build


def _find_resumable(store, map_id: str, job_params: dict[str, Any]):
    """The latest interrupted build with the same parameters. An ``accepted`` job
    is waiting for a server's worker and is left to it."""
    jobs = store.find_jobs(kind=JOB_KIND, map_id=map_id, status=("running", "failed"))
    for job in reversed(jobs):
        if job.params == job_params:
            return job
    return None


def _ensure_map(store, map_id: str, first_image: str, title: str) -> str:
    from .store import UnknownMapError

    try:
        info = store.get_map(map_id)
    except UnknownMapError:
        crs = default_storage_crs(first_image)
        # A map made by a build speaks for the ground its imagery shows (store.MAP_COVERAGES).
        info = store.create_map(map_id, title=title, crs=crs, coverage="imagery")
        log.info("created map %s in %s, covering its imagery", map_id, crs)
    if info.coverage is None:
        # A map made empty (POST /collections, `maps create`) and first built into: as if the build had made it.
        store.adopt_coverage(map_id, "imagery")
    if not info.crs:  # created without one: the first build chooses it, as a first import does
        return store.adopt_crs(map_id, default_storage_crs(first_image))
    return info.crs


def _register_imagery(store, map_id: str, plan: ImagePlan) -> None:
    known = {i.path for i in store.list_imagery(map_id)}
    if plan.path not in known:
        grid = plan.grid
        store.add_imagery(map_id, plan.path, grid.crs, grid.bounds, grid.resolution_m)


def _drop_stale_tiles(store, map_id: str, plans: list[ImagePlan]) -> int:
    """Empty tiles an earlier build of the same image made with another grid."""
    dropped = 0
    for plan in plans:
        current = {t.key for t in plan.tasks}
        prefix = plan.tag + "/"
        stale = {
            m.tile_key
            for m in store.query_bbox(map_id, *plan.grid.bounds, statuses=["unreviewed"])
            if m.source == "detected" and m.tile_key and m.tile_key.startswith(prefix)
            and m.tile_key not in current
        }
        for key in sorted(stale):
            store.replace_detected(map_id, key, [])
            dropped += 1
    return dropped


def build_map(
    store,
    map_id: str,
    images: Sequence[str | Path],
    params: BuildParams | None = None,
    *,
    workers: int | None = None,
    dask_address: str | None = None,
    dask_timeout_s: float = 20.0,
    progress: bool = True,
    resume: bool = True,
    title: str = "",
    on_tile: Callable[[TileResult], None] | None = None,
    job_id: int | None = None,
) -> BuildResult:
    """Build (or rebuild, or resume) a map's detected markings from imagery.

    Parameters
    ----------
    store : mapbuilder.store.Store
    map_id : str
        The map; created in the first image's metric CRS (its own, or its UTM
        zone) when it does not exist.
    images : sequence of path
        GeoTIFFs/COGs to build from.
    params : BuildParams, optional
    workers : int, optional
        Local worker processes (default: all cores); 1 or 0 runs in this process.
    dask_address : str, optional
        Address of a Dask distributed scheduler to run the tiles on instead.
    dask_timeout_s : float
        How long to try to reach the scheduler, seconds.
    progress : bool
        Show a tqdm bar on stderr (tiles done/total, rate, ETA).
    resume : bool
        Continue an unfinished job with the same map, images and parameters.
    on_tile : callable, optional
        Called with every tile's result after it is stored; an exception it
        raises stops the build (the job is marked failed).
    job_id : int, optional
        Run as this existing job (one a server created for the build),
        skipping the tiles it has done, instead of finding or creating one.

    Raises
    ------
    BuildError, ImageryError
        Bad parameters or imagery; nothing is written then.
    """
    from tqdm import tqdm

    params = params or BuildParams()
    if not images:
        raise BuildError("no imagery given")
    paths = []
    for p in images:
        p = Path(p)
        if not p.is_file():
            raise ImageryError(f"image not found: {p}")
        paths.append(str(p.resolve()))
    paths = list(dict.fromkeys(paths))  # the same file twice would repeat its tiles
    t0 = time.perf_counter()
    if workers is None:
        workers = os.cpu_count() or 1
    inline = not dask_address and workers <= 1
    # A bad model file fails here, before any job starts.
    if inline:
        _model(params.model)
    else:
        _check_model(params.model)
    _verifier(params.cluster, params.verifier)
    crs = _ensure_map(store, map_id, paths[0], title)
    plans = [plan_image(p, crs, params) for p in paths]
    for plan in plans:
        _register_imagery(store, map_id, plan)

    job_params = {
        "images": [_file_stamp(p) for p in paths],
        "params": params.to_dict(),
        "crs": crs,
    }
    if job_id is not None:
        job = store.get_job(job_id)
        if job.map_id != map_id or job.kind != JOB_KIND:
            raise BuildError(f"job {job_id} is not a build of map {map_id!r}")
    else:
        job = _find_resumable(store, map_id, job_params) if resume else None
    if job is not None:
        job_id = job.id
        done = store.done_tiles(job_id)
        if done:
            log.info("resuming build job %d: %d tiles already done", job_id, len(done))
    else:
        job_id = store.create_job(JOB_KIND, map_id, job_params)
        done = set()
    store.update_job(job_id, status="running")

    all_tasks = [t for plan in plans for t in plan.tasks]
    todo = [t for t in all_tasks if t.key not in done]
    skipped = len(all_tasks) - len(todo)
    n_exec = 1 if inline else max(1, workers)
    runs = group_runs(todo, _run_length(len(todo), n_exec))
    if dask_address:
        results = _run_dask(todo, dask_address, dask_timeout_s)
    elif inline or len(runs) <= 1:
        results = _run_inline(runs)
    else:
        results = _run_pool(runs, min(workers, len(runs)))

    n_markings = 0
    cpu = 0.0
    timings: dict[str, float] = {}
    mpx = 0.0
    n_run = 0
    last_update = time.monotonic()
    bar = tqdm(
        total=len(all_tasks),
        initial=skipped,
        unit="tile",
        desc=f"build {map_id}",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    try:
        with bar:
            for result in results:
                n_markings += store.replace_detected(map_id, result.key, result.markings, job_id,
                                                     ground=result.ground)
                mpx += result.megapixels
                cpu += result.cpu_seconds
                for k, v in result.timings.items():
                    timings[k] = timings.get(k, 0.0) + v
                n_run += 1
                bar.update(1)
                bar.set_postfix(markings=n_markings, refresh=False)
                if on_tile is not None:
                    on_tile(result)
                now = time.monotonic()
                if now - last_update > 2.0:
                    store.update_job(job_id, progress=100.0 * (skipped + n_run) / len(all_tasks))
                    last_update = now
        if skipped == 0 and len(store.find_jobs(kind=JOB_KIND, map_id=map_id)) > 1:
            _drop_stale_tiles(store, map_id, plans)
    except BaseException as exc:
        reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else str(exc)
        try:
            store.update_job(job_id, status="failed", error=reason or exc.__class__.__name__)
        except Exception:  # the store itself may be what failed
            log.exception("could not mark job %d failed", job_id)
        raise
    store.update_job(job_id, status="successful", progress=100.0)
    result = BuildResult(
        map_id=map_id,
        job_id=job_id,
        images=paths,
        tiles_total=len(all_tasks),
        tiles_skipped=skipped,
        tiles_run=n_run,
        markings=n_markings,
        megapixels=mpx,
        seconds=time.perf_counter() - t0,
        resumed=skipped > 0,
        timings=timings,
        cpu_seconds=cpu,
        verified=params.cluster.verify,
        threshold=params.cluster.threshold,
        threshold_low=params.cluster.threshold_low,
    )
    log.info("%s", result.summary())
    return result

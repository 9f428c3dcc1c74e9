"""The server's localization indexes of its maps, kept current in the background."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import ctypes
import ctypes.util
import functools
import logging
import multiprocessing
import queue
import threading
import time
from dataclasses import dataclass

from localizer import LocalizationInputError, MapIndex
from mapbuilder.store import Store, UnknownMapError

from . import metrics
from .index_files import NOT_KEPT, IndexFiles, build_kept
from .map_index import UPDATE_SHARE, load_index, updated_index
from .problems import Problem

log = logging.getLogger(__name__)

#: An index kept current by updates is kept in a file again once the markings written since
#: the last was kept reach this share of the map (half of what an update takes on: a process
#: that starts then catches up by updating, not building) ...
KEEP_SHARE = UPDATE_SHARE / 2
#: ... or this many seconds after the last, if any was written (a change feed pruned of its
#: deletions older than ``LANEMAP_FEED_RETENTION_DAYS`` still reaches back to the file).
KEEP_AFTER_S = 3600.0


def _heap_trimmer():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


_malloc_trim = _heap_trimmer()


def _trim_heap() -> None:
    """Give the memory a build freed back to the system.

    A build's triangles, polygons and rows are freed when it ends, but glibc
    keeps the pages: about ten times the index's own size (400 MB after the
    index of 200,000 markings by ``markings``, which itself holds 40 MB).
    """
    if _malloc_trim is not None:
        _malloc_trim(0)


class _Builder:
    """Runs builds in turn on one daemon thread.

    Not a ``ThreadPoolExecutor``: the interpreter waits for those threads at
    exit, and a server asked to stop would first finish a city's index
    nobody will use.
    """

    def __init__(self):
        self._jobs: queue.SimpleQueue | None = None
        self._stop = threading.Event()
        self._start = threading.Lock()

    def submit(self, fn, *args) -> concurrent.futures.Future:
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._start:
            if self._jobs is None:  # at the first build (again after close): an app that never localizes has none
                self._jobs, self._stop = queue.SimpleQueue(), threading.Event()
                threading.Thread(target=self._run, args=(self._jobs, self._stop), name="lanemap-index",
                                 daemon=True).start()  # fmt: skip
            self._jobs.put((future, fn, args))
        return future

    def close(self) -> None:
        """Let the thread end after the build under way; builds not begun are cancelled."""
        with self._start:
            if self._jobs is not None:
                self._stop.set()
                self._jobs.put(None)
                self._jobs = None

    @staticmethod
    def _run(jobs: queue.SimpleQueue, stop: threading.Event) -> None:
        while (job := jobs.get()) is not None:
            future, fn, args = job
            if stop.is_set():
                future.cancel()
            elif future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(*args))
                except BaseException as exc:  # noqa: BLE001 - handed to whoever waits for the build
                    future.set_exception(exc)
                _trim_heap()


class IndexPending(Exception):
    """A map's index must be built before a request can be answered from it.

    Raised where waiting would hold a thread others need (the localization
    thread): the caller awaits :meth:`wait` off that thread, then looks again
    with ``accept_stale=True``.
    """

    def __init__(self, map_id: str, future: concurrent.futures.Future):
        super().__init__(f"the index of map {map_id!r} is being built")
        self.future = future

    async def wait(self) -> None:
        """Until the build is done; raises what the build raised (an unknown or empty map).

        A request cancelled meanwhile (its client gone) leaves the build to the others
        waiting for it: unshielded, the cancellation would reach the build itself.
        """
        await asyncio.shield(asyncio.wrap_future(self.future))


@dataclass(frozen=True)
class IndexedMap:
    """A map's index, and the head of the map it was built from."""

    index: MapIndex
    revision: int
    coverage: str
    created: str
    read: bool = False  # from a kept file


class IndexCache:
    """The localization indexes of a server process's maps, kept current in the background.

    A map's index is built from all its markings: seconds for a city's
    (:func:`load_index`; 0.7 s for 200,000 markings drawn by their hull,
    2.6 s by ``markings``). Every edit moves the map's revision on, and an index
    built in the localization thread on the first request after each edit
    held every localization of the process for that long. Here builds run on
    a thread of their own, one at a time, and a map of at least
    ``background_from`` markings goes on answering from its previous index
    while the next is built (the answer names the revision it used); smaller
    maps, whose index takes milliseconds, are answered at their newest
    revision. After a build, a map's next build in the background waits as
    long as that one took (``build_share``): under a stream of edits (a
    review, a decision a second) a city's builds take at most half of a
    core in each server process, not all of it. A request for a map without
    an index yet, or whose coverage changed, waits for the build
    (:class:`IndexPending`), but other maps' requests do not wait with it.
    After an edit, a map's index is not built anew but updated with the
    markings changed since its revision (:func:`updated_index`: 0.08-0.10 s
    for an edit of 200,000 markings, against 2.4-4.8 s for a build), unless
    they are more than a tenth of the map.

    Parameters
    ----------
    store : mapbuilder.store.Store
    default_coverage : str
        The coverage of maps that do not set their own (``LANEMAP_MAP_COVERAGE``).
    background_from : int
        ``LANEMAP_INDEX_BACKGROUND_FROM``; 0: every map.
    build_share : float
        The most of the time a map's builds in the background take: after a
        build of ``d`` seconds the next waits ``d (1 / build_share - 1)``.
    files : IndexFiles, optional
        Where built indexes are kept (``LANEMAP_INDEX_DIR``): a build first
        looks there, for the index at the map's revision that another process
        built (or, for a map of at least ``background_from`` markings that
        has none here yet, an older one to answer from meanwhile), and keeps
        what it builds there. A process that starts then reads a city's index
        in a tenth of a second, and the workers of one server build each
        revision once between them. An index kept current by updates is kept
        again after :data:`KEEP_SHARE` of the map was written, or
        :data:`KEEP_AFTER_S`, and after catching up at a start.
    process_from : int, optional
        A map of at least this many markings has its index built in a child
        process (``LANEMAP_INDEX_PROCESS_FROM``; with ``files`` only, through
        which it is handed over): its build then neither holds this process's
        interpreter (up to 0.8 s at a time for 1,000,000 markings by
        ``markings``) nor grows its memory. None: every build here.
    """

    def __init__(self, store: Store, default_coverage: str, background_from: int, build_share: float = 0.5,
                 files: IndexFiles | None = None, process_from: int | None = None):
        if not 0.0 < build_share <= 1.0:
            raise ValueError(f"build_share: {build_share} is not in (0, 1]")
        self.store = store
        self.default_coverage = default_coverage
        self.background_from = background_from
        self.rest_factor = 1.0 / build_share - 1.0
        self.files = files
        self.process_from = process_from
        self._children: set[multiprocessing.process.BaseProcess] = set()
        # Reentrant: a build that ends before its callback is added runs the callback at once.
        self._lock = threading.RLock()
        self._maps: dict[str, IndexedMap] = {}
        self._building: dict[str, tuple[str, concurrent.futures.Future]] = {}  # map id: coverage, build
        self._rest_until: dict[str, float] = {}  # map id: no background build before (time.monotonic)
        self._catch_up: set[str] = set()  # maps answering from an older kept index: build the newest next
        self._unkept: dict[str, tuple[float, int]] = {}  # map id: last kept (time.monotonic), markings written since
        self._closed = False
        self._builder = _Builder()

    def lookup(self, map_id: str, accept_stale: bool = False) -> tuple[IndexedMap, bool]:
        """The map's index to answer from now, and whether it is older than the map.

        Starts a build when the map moved on (one in the background only once
        the last build's rest is over, ``build_share``). Never waits for one: raises
        :class:`IndexPending` when none can answer meanwhile, unless
        ``accept_stale`` and the map's previous index (same map, same
        coverage) is there: after waiting for a build once, a request is
        answered even if the map moved on again meanwhile.

        Raises
        ------
        mapbuilder.store.UnknownMapError
            The map does not exist (its index, if any, is forgotten).
        """
        try:
            head = self.store.map_head(map_id)
        except UnknownMapError:
            self.drop(map_id)
            raise
        coverage = head.coverage or self.default_coverage
        with self._lock:
            have = self._maps.get(map_id)
            # At or past the head: a build may have read a revision committed after this read.
            if have is not None and (have.coverage, have.created) == (coverage, head.created) and \
                    have.revision >= head.revision:
                return have, False
            if (have is not None and have.coverage == coverage and have.created == head.created
                    and (accept_stale or len(have.index) >= self.background_from)):
                if time.monotonic() >= self._rest_until.get(map_id, 0.0):
                    self._build_locked(map_id, coverage)
                return have, True
            future = self._build_locked(map_id, coverage)
        raise IndexPending(map_id, future)

    def preload(self) -> list[str]:
        """Start building the index of every map that has markings; their ids.

        A server that starts (a deployment, a worker replaced) would otherwise
        make each map's first vehicle wait for its build, seconds for a city.
        Requests for a map whose index is still being built wait for it.
        """
        ids = []
        for info in self.store.list_maps():
            if info.crs is None or not info.count:
                continue
            with self._lock:
                self._build_locked(info.id, info.coverage or self.default_coverage)
            ids.append(info.id)
        return ids

    def status(self) -> dict:
        """This process's indexes: how many maps have one, and which are being built (``/health``)."""
        with self._lock:
            return {"ready": len(self._maps), "building": sorted(self._building)}

    def get(self, map_id: str) -> tuple[IndexedMap, bool]:
        """:meth:`lookup`, waiting for a build where one must be done first (for threads that may wait)."""
        try:
            return self.lookup(map_id)
        except IndexPending as pending:
            pending.future.result()
        return self.lookup(map_id, accept_stale=True)

    def drop(self, map_id: str, created: str | None = None) -> None:
        """Forget the map's index (a deleted map), and with ``created`` (its head's) its kept files."""
        with self._lock:
            self._maps.pop(map_id, None)
            self._rest_until.pop(map_id, None)
            self._unkept.pop(map_id, None)
        if created is not None and self.files is not None:
            self.files.forget(map_id, created)

    def close(self) -> None:
        """Stop building: builds not begun are cancelled, one under way is left to the process's end."""
        with self._lock:
            self._closed = True
            children = list(self._children)
        self._builder.close()
        for child in children:
            child.terminate()

    def _build_locked(self, map_id: str, coverage: str) -> concurrent.futures.Future:
        """The build of the map's index by ``coverage`` under way, or a new one (under ``_lock``)."""
        under_way = self._building.get(map_id)
        if under_way is not None and under_way[0] == coverage:
            return under_way[1]
        # In the request's context: the build logs under the ID of the request that asked for it.
        future = self._builder.submit(contextvars.copy_context().run, self._build, map_id, coverage)
        self._building[map_id] = (coverage, future)
        future.add_done_callback(functools.partial(self._built, map_id))
        return future

    def _build(self, map_id: str, coverage: str) -> IndexedMap:
        t = time.perf_counter()
        head = self.store.map_head(map_id)  # before the markings: an index never claims a newer revision
        with self._lock:
            have = self._maps.get(map_id)
        if have is not None and (have.coverage, have.created) == (coverage, head.created) and \
                have.revision < head.revision:
            updated = self._updated(map_id, have, head, t)
            if updated is not None:
                return updated
        files = self.files
        info = self.store.get_map(map_id, with_count=files is not None)  # counted once per revision
        if info.crs is None:
            raise Problem(409, f"map {map_id!r} has no markings to localize against", "empty-map")
        if files is None or info.count < files.min_markings:
            return self._built_here(map_id, coverage, head, info.crs, t)
        with self._lock:
            have = self._maps.get(map_id)
        if have is not None and (have.coverage, have.created) == (coverage, head.created):
            newer_than = have.revision  # only a file newer than what answers now is worth reading
        elif info.count >= self.background_from:
            newer_than = -1  # an older one may answer while the newest is built
        else:
            newer_than = head.revision - 1
        kept = files.load(map_id, head, coverage, newer_than=newer_than)
        if kept is not None:
            return self._install_kept(map_id, coverage, head, kept, t)
        with files.building(map_id, head, coverage):
            # another process may have built it while this one waited
            kept = files.load(map_id, head, coverage, newer_than=head.revision - 1)
            if kept is not None:
                return self._install_kept(map_id, coverage, head, kept, t)
            if self.process_from is not None and info.count >= self.process_from:
                return self._built_in_child(map_id, coverage, head, info.crs, t)
            built = self._built_here(map_id, coverage, head, info.crs, t)
            if files.save(map_id, head, coverage, built.index) is not None:
                self._kept(map_id, "build")
            self._forget_if_deleted(map_id, head)
        return built

    def _updated(self, map_id: str, have: IndexedMap, head, t: float) -> IndexedMap | None:
        """``have`` updated with the map's changes since (:func:`updated_index`); None where it must
        be built anew."""
        imaged = self.store.imaged_footprint(map_id) if have.coverage == "imagery" else None
        try:
            done = updated_index(self.store, map_id, have.index, have.revision, have.coverage, imaged)
        except LocalizationInputError as exc:  # values a build would refuse too: it says so
            log.warning("map %s: its spatial index could not be updated (%s); building it anew", map_id, exc)
            return None
        if done is None:
            return None
        index, revision, changes = done
        built = IndexedMap(index, revision, have.coverage, head.created)
        seconds = time.perf_counter() - t
        self._install(map_id, built, rest_s=self.rest_factor * seconds)
        log.info("map %s: spatial index of %d markings updated from revision %d to %d with %d changed markings "
                 "(coverage: %s) in %.2f s", map_id, len(index), have.revision, revision, changes, have.coverage,
                 seconds)  # fmt: skip
        metrics.index_update_seconds.observe(seconds)
        if self._keep_due(map_id, have, len(index), changes):  # not after each edit: a city's file is 150 MB
            t_keep = time.perf_counter()
            if self.files.save_updated(self.store, map_id, head.created, revision, have.coverage, index) is not None:
                self._kept(map_id, "update")
                log.info("map %s: spatial index at revision %d kept in %s in %.2f s", map_id, revision,
                         self.files.directory, time.perf_counter() - t_keep)  # fmt: skip
                self._forget_if_deleted(map_id, head)
        return built

    def _keep_due(self, map_id: str, have: IndexedMap, size: int, changes: int) -> bool:
        """Whether the map's index, updated from ``have`` with ``changes`` markings, is to be kept:
        ``have`` was read from an older file (a process that started after edits), or
        :data:`KEEP_SHARE` of the map was written or :data:`KEEP_AFTER_S` passed since the last."""
        if self.files is None or size < self.files.min_markings:
            return False
        with self._lock:
            since, written = self._unkept.get(map_id, (time.monotonic(), 0))
            written += changes
            self._unkept[map_id] = (since, written)
        return have.read or written >= KEEP_SHARE * size or time.monotonic() - since >= KEEP_AFTER_S

    def _kept(self, map_id: str, after: str | None = None) -> None:
        """The map's index was kept in a file just now, after a ``"build"`` or an ``"update"``
        (counted), or read from one (``after`` None)."""
        with self._lock:
            self._unkept[map_id] = (time.monotonic(), 0)
        if after is not None:
            metrics.index_file_saves.labels(after).inc()

    def _forget_if_deleted(self, map_id: str, head) -> bool:
        """A map deleted while its index was built and kept: its file goes too (the deletion's own
        clean-up, :meth:`drop`, may have come before the file was written). Whether it was."""
        try:
            now = self.store.map_head(map_id)
        except UnknownMapError:
            now = None
        if now is None or now.created != head.created:
            self.files.forget(map_id, head.created)
            return True
        return False

    def _built_in_child(self, map_id: str, coverage: str, head, crs: str, t: float) -> IndexedMap:
        child = multiprocessing.get_context("spawn").Process(
            target=build_kept, args=(self.files, self.store.url, map_id, crs, coverage, head),
            name=f"lanemap-index-{map_id}", daemon=False)  # fmt: skip
        with self._lock:
            if self._closed:
                raise Problem(503, "the server is stopping", "busy")
            child.start()
            self._children.add(child)
        try:
            child.join()
        finally:
            with self._lock:
                self._children.discard(child)
        if not self._closed and self._forget_if_deleted(map_id, head):
            raise UnknownMapError(map_id)  # whether the child read it before (0) or failed to (1)
        kept = self.files.load(map_id, head, coverage, newer_than=head.revision - 1) \
            if child.exitcode == 0 else None
        if kept is None:
            why = "its file could not be written" if child.exitcode == NOT_KEPT else \
                f"the process building it ended with exit code {child.exitcode}"
            if not self._closed:
                log.warning("map %s: its spatial index could not be built: %s", map_id, why)
            raise Problem(503, f"the localization index of map {map_id!r} could not be built: {why}; retry shortly",
                          "busy", headers={"Retry-After": "5"})
        built = IndexedMap(kept.index, head.revision, coverage, head.created)
        seconds = time.perf_counter() - t
        self._install(map_id, built, rest_s=self.rest_factor * seconds)
        self._kept(map_id, "build")  # by the child
        log.info("map %s: spatial index of %d markings at revision %d (coverage: %s) in %.2f s, built by process %d",
                 map_id, len(kept.index), head.revision, coverage, seconds, child.pid)
        metrics.index_build_seconds.observe(seconds)
        return built

    def _built_here(self, map_id: str, coverage: str, head, crs: str, t: float) -> IndexedMap:
        index = load_index(self.store, map_id, crs, coverage)
        _ = index.extent  # drawn here, not by the requests
        built = IndexedMap(index, head.revision, coverage, head.created)
        seconds = time.perf_counter() - t
        self._install(map_id, built, rest_s=self.rest_factor * seconds)
        log.info("map %s: spatial index of %d markings at revision %d (coverage: %s) in %.2f s", map_id, len(index),
                 head.revision, coverage, seconds)
        metrics.index_build_seconds.observe(seconds)
        return built

    def _install_kept(self, map_id: str, coverage: str, head, kept, t: float) -> IndexedMap:
        built = IndexedMap(kept.index, kept.revision, coverage, head.created, read=True)
        self._install(map_id, built, rest_s=0.0)
        self._kept(map_id)
        current = kept.revision == head.revision
        if not current:
            with self._lock:
                self._catch_up.add(map_id)  # the newest is built as soon as this is done (_built)
        log.info("map %s: spatial index of %d markings at revision %d%s (coverage: %s) read from %s in %.2f s",
                 map_id, len(kept.index), kept.revision, "" if current else f" of {head.revision}", coverage,
                 self.files.directory, time.perf_counter() - t)
        metrics.index_file_loads.labels("current" if current else "stale").inc()
        return built

    def _install(self, map_id: str, built: IndexedMap, rest_s: float) -> None:
        with self._lock:
            have = self._maps.get(map_id)
            if have is None or have.created != built.created or have.coverage != built.coverage or \
                    have.revision <= built.revision:
                self._maps[map_id] = built
            self._rest_until[map_id] = time.monotonic() + rest_s

    def _built(self, map_id: str, future: concurrent.futures.Future) -> None:
        with self._lock:
            if self._building.get(map_id, (None, None))[1] is future:
                del self._building[map_id]
            error = None if future.cancelled() else future.exception()
            if isinstance(error, UnknownMapError):
                self._maps.pop(map_id, None)
            if map_id in self._catch_up:
                self._catch_up.discard(map_id)
                if error is None and not future.cancelled() and not self._closed:
                    self._build_locked(map_id, future.result().coverage)
        if error is not None and not self._closed and not isinstance(error, (UnknownMapError, Problem)):
            log.warning("map %s: building its spatial index failed: %r", map_id, error)


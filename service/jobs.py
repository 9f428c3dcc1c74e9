"""Build jobs in worker processes.

A build never runs in a request thread: the API records a job (status
``accepted``) and hands it to the :class:`JobRunner`, which starts one spawned
process per job (at most ``workers`` at a time). The process runs
:func:`mapbuilder.build.build_map`, which writes progress and the final status
to the job row, so job state lives in the database. Cancelling marks the job
``dismissed`` and ends its process. When a server starts,
:func:`recover_jobs` resumes the builds a previous server left unfinished
(a build resumes tile by tile).

With a Dask scheduler configured (``LANEMAP_DASK_SCHEDULER``) the job's
process plans the tiles and stores their markings, and the tiles themselves
run on the Dask cluster: each task carries an image path and a tile's
windows, never an open dataset, so the workers must see the imagery folder
at the same path as the server (a shared volume). A worker lost mid-build
costs only its tasks, which the scheduler runs again elsewhere.
"""

from __future__ import annotations

import inspect
import logging
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapbuilder.store import Store, UnknownJobError

log = logging.getLogger(__name__)

ACTIVE = ("accepted", "running")


def _file_stamp(path: str) -> dict[str, Any]:
    st = os.stat(path)
    return {"path": path, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def build_job_params(images: list[str], params: Any, crs: str) -> dict[str, Any]:
    """The job parameters :func:`mapbuilder.build.build_map` records for a build.

    A job created with exactly these is the one ``build_map`` resumes, so the
    job the API answers with is the job that runs.
    """
    return {"images": [_file_stamp(str(Path(p).resolve())) for p in images], "params": params.to_dict(), "crs": crs}


def params_from_job(job_params: dict[str, Any]):
    from mapbuilder.build import BuildParams
    from mapbuilder.cluster import ClusterParams

    p = dict(job_params.get("params") or {})
    cluster = ClusterParams(**(p.pop("cluster", None) or {}))
    return BuildParams(tile_px=p.get("tile_px", 1024), halo_m=p.get("halo_m", 4.0),
                       model=p.get("model"), cluster=cluster)  # fmt: skip


class _Cancelled(Exception):
    pass


def _exit_with_parent(parent: int, period_s: float = 0.5) -> None:
    """End this worker when the server ``parent`` that started it dies.

    A restarted server resumes the job; an orphaned worker would build it twice.
    """

    def watch():
        while True:
            if os.getppid() != parent:
                log.warning("the server died; ending the job's worker")
                os._exit(3)
            time.sleep(period_s)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_build_job(db_url: str, job_id: int, server_pid: int | None = None,
                  dask_address: str | None = None, dask_timeout_s: float = 20.0) -> None:  # fmt: skip
    """Body of a worker process: run the build of job ``job_id`` to its end.

    Parameters
    ----------
    db_url : str
    job_id : int
    server_pid : int, optional
        End when this process (the server) is gone.
    dask_address : str, optional
        Run the tiles on this Dask scheduler instead of in this process.
    dask_timeout_s : float
        How long to try to reach the scheduler, seconds.
    """
    logging.basicConfig(level=logging.INFO, format="%(levelname)s build job %(process)d: %(message)s")
    if server_pid is not None:
        _exit_with_parent(server_pid)
    from mapbuilder.build import build_map

    store = Store(db_url)
    job = store.get_job(job_id)
    if job.status not in ACTIVE:
        return
    images = [i["path"] for i in job.params.get("images", [])]

    def on_tile(_result) -> None:
        if store.get_job(job_id).status == "dismissed":
            raise _Cancelled()

    kwargs: dict[str, Any] = {}
    if "job_id" in inspect.signature(build_map).parameters:
        kwargs["job_id"] = job_id
    try:
        params = params_from_job(job.params)
        result = build_map(store, job.map_id, images, params, workers=1, progress=False, resume=True,
                           on_tile=on_tile, dask_address=dask_address or None,
                           dask_timeout_s=dask_timeout_s, **kwargs)  # fmt: skip
    except _Cancelled:
        store.update_job(job_id, status="dismissed", error="cancelled")
        return
    except Exception as exc:  # the job row carries the error to the client
        log.warning("build job %d failed: %s", job_id, exc)
        if store.get_job(job_id).status in ACTIVE:
            store.update_job(job_id, status="failed", error=str(exc) or exc.__class__.__name__)
        return
    finally:
        store.close()
    if result.job_id != job_id:
        # build_map recorded the run under another job (parameters differed):
        # report its outcome on the job the client is watching.
        log.warning("build of job %d ran as job %d", job_id, result.job_id)
        store = Store(db_url)
        store.update_job(job_id, status="successful", progress=100.0)
        store.close()


#: Share of an import job's progress its reading of the file takes; its writing takes the rest.
IMPORT_READ_SHARE = 30.0
#: Seconds between an import job's writes of its progress.
PROGRESS_EVERY_S = 1.0


def import_files(data_dir: Path) -> Path:
    """The folder where the bodies of asynchronous imports wait for their job."""
    return Path(data_dir) / "imports"


def progress_file(body: str | Path) -> Path:
    """Where an import job on SQLite keeps its progress while its transaction holds the only
    writer: beside its body, in the data folder the API reads it from."""
    return Path(body).with_suffix(".progress")


def read_progress(job) -> float | None:
    """An import job's progress from its :func:`progress_file`, in percent; None without one."""
    try:
        return float(progress_file(job.params["file"]).read_text())
    except (KeyError, OSError, ValueError):
        return None


class ImportBodyError(ValueError):
    """An import's body that is not markings: the status and detail the import answers with,
    for a request and a job alike (a plain error: a job's process need not load the web stack,
    120 MB)."""

    def __init__(self, status: int, detail: str, slug: str | None = None):
        super().__init__(detail)
        self.status, self.detail, self.slug = status, detail, slug


def read_import(path: str | Path, progress: Callable[[int, int], None] | None = None) -> list:
    """The markings of an import's body kept at ``path``; :class:`ImportBodyError` 400 where it
    is not JSON, 422 where it is not markings. ``progress`` as for
    :func:`mapbuilder.geojson.read_feature_collection`."""
    from mapbuilder.geojson import GeoJSONError, InvalidJSONError, read_geojson_stream

    try:
        with open(path, "rb") as fh:
            items = read_geojson_stream(fh, "request body", progress)
    except InvalidJSONError as exc:
        raise ImportBodyError(400, str(exc)) from None
    except GeoJSONError as exc:
        raise ImportBodyError(422, f"body: {exc}", "invalid-geojson") from None
    if not items:
        raise ImportBodyError(422, "body: the FeatureCollection has no features", "invalid-geojson")
    return items


def run_import_job(db_url: str, job_id: int, server_pid: int | None = None) -> None:
    """Body of a worker process: import the GeoJSON file of job ``job_id`` into its map.

    All of it or none, as a synchronous import: the markings and the job's success are
    written in one transaction (:meth:`Store.add_markings`), so a job still active after a
    crash has imported nothing and runs again. Its reading of the file is the first
    :data:`IMPORT_READ_SHARE` % of its progress, its writing the rest. On SQLite, where the
    transaction holds the database's only writer, the writing's progress goes to a file
    beside the body (:func:`progress_file`), which the job's answers read.
    """
    logging.basicConfig(level=logging.INFO, format="%(levelname)s import job %(process)d: %(message)s")
    if server_pid is not None:
        _exit_with_parent(server_pid)
    from mapbuilder.store import StoreError

    store = Store(db_url)
    try:
        job = store.get_job(job_id)
        if job.status not in ACTIVE:
            return
        store.update_job(job_id, status="running", progress=0.0)
        path = job.params["file"]
        progress_file(path).unlink(missing_ok=True)  # a run before a crash left it
        last = [0.0]

        def report(share: float) -> None:
            now = time.monotonic()
            if now - last[0] >= PROGRESS_EVERY_S:
                last[0] = now
                store.update_job(job_id, progress=share)

        try:
            items = read_import(path, lambda k, n: report(IMPORT_READ_SHARE * k / max(n, 1)))
        except ImportBodyError as exc:  # what the synchronous import answers
            store.update_job(job_id, status="failed", error=exc.detail)
            return
        store.update_job(job_id, progress=IMPORT_READ_SHARE)
        beside = progress_file(path) if store.dialect == "sqlite" else None

        def written(k: int, n: int) -> None:
            share = IMPORT_READ_SHARE + (99.0 - IMPORT_READ_SHARE) * k / n
            if beside is None:
                report(share)
            elif time.monotonic() - last[0] >= PROGRESS_EVERY_S:
                last[0] = time.monotonic()
                part = beside.with_suffix(".progress-part")
                part.write_text(f"{share:.1f}")
                part.replace(beside)

        try:
            store.add_markings(job.map_id, items, job.params.get("who", "api"),
                               job.params.get("comment") or "import", lonlat=True, progress=written,
                               job_id=job_id)  # fmt: skip
        except StoreError as exc:  # an invalid marking, a map deleted meanwhile: nothing was written
            if store.get_job(job_id).status in ACTIVE:
                store.update_job(job_id, status="failed", error=str(exc))
            return
        log.info("import job %d: %d markings into %s", job_id, len(items), job.map_id)
        _remove_import_files(path)
    finally:
        store.close()


def _remove_import_files(body: str | Path) -> None:
    """An import job's body and progress, once the job has ended."""
    for p in (Path(body), progress_file(body), progress_file(body).with_suffix(".progress-part")):
        p.unlink(missing_ok=True)


class JobRunner:
    """Runs jobs (builds, asynchronous imports) in spawned processes, at most ``workers`` at a time.

    Parameters
    ----------
    store : Store
    data_dir : Path
        The server's data folder (uploaded imagery lives in ``imagery/``).
    workers : int
        Build jobs running at the same time; asynchronous imports run one at a time beside them.
    dask_address : str, optional
        Dask scheduler the jobs run their tiles on; None: in the job's process.
    dask_timeout_s : float
        How long a job tries to reach the scheduler, seconds.
    """

    def __init__(self, store: Store, data_dir: Path, workers: int = 1, *,
                 dask_address: str | None = None, dask_timeout_s: float = 20.0):  # fmt: skip
        self.store = store
        self.data_dir = Path(data_dir)
        self.dask_address = dask_address or None
        self.dask_timeout_s = dask_timeout_s
        self._slots = threading.Semaphore(max(1, int(workers)))
        self._import_slot = threading.Semaphore(1)
        self._procs: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._stopping = False
        self._threads: list[threading.Thread] = []
        self._submitted: set[int] = set()
        self._stop_event = threading.Event()
        self._lock_fh = None
        self._needs_recover = False
        self.owner = False
        self.poll_s = 1.0
        #: How often a standing-by process tries to take over the runner, seconds.
        self.standby_s = 2.0

    def start(self) -> None:
        """Become the job runner of this data folder, if no other server process is.

        One process per data folder runs builds (a file lock decides); it also
        picks up jobs other processes accepted, and resumes interrupted ones.
        The others stand by and take over when the runner's process ends.
        """
        self._stopping = False
        self._stop_event.clear()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if self._try_lock():
            self._become_runner()
            return
        log.info("another server process runs the build jobs of %s; standing by", self.data_dir)
        self._standby = threading.Thread(target=self._stand_by, name="build-job-standby", daemon=True)
        self._standby.start()

    def _try_lock(self) -> bool:
        import fcntl

        fh = open(self.data_dir / "job-runner.lock", "a+")
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            return False
        self._lock_fh = fh
        return True

    def _stand_by(self) -> None:
        while not self._stop_event.wait(self.standby_s):
            if self._try_lock():
                log.warning("the build job runner of %s is gone: this process takes over", self.data_dir)
                self._become_runner()
                return

    def _become_runner(self) -> None:
        self.owner = True
        self._recover()
        self._poller = threading.Thread(target=self._poll, name="build-job-poller", daemon=True)
        self._poller.start()

    def _recover(self) -> bool:
        """Resume the builds left unfinished; False (retried by the poller) if the database is down."""
        try:
            resume, _failed = recover_jobs(self.store, self.data_dir)
        except Exception:  # a database that is down now: try again at the next poll
            log.warning("cannot look for interrupted builds yet", exc_info=True)
            self._needs_recover = True
            return False
        self._needs_recover = False
        for job_id in resume:
            log.info("resuming build job %d", job_id)
            self.submit(job_id)
        return True

    def _poll(self) -> None:
        root = (self.data_dir / "imagery").resolve()
        while not self._stop_event.wait(self.poll_s):
            if self._needs_recover and not self._recover():
                continue
            try:
                for job in self.store.find_jobs(kind="build", status="accepted"):
                    if job.id in self._submitted:
                        continue
                    paths = [Path(i.get("path", "")) for i in job.params.get("images", [])]
                    if paths and all(p.resolve().is_relative_to(root) for p in paths):
                        self.submit(job.id)
                for job in self.store.find_jobs(kind="import", status="accepted"):
                    if job.id not in self._submitted and _own_import(job, self.data_dir):
                        self.submit(job.id)
            except Exception:  # a busy or briefly unavailable database: try again later
                log.debug("job poll failed", exc_info=True)

    def submit(self, job_id: int) -> None:
        """Run a job (in this process's runner; elsewhere the owning runner picks it up)."""
        if not self.owner:
            return
        with self._lock:
            if job_id in self._submitted:
                return
            self._submitted.add(job_id)
        t = threading.Thread(target=self._run, args=(job_id,), name=f"job-{job_id}", daemon=True)
        self._threads.append(t)
        t.start()

    def _run(self, job_id: int) -> None:
        try:
            kind = self.store.get_job(job_id).kind
        except UnknownJobError:
            return
        # Imports take a slot of their own, one at a time: a city's import lasts about a
        # minute, a build can last hours, and neither should wait for the other.
        with self._import_slot if kind == "import" else self._slots:
            if self._stopping:
                return
            try:
                job = self.store.get_job(job_id)
            except UnknownJobError:
                return
            if job.status not in ACTIVE:
                return
            if job.kind == "import":
                target, args = run_import_job, (self.store.url, job_id, os.getpid())
            else:
                target, args = run_build_job, (self.store.url, job_id, os.getpid(), self.dask_address,
                                               self.dask_timeout_s)  # fmt: skip
            proc = mp.get_context("spawn").Process(target=target, args=args, name=f"lanemap-{job.kind}-{job_id}")
            with self._lock:
                proc.start()
                self._procs[job_id] = proc
            proc.join()
            with self._lock:
                self._procs.pop(job_id, None)
            if self._stopping:
                return
            try:
                job = self.store.get_job(job_id)
                if job.status in ACTIVE:
                    self.store.update_job(job_id, status="failed",
                                          error=f"the {job.kind} process ended unexpectedly (exit code {proc.exitcode})")
            except Exception:  # the map (and its jobs) may have been deleted meanwhile
                log.info("job %d is gone after its process ended", job_id)
            if job.kind == "import" and job.params.get("file"):  # no longer needed, whatever became of it
                _remove_import_files(job.params["file"])

    def cancel(self, job_id: int) -> None:
        """Dismiss a job: it will not start, or its process is ended."""
        job = self.store.get_job(job_id)
        if job.status in ACTIVE:
            self.store.update_job(job_id, status="dismissed", error="cancelled")
        with self._lock:
            proc = self._procs.get(job_id)
        if proc is not None and proc.is_alive():
            proc.terminate()

    def running(self) -> list[int]:
        with self._lock:
            return [j for j, p in self._procs.items() if p.is_alive()]

    def stop(self, timeout: float = 5.0) -> None:
        """End running builds; their jobs stay ``running`` and resume at the next start."""
        self._stopping = True
        self._stop_event.set()
        with self._lock:
            procs = list(self._procs.values())
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout)
        if self._lock_fh is not None:
            self._lock_fh.close()
            self._lock_fh = None


def _own_import(job, data_dir: Path) -> bool:
    """Whether an import job's body waits in this server's data folder."""
    path = Path(job.params.get("file", ""))
    return path.name != "" and path.resolve().is_relative_to(import_files(data_dir).resolve())


def recover_jobs(store: Store, data_dir: Path) -> tuple[list[int], list[int]]:
    """Find the jobs a stopped server left unfinished.

    Jobs of imagery the server stored (under ``<data_dir>/imagery``) are
    returned to be resumed (``build_map`` continues a job tile by tile); other
    unfinished jobs — builds started elsewhere, e.g. by the CLI, are left alone.
    An import left active imported nothing (it ends in the transaction that writes its
    markings): it runs again while its body is kept, and fails when it is gone.

    Returns
    -------
    resume : list of int
        Job ids to hand to :meth:`JobRunner.submit`.
    failed : list of int
        Jobs marked failed because their imagery is gone.
    """
    root = (Path(data_dir) / "imagery").resolve()
    resume, failed = [], []
    for job in store.find_jobs(kind="build", status=ACTIVE):
        paths = [Path(i.get("path", "")) for i in job.params.get("images", [])]
        if not paths or not all(p.resolve().is_relative_to(root) for p in paths):
            continue
        if all(p.is_file() for p in paths):
            resume.append(job.id)
        else:
            store.update_job(job.id, status="failed", error="interrupted by a server restart; its imagery is gone")
            failed.append(job.id)
    for job in store.find_jobs(kind="import", status=ACTIVE):
        if not _own_import(job, data_dir):
            continue
        if Path(job.params["file"]).is_file():
            resume.append(job.id)
        else:
            store.update_job(job.id, status="failed", error="interrupted by a server restart; its body is gone")
            failed.append(job.id)
    return resume, failed

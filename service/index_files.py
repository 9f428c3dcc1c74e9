"""Built localization indexes kept in files, for the next process that needs them.

A city's index takes seconds to build from its stored markings (for
1,000,000 markings 7–10 s drawn by their hull, 18–25 s by ``markings`` on
two cores, 2026-12-07), and
every process built its own: each ``lanemap localize`` call, and each server
worker at every start. Kept in a file (``LANEMAP_INDEX_DIR``) it is read back
in about 0.1 s by any process of the machine that asks for the same map at
the same revision.

A file is named by the map and how it was drawn (the database, the map's id
and creation, its coverage, this file format and the versions of what it
holds) and by the revision it was built at. A file is current for a map
whose head (:class:`mapbuilder.store.MapHead`) has that revision and was last
changed at the same time; an older one can still answer while the newest is
built (the server does, for maps of at least
``LANEMAP_INDEX_BACKGROUND_FROM`` markings). One of a newer revision than the
map, or of the same revision changed at another time, belongs to another
history of the database (one restored from a backup) and is deleted.

The files are pickles: only files the process's own user owns and nobody
else may write are read, and the folder is made for that user alone (mode
0700). A map of at least ``LANEMAP_INDEX_PROCESS_FROM`` markings is built by
a child process (:func:`build_kept`) that hands its index over in its file.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import pickle
import stat
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from localizer import MapIndex
from mapbuilder.store import MapHead

try:
    import fcntl
except ImportError:  # not on Windows: builds there are not shared
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

#: A build lock unused this long (seconds) is deleted when a file is kept.
LOCK_UNUSED_S = 86_400.0
#: Bumped whenever what a file holds changes shape.
FORMAT = 1
SUFFIX = ".index"


def _versions() -> str:
    """What an index's content depends on: the libraries' versions, and the code that builds
    it (hashed, so that an installation from a working copy changes it with every edit)."""
    import numpy
    import scipy
    import shapely

    import localizer
    from mapbuilder import store

    from . import map_index

    code = hashlib.sha256()
    for path in sorted(Path(localizer.__file__).parent.glob("*.py")) + [Path(store.__file__),
                                                                         Path(map_index.__file__)]:
        code.update(path.read_bytes())
    return f"numpy {numpy.__version__} scipy {scipy.__version__} shapely {shapely.__version__} {code.hexdigest()}"


def database_identity(url) -> str:
    """Which database a URL names, the same from any working directory: an SQLite file's
    resolved path, else the URL with its password masked."""
    from sqlalchemy.engine import make_url

    u = make_url(str(url)) if not hasattr(url, "drivername") else url
    if u.drivername.startswith("sqlite"):
        return "sqlite:" + os.path.realpath(u.database or ":memory:")
    return u.render_as_string(hide_password=True)


def index_files(settings, data_dir: Path, database_url) -> "IndexFiles | None":
    """The kept indexes as ``settings`` (:class:`service.settings.IndexDirSettings`) say; None: off."""
    directory = settings.index_directory(data_dir)
    if directory is None:
        return None
    return IndexFiles(directory, database_identity(database_url), settings.index_dir_from,
                      settings.index_dir_max_mb << 20)


def current_index(store, map_id: str, crs: str, coverage: str, files: "IndexFiles | None",
                  on_build=None) -> MapIndex:
    """The map's index at its revision now: read from ``files`` when one is kept, else an older
    one kept there updated with the edits since (:func:`~service.map_index.updated_index`), else
    built; kept there for the next process. ``on_build(count)`` is called before building a map of
    ``count`` markings that will be kept (``lanemap localize`` says that it takes a while)."""
    from .map_index import INDEXED_STATUSES, load_index, update_cap, updated_index

    count = 0 if files is None else store.get_map(map_id, with_count=True).count
    if files is None or count < files.min_markings:
        return load_index(store, map_id, crs, coverage)
    head = store.map_head(map_id)  # before the markings: a file never claims a newer revision
    kept = files.load(map_id, head, coverage, newer_than=head.revision - 1)
    if kept is not None:
        return kept.index
    with files.building(map_id, head, coverage):
        kept = files.load(map_id, head, coverage, newer_than=head.revision - 1)  # built by another process meanwhile
        if kept is not None:
            return kept.index
        older = None  # updated with the edits since, if few: counted before the file is read
        since = files.newest_revision(map_id, head, coverage)
        if since is not None:
            # The update's cap is a share of the index, not of the map: its rejected markings are
            # not in it. The index's size now differs from the file's by no more than the changes.
            indexed = store.count_markings(map_id, INDEXED_STATUSES)
            if store.count_changes(map_id, since) <= update_cap(indexed):
                older = files.load(map_id, head, coverage)
        imaged = store.imaged_footprint(map_id) if older is not None and coverage == "imagery" else None
        done = None if older is None else updated_index(store, map_id, older.index, older.revision, coverage, imaged)
        if done is not None:
            index, revision, _ = done
            files.save_updated(store, map_id, head.created, revision, coverage, index)
            return index
        if on_build is not None:
            on_build(count)
        index = load_index(store, map_id, crs, coverage)
        files.save(map_id, head, coverage, index)
    return index


#: Exit code of :func:`build_kept` when the index was built but could not be kept.
NOT_KEPT = 3


def build_kept(files: "IndexFiles", url: str, map_id: str, crs: str, coverage: str, head: MapHead) -> None:
    """A child process's work: build the map's index by ``coverage`` and keep it in ``files``, as
    at ``head`` (read by the parent before it started this). Exits with :data:`NOT_KEPT` when the
    file could not be written.

    The server builds a city's index so (``LANEMAP_INDEX_PROCESS_FROM``): in its own process the
    triangulation and the geometry of the extent hold the server's interpreter for up to 0.8 s at
    a time, and its peak memory, a gigabyte for 1,000,000 markings, stays with the server.
    """
    import signal
    import sys

    from mapbuilder.store import Store

    from .map_index import load_index

    # A Ctrl+C in the server's terminal reaches this process too; the server ends it when it stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    store = Store(url)
    try:
        index = load_index(store, map_id, crs, coverage)
    finally:
        store.close()
    if files.save(map_id, head, coverage, index, force=True) is None:
        sys.exit(NOT_KEPT)


def _digest(*parts: object, size: int = 20) -> str:
    return hashlib.sha256("\0".join(map(str, parts)).encode()).hexdigest()[:size]


@dataclass(frozen=True)
class KeptIndex:
    """An index read from a file, and the revision of the map it was built at."""

    index: MapIndex
    revision: int


class IndexFiles:
    """The folder of kept indexes (``LANEMAP_INDEX_DIR``).

    Parameters
    ----------
    directory : Path
        Created (mode 0700) on the first save.
    database : str
        :func:`database_identity` of the store's URL.
    min_markings : int
        Indexes of fewer markings are not kept (``LANEMAP_INDEX_DIR_FROM``):
        they build in milliseconds.
    max_bytes : int
        The folder's files are deleted, least recently used first, beyond this
        (``LANEMAP_INDEX_DIR_MAX_MB``).
    """

    def __init__(self, directory: Path, database: str, min_markings: int = 10_000, max_bytes: int = 2 << 30):
        self.directory = Path(directory)
        self.database = database
        self.min_markings = min_markings
        self.max_bytes = max_bytes
        self._versions = _versions()

    def _map_key(self, map_id: str, created: str) -> str:
        return _digest(FORMAT, self._versions, self.database, map_id, created)

    def _prefix(self, map_id: str, head: MapHead, coverage: str) -> str:
        return f"{self._map_key(map_id, head.created)}-{coverage}"

    def _name(self, map_id: str, head: MapHead, coverage: str) -> str:
        return f"{self._prefix(map_id, head, coverage)}-r{head.revision:010d}-{_digest(head.updated, size=12)}{SUFFIX}"

    def _kept(self, map_id: str, head: MapHead, coverage: str) -> list[tuple[int, Path]]:
        """This map's files (revision, path), newest first; those of another history deleted."""
        prefix = self._prefix(map_id, head, coverage) + "-r"
        current = self._name(map_id, head, coverage)
        out = []
        try:
            paths = list(self.directory.glob(prefix + "*" + SUFFIX))
        except OSError:
            return []
        for path in paths:
            try:
                revision = int(path.name[len(prefix):].split("-", 1)[0])
            except ValueError:
                continue
            if revision > head.revision or (revision == head.revision and path.name != current):
                log.info("%s: built from another history of map %s (a database restored?); deleted", path, map_id)
                _unlink(path)
                continue
            out.append((revision, path))
        return sorted(out, reverse=True)

    def newest_revision(self, map_id: str, head: MapHead, coverage: str) -> int | None:
        """The revision of the newest kept index of the map by ``coverage`` at or before ``head``'s,
        from the files' names (not read); None if none."""
        kept = self._kept(map_id, head, coverage)
        return kept[0][0] if kept else None

    def load(self, map_id: str, head: MapHead, coverage: str, newer_than: int = -1) -> KeptIndex | None:
        """The newest kept index of the map by ``coverage`` at or before ``head``'s revision and after
        ``newer_than``; None if none (``newer_than=head.revision - 1``: only a current one).

        A file that cannot be read back (cut short, of another version) is deleted.
        """
        for revision, path in self._kept(map_id, head, coverage):
            if revision <= newer_than:
                break
            index = self._read(path, map_id, head, coverage, revision)
            if index is not None:
                return KeptIndex(index, revision)
        return None

    def _read(self, path: Path, map_id: str, head: MapHead, coverage: str, revision: int) -> MapIndex | None:
        try:
            with open(path, "rb") as fh:
                st = os.fstat(fh.fileno())
                if not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid() or st.st_mode & 0o022:
                    log.warning("%s: not a file of this user's only; not read", path)
                    return None
                kept = pickle.load(fh)
            if not (isinstance(kept, dict) and kept.get("format") == FORMAT and isinstance(kept.get("index"), MapIndex)
                    and (kept.get("map"), kept.get("created"), kept.get("coverage"), kept.get("revision"))
                    == (map_id, head.created, coverage, revision)):
                raise ValueError("not the index its name says")
        except FileNotFoundError:  # deleted meanwhile (a newer one saved by another process)
            return None
        except Exception as exc:  # noqa: BLE001 - a bad file is a cache miss, and goes
            log.warning("%s: cannot be read back (%s); deleted", path, exc)
            _unlink(path)
            return None
        with contextlib.suppress(OSError):
            os.utime(path)  # used: the last to go when the folder is full
        return kept["index"]

    def save_updated(self, store, map_id: str, created: str, revision: int, coverage: str,
                     index: MapIndex) -> Path | None:  # fmt: skip
        """:meth:`save` an index updated to ``revision`` of the map made at ``created``, if that is
        still the map's head: an older revision would replace the newest file another process kept."""
        now = store.map_head(map_id)
        if (now.revision, now.created) != (revision, created):
            return None
        return self.save(map_id, now, coverage, index)

    def save(self, map_id: str, head: MapHead, coverage: str, index: MapIndex, force: bool = False) -> Path | None:
        """Keep ``index``, built from the map at ``head`` by ``coverage``; its file, or None if not kept.

        The extent is drawn first, so that the file holds it. Older files of the
        map by the same coverage go; a failure to write (a full disk, a folder
        that cannot be written) is logged, not raised: the index is kept in
        memory all the same. An index of fewer than ``min_markings`` is kept only
        with ``force``.
        """
        if len(index) < self.min_markings and not force:
            return None
        kept = self._kept(map_id, head, coverage)
        if kept and kept[0][0] == head.revision:
            return kept[0][1]  # another process kept it meanwhile
        _ = index.extent
        path = self.directory / self._name(map_id, head, coverage)
        tmp = None
        try:
            self.directory.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".", suffix=".part", dir=self.directory)  # mode 0600
            with os.fdopen(fd, "wb") as fh:
                pickle.dump({"format": FORMAT, "map": map_id, "created": head.created, "revision": head.revision,
                             "updated": head.updated, "coverage": coverage, "index": index}, fh, protocol=5)
            os.replace(tmp, path)
        except OSError as exc:
            log.warning("map %s: its index could not be kept in %s: %s", map_id, self.directory, exc)
            if tmp is not None:
                _unlink(Path(tmp))
            return None
        for _, older in kept:
            _unlink(older)
        self._trim(keep=path)
        return path

    def _trim(self, keep: Path) -> None:
        """Delete the least recently used files beyond ``max_bytes`` (never ``keep``), and the
        locks of builds none took for a day (a map's deleted, or built by an older version)."""
        stale = time.time() - LOCK_UNUSED_S
        for path in self.directory.glob("*.lock"):
            with contextlib.suppress(OSError):
                if path.stat().st_mtime < stale:
                    path.unlink()
        files = []
        for path in self.directory.glob("*" + SUFFIX):
            with contextlib.suppress(OSError):
                st = path.stat()
                files.append((st.st_mtime, st.st_size, path))
        total = sum(size for _, size, _ in files)
        for _, size, path in sorted(files, key=lambda f: f[0]):
            if total <= self.max_bytes:
                break
            if path != keep:
                log.info("%s: deleted, the least recently used of %s beyond %d MB", path, self.directory,
                         self.max_bytes >> 20)
                _unlink(path)
                total -= size

    def forget(self, map_id: str, created: str) -> None:
        """Delete the kept indexes of a map deleted from the database (``created``: its head's), by
        every coverage: what they hold is the deleted map's."""
        for path in self.directory.glob(self._map_key(map_id, created) + "-*"):
            _unlink(path)

    @contextlib.contextmanager
    def building(self, map_id: str, head: MapHead, coverage: str) -> Iterator[None]:
        """Held while this process builds the map's index: another process that wants it
        waits, then reads the file instead of building it too (the workers of one server at
        its start)."""
        lock = None
        if fcntl is not None:
            try:
                self.directory.mkdir(mode=0o700, parents=True, exist_ok=True)
                path = self.directory / (self._prefix(map_id, head, coverage) + ".lock")
                lock = os.fdopen(os.open(path, os.O_RDWR | os.O_CREAT, 0o600), "r+")
                fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
                os.utime(path)  # used: kept by _trim
            except OSError as exc:
                log.debug("no lock on the build of map %s: %s", map_id, exc)
        try:
            yield
        finally:
            if lock is not None:
                lock.close()  # releases the lock


def _unlink(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink()

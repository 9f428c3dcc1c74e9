"""The map store: the one module every part reads and writes maps through.

SQLAlchemy 2 Core over SQLite (default: a file, WAL mode, foreign keys on, a
busy timeout, write transactions taken with ``BEGIN IMMEDIATE``) or PostgreSQL
(``LANEMAP_DATABASE_URL=postgresql://...``), with the same code for both. The
schema belongs to Alembic (``migrations/``): an empty database is upgraded on
first use, an older one must be upgraded with ``lanemap db upgrade``.

Every write is one transaction; a failure leaves the database as it was.
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
from bisect import bisect_right
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from operator import itemgetter
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import orjson
from sqlalchemy import (
    Text, and_, bindparam, case, create_engine, delete, event, func, insert, literal, literal_column, or_, select,
    text, tuple_, type_coerce, update,
)  # fmt: skip
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine, make_url
from sqlalchemy.exc import DBAPIError, IntegrityError

from . import migrate
from .crs import CRSError, from_wgs84, metric_crs, to_wgs84, utm_crs_for
from .model import SOURCES, STATUSES, Marking
from .schema import (
    GRID_CELL_M, QUEUED, changesets, edits, imaged_ground, imagery, job_tiles, jobs, maps, marking_counts, markings,
    removed_markings, retired_maps,
)  # fmt: skip
from .settings import Settings

log = logging.getLogger(__name__)

MAP_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
JOB_STATUSES = ("accepted", "running", "successful", "failed", "dismissed")
#: Seconds to wait for a PostgreSQL connection unless the URL sets ``connect_timeout``.
PG_CONNECT_TIMEOUT_S = 10
#: The grid the ground a map's builds imaged is joined on, metres (:meth:`Store.imaged_footprint`).
GROUND_GRID_M = 0.001
#: Distance within which a person's decision suppresses a rebuilt detection, metres.
SUPPRESS_RADIUS_M = 0.5
#: Rows :meth:`Store.marking_arrays` reads and converts at a time.
_ARRAYS_PART = 10_000

_MARKING_FIELDS = (
    "x", "y", "length_m", "width_m", "bearing_deg", "weight", "score", "kind",
    "source", "status", "x0", "y0", "x1", "y1", "tile_key", "extra",
)  # fmt: skip
#: Fields a caller may change on an existing marking (lon/lat are converted to x/y).
EDITABLE_FIELDS = frozenset(_MARKING_FIELDS) | {"lon", "lat"}



class StoreError(ValueError):
    """Base class of the store's errors; the message names the problem."""


class UnknownMapError(StoreError):
    def __init__(self, map_id: str):
        super().__init__(f"unknown map {map_id!r}")
        self.map_id = map_id


class MapExistsError(StoreError):
    def __init__(self, map_id: str):
        super().__init__(f"map {map_id!r} already exists")
        self.map_id = map_id


class UnknownMarkingError(StoreError):
    def __init__(self, map_id: str, marking_id: int):
        super().__init__(f"map {map_id!r} has no marking {marking_id}")
        self.map_id, self.marking_id = map_id, marking_id


class UnknownJobError(StoreError):
    def __init__(self, job_id: int):
        super().__init__(f"unknown job {job_id}")
        self.job_id = job_id


class UnknownImageryError(StoreError):
    def __init__(self, imagery_id: int):
        super().__init__(f"unknown imagery {imagery_id}")
        self.imagery_id = imagery_id


class UnknownChangesetError(StoreError):
    def __init__(self, map_id: str, changeset_id: int):
        super().__init__(f"map {map_id!r} has no changeset {changeset_id}")
        self.changeset_id = changeset_id


class InvalidMarkingError(StoreError):
    """A marking's values are out of range; nothing was written."""


class SchemaError(StoreError):
    """The database schema is not the one this version of lanemap needs."""


class StoreUnavailableError(StoreError):
    """The database cannot be reached."""


@dataclass
class Conflict:
    """One change of a changeset that cannot apply."""

    id: int
    reason: str  # "version" | "missing" | "exists"
    expected_version: int | None = None
    actual_version: int | None = None


class ConflictError(StoreError):
    """Some changes of a changeset met a newer or missing marking; nothing was written."""

    def __init__(self, conflicts: list[Conflict]):
        ids = ", ".join(str(c.id) for c in conflicts)
        super().__init__(f"{len(conflicts)} conflicting marking(s): {ids}")
        self.conflicts = conflicts


@dataclass
class MapInfo:
    id: str
    title: str
    crs: str | None
    bounds: tuple[float, float, float, float] | None  # storage CRS
    revision: int
    created_at: datetime
    updated_at: datetime
    count: int | None = None
    #: The oldest revision the change feed answers from (0: every one; :meth:`Store.prune_removed`).
    feed_since: int = 0
    #: How far the map speaks for the ground (:data:`MAP_COVERAGES`); None: as the server is set.
    coverage: str | None = None

    def bounds_wgs84(self) -> tuple[float, float, float, float] | None:
        """Bounds as (west, south, east, north), degrees."""
        if self.bounds is None or self.crs is None:
            return None
        return to_wgs84(self.crs).transform_bounds(*self.bounds, densify_pts=21)


#: Bins of :attr:`MapSummary.unreviewed_scores`: the detections' scores, 0-1.
SCORE_BINS = 10


class MapHead(NamedTuple):
    """What a cache of a map's content checks on every use (:meth:`Store.map_head`)."""

    #: The map's revision: it moves on with every write to its markings.
    revision: int
    #: How far the map speaks for the ground; None: as the server is set.
    coverage: str | None
    #: When the map was made: tells a map made anew under a deleted one's id from it.
    created: str
    #: When the map last changed: with the revision, it tells the same revision of a map
    #: written twice (a database restored from a backup, then edited) from itself.
    updated: str


class _Selection(NamedTuple):
    """What a read of a map's markings reads (:meth:`Store._selection`)."""

    #: The WHERE clause; None when no marking can match (a box beside the map).
    where: Any
    #: The lon/lat box it reads, clipped to the map (:meth:`Store._box_within`); None: the whole map.
    box: tuple[float, float, float, float] | None
    #: What to order the markings by: their id, or an expression of it (``_BOXED_ID``).
    key: Any
    #: The state of the map it reads (:func:`_state_of`).
    state: tuple
    #: The statuses it selects, sorted; empty: all.
    statuses: tuple[str, ...]
    #: Whether the box is read along the map's ids, tested marking by marking (``WIDE_BOX_SHARE``).
    wide: bool = False


def _state_of(info: MapInfo) -> tuple:
    """What tells one state of a map's markings from another, as :class:`MapHead` does: the
    revision every write moves on, when the map was made (a map made anew under a deleted
    one's id) and last changed (the same revision written twice, after a restore)."""
    return info.revision, info.created_at, info.updated_at


@dataclass
class MapSummary:
    """What a map holds, counted (:meth:`Store.summary`): how far its review has come.

    Attributes
    ----------
    revision : int
        The map's revision the counts were read at.
    count : int
        Markings in the map.
    by_status, by_source, by_kind : dict of str to int
        Markings per status, per source and per kind (``"unknown"`` for none);
        only values that occur.
    detections : dict of str to int
        Detected markings per status (``unreviewed``, ``accepted``, ``rejected``,
        each present): the review of what the builds found.
    unreviewed_scores : list of int
        Unreviewed detections per score bin, ``SCORE_BINS`` bins of equal width
        from 0 to 1 (the last includes 1); detections without a score are in
        none of them.
    """

    revision: int
    count: int
    by_status: dict[str, int]
    by_source: dict[str, int]
    by_kind: dict[str, int]
    detections: dict[str, int]
    unreviewed_scores: list[int]

    @property
    def reviewed_share(self) -> float | None:
        """The share of detections accepted or rejected; None for a map without detections."""
        total = sum(self.detections.values())
        return None if total == 0 else 1.0 - self.detections.get("unreviewed", 0) / total


class StaleRevisionError(StoreError):
    """A change feed was asked for the changes since a revision it cannot answer from: one the
    map has not reached (a database restored from an older backup), one from before the map
    was made anew under its id, or one from before the deletions it still keeps."""


@dataclass
class Changes:
    """A page of a map's changes since a revision (:meth:`Store.changes`), oldest first.

    Attributes
    ----------
    revision : int
        The map's revision this page was read at. After the last page (``more``
        False) a copy that applied every page is at this revision.
    changed : list of (int, Marking)
        Markings written since, with the revision that wrote them last: what a
        copy should now hold under their ids.
    removed : list of (int, int)
        ``(revision, id)`` of markings deleted since (or, with a status filter,
        whose status left it): what a copy should no longer hold.
    more : bool
        Whether more changes follow; ask again from ``after``.
    after : (int, int) or None
        The ``(revision, id)`` of this page's last change: where the next page starts.
    crs : str or None
        The map's storage CRS (None while it has none): what a copy needs to
        use the markings in the metric frame the map keeps them in.
    """

    revision: int
    changed: list[tuple[int, Marking]]
    removed: list[tuple[int, int]]
    more: bool
    after: tuple[int, int] | None
    crs: str | None = None


@dataclass
class MarkingArrays:
    """A map's markings as arrays, for numerics (the localizer's index)."""

    id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    weight: np.ndarray
    length_m: np.ndarray
    bearing_deg: np.ndarray
    kind: np.ndarray  # object: "dash", "solid", "stop_line", ... or None where unknown
    source: np.ndarray | None = None  # object: "detected", "imported", ...; None: not read

    def __len__(self) -> int:
        return len(self.id)


@dataclass
class JobInfo:
    id: int
    kind: str
    map_id: str | None
    status: str
    progress: float
    params: dict[str, Any]
    error: str | None
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


@dataclass
class ImageryInfo:
    id: int
    map_id: str
    path: str
    crs: str
    bounds: tuple[float, float, float, float]
    resolution_m: float
    created_at: datetime


@dataclass
class Change:
    """One change of a changeset.

    ``op`` is ``create`` (``marking`` given), ``update`` (``id``, ``fields``; a
    partial set of :data:`EDITABLE_FIELDS`) or ``delete`` (``id``). ``version``,
    when given, must equal the marking's current version.
    """

    op: str
    id: int | None = None
    version: int | None = None
    marking: Marking | None = None
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass
class ReviewResult:
    """What a review by score did or would do (:meth:`Store.review_by_score`)."""

    accepted: int
    rejected: int
    #: The changeset that recorded it; None for a dry run, or when nothing matched.
    changeset_id: int | None = None
    #: The map's revision after it (before it, for a dry run).
    revision: int = 0


@dataclass
class ChangesetResult:
    changeset_id: int
    results: list[dict[str, Any]]  # {"op", "id", "version"} per change, in order
    #: The markings as this changeset wrote them (created and updated ones), by id. A later
    #: read may already show another writer's change; answers about this write use these.
    markings: Mapping[int, Marking] = field(default_factory=dict)


class _LoggedMarkings(Mapping):
    """The markings a revert wrote, by id, made from the states it logged when asked for: an
    answer names one marking at most, and making all of a review's 300,000 took 2.6 s."""

    def __init__(self, states: dict[int, dict[str, Any]]):
        self._states = states

    def __getitem__(self, marking_id: int) -> Marking:
        return Marking(**{**self._states[marking_id], "id": marking_id})

    def __iter__(self) -> Iterator[int]:
        return iter(self._states)

    def __len__(self) -> int:
        return len(self._states)


@dataclass
class ChangesetInfo:
    id: int
    map_id: str
    who: str
    at: datetime
    comment: str
    n_create: int
    n_update: int
    n_delete: int
    reverts: int | None


@dataclass
class EditInfo:
    id: int
    changeset_id: int
    marking_id: int | None
    op: str
    who: str
    at: datetime
    before: dict[str, Any] | None
    after: dict[str, Any] | None
    comment: str


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _utc(value: datetime | None) -> datetime | None:
    # SQLite hands back naive datetimes; everything stored is UTC.
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=timezone.utc)
    return value


def _stamp(value: datetime | str) -> str:
    """A stored time as one string, whichever driver read it (SQLite's text, a datetime, naive or
    not, in any session time zone): UTC, ISO 8601, to the microsecond."""
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    return _utc(value).astimezone(timezone.utc).isoformat(timespec="microseconds")


def normalize_url(url: str) -> str:
    """Pick the psycopg 3 driver for plain ``postgresql://`` URLs."""
    for prefix in ("postgres://", "postgresql://"):
        if url.startswith(prefix):
            return "postgresql+psycopg://" + url[len(prefix) :]
    return url


def check_map_id(map_id: str) -> str:
    if not isinstance(map_id, str) or not MAP_ID_RE.match(map_id):
        raise StoreError(
            f"invalid map id {map_id!r}: use 1-64 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    return map_id


def _finite(name: str, value: Any, *, optional: bool = False) -> float | None:
    if value is None and optional:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidMarkingError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InvalidMarkingError(f"{name} must be finite, got {value!r}")
    return v


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):  # json takes numpy's float64 (a float); take its kin alike
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


def dumps_json(value: Any) -> str:
    """The JSON text the store writes (its ``JSON`` columns: extras, the edit log's states).

    orjson, not :mod:`json`: a review of 300,000 detections logs 600,000 marking states, and
    its revert reads them back; json spent 5.5 s writing and 11.4 s reading them."""
    return orjson.dumps(value, default=_json_default, option=orjson.OPT_NON_STR_KEYS).decode()


def loads_json(text: str | bytes) -> Any:
    """What :func:`dumps_json` wrote, or :mod:`json` before it: a ``NaN`` that json wrote (which
    orjson does not read) reads as json read it."""
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError:
        return json.loads(text)


def _check_json(name: str, value: Any) -> None:
    """Refuse what JSON cannot hold: numbers that are not finite (SQLite would store them, and
    the map could then not be exported or served) and values that are not JSON at all."""
    try:
        json.dumps(value, allow_nan=False, default=_json_default)
        dumps_json(value)  # nested deeper than orjson writes (255)
    except ValueError as exc:
        if "float" in str(exc):  # "Out of range float values are not JSON compliant"
            raise InvalidMarkingError(f"{name} holds a number that is not finite (JSON has no NaN or "
                                      "Infinity)") from None
        raise InvalidMarkingError(f"{name} is not JSON: {exc}") from None
    except (TypeError, RecursionError) as exc:
        raise InvalidMarkingError(f"{name} is not JSON: {exc}") from None


def marking_row(m: Marking, crs: str, now: datetime) -> dict[str, Any]:
    """Validate a marking and turn it into a ``markings`` row (without id/map_id)."""
    x, y = _finite("x", m.x), _finite("y", m.y)
    weight = _finite("weight", m.weight)
    if weight <= 0:
        raise InvalidMarkingError(f"weight must be > 0, got {m.weight!r}")
    length, width = _finite("length_m", m.length_m), _finite("width_m", m.width_m)
    if length < 0 or width < 0:
        raise InvalidMarkingError("length_m and width_m must be >= 0")
    if m.source not in SOURCES:
        raise InvalidMarkingError(f"source must be one of {', '.join(SOURCES)}, got {m.source!r}")
    if m.status not in STATUSES:
        raise InvalidMarkingError(
            f"status must be one of {', '.join(STATUSES)}, got {m.status!r}"
        )
    lon, lat = to_wgs84(crs).transform(x, y)
    if not (math.isfinite(lon) and math.isfinite(lat) and -180 <= lon <= 180 and -90 <= lat <= 90):
        raise InvalidMarkingError(f"x={x}, y={y} is outside the valid area of {crs}")
    extra = m.extra if m.extra is not None else {}
    if not isinstance(extra, dict):
        raise InvalidMarkingError("extra must be a JSON object")
    if extra:
        _check_json("extra", extra)
    return {
        "tile_key": m.tile_key,
        "gx": math.floor(x / GRID_CELL_M),
        "gy": math.floor(y / GRID_CELL_M),
        "x": x,
        "y": y,
        "lon": lon,
        "lat": lat,
        "weight": weight,
        "length_m": length,
        "width_m": width,
        "bearing_deg": _finite("bearing_deg", m.bearing_deg) % 180.0,
        "score": _finite("score", m.score, optional=True),
        "kind": m.kind,
        "source": m.source,
        "status": m.status,
        "x0": _finite("x0", m.x0, optional=True),
        "y0": _finite("y0", m.y0, optional=True),
        "x1": _finite("x1", m.x1, optional=True),
        "y1": _finite("y1", m.y1, optional=True),
        "extra": extra,
        "created_at": now,
        "updated_at": now,
    }


def _update_many(conn: Connection, rows: list[dict[str, Any]]) -> None:
    """UPDATE markings by id (``_id``) to the values ``_v_<column>``, in one ``executemany``.

    Every row gives the same columns: a changeset's updates write whole rows, a review by
    score the status and what moves with it.
    """
    if not rows:
        return
    cols = [k[3:] for k in rows[0] if k.startswith("_v_")]
    dialect = conn.dialect
    pg = dialect.name == "postgresql" and dialect.driver == "psycopg"
    if not pg and not (dialect.name == "sqlite" and dialect.paramstyle == "qmark"):
        stmt = update(markings).where(markings.c.id == bindparam("_id")).values(
            {c: bindparam(f"_v_{c}") for c in cols})  # fmt: skip
        conn.execute(stmt, rows)
        return
    # As _insert_many: SQLAlchemy's parameters, built row by row, cost more than the update.
    columns = [_bound(dialect, markings.c[c], [r[f"_v_{c}"] for r in rows]) for c in cols]
    columns.append([r["_id"] for r in rows])
    quote = dialect.identifier_preparer
    mark = "%s" if pg else "?"
    sql = (f"UPDATE {quote.format_table(markings)} SET {', '.join(f'{quote.quote(c)} = {mark}' for c in cols)} "
           f"WHERE {quote.quote('id')} = {mark}")
    if not pg:
        conn.exec_driver_sql(sql, list(zip(*columns)))
        return
    raw = conn.connection.dbapi_connection
    try:
        with raw.cursor() as cur:
            if len(rows) < PG_COPY_UPDATE_FROM:
                cur.executemany(sql, list(zip(*columns)))
                return
            # Row by row, PostgreSQL waits a round trip per marking (10 s for a review's 66,000):
            # the rows are copied into a table of this transaction and updated in one statement.
            names = [quote.quote(c) for c in cols]
            sql = (f"CREATE TEMPORARY TABLE lanemap_update ON COMMIT DROP AS SELECT {', '.join(names)}, "
                   f"{quote.quote('id')} FROM {quote.format_table(markings)} WITH NO DATA")
            cur.execute(sql)
            sql = f"COPY lanemap_update ({', '.join(names)}, {quote.quote('id')}) FROM STDIN"
            with cur.copy(sql) as out:
                for row in zip(*columns):
                    out.write_row(row)
            sql = (f"UPDATE {quote.format_table(markings)} AS m SET {', '.join(f'{n} = u.{n}' for n in names)} "
                   f"FROM lanemap_update AS u WHERE m.{quote.quote('id')} = u.{quote.quote('id')}")
            cur.execute(sql)
            cur.execute("DROP TABLE lanemap_update")
    except dialect.loaded_dbapi.Error as exc:
        raise _driver_error(conn, raw, sql, exc) from None


def _bound(dialect, column, values: list) -> list:
    """``values`` of ``column`` as the driver takes them: its bind processor run over them (once
    where every row has the same object, such as a changeset's timestamp)."""
    proc = column.type.dialect_impl(dialect).bind_processor(dialect)
    if proc is None:
        return values
    first = values[0]
    if all(v is first for v in values):
        return [proc(first)] * len(values)
    return list(map(proc, values))


def _insert_many(conn: Connection, table, rows: list[dict[str, Any]]) -> None:
    """INSERT rows that all have the same keys, in the connection's transaction.

    SQLAlchemy builds and processes each row's parameters one at a time; for
    the tens of thousands of markings of a build that is most of the client's
    CPU. Here each column's bind processor runs column by column (once for a
    value every row shares, such as the timestamps) and the rows go to the
    driver directly: ``executemany`` on SQLite, ``COPY ... FROM STDIN`` on
    PostgreSQL (psycopg). Other drivers take the SQLAlchemy path.
    """
    if not rows:
        return
    dialect = conn.dialect
    copy = dialect.name == "postgresql" and dialect.driver == "psycopg"
    if not copy and not (dialect.name == "sqlite" and dialect.paramstyle == "qmark"):
        conn.execute(insert(table), rows)
        return
    keys = list(rows[0])
    columns = [_bound(dialect, table.c[k], [r[k] for r in rows]) for k in keys]
    quote = dialect.identifier_preparer
    names = ", ".join(quote.quote(k) for k in keys)
    if copy:
        sql = f"COPY {quote.format_table(table)} ({names}) FROM STDIN"
        raw = conn.connection.dbapi_connection
        try:
            with raw.cursor() as cur, cur.copy(sql) as out:
                for row in zip(*columns):
                    out.write_row(row)
        except dialect.loaded_dbapi.Error as exc:
            raise _driver_error(conn, raw, sql, exc) from None
        return
    conn.exec_driver_sql(f"INSERT INTO {quote.format_table(table)} ({names}) "
                         f"VALUES ({', '.join('?' * len(keys))})", list(zip(*columns)))


def _driver_error(conn: Connection, raw, sql: str, exc: Exception) -> DBAPIError:
    """A driver's error as SQLAlchemy would raise it, so that the store maps an outage as usual."""
    dialect = conn.dialect
    lost = dialect.is_disconnect(exc, raw, None)
    if lost:
        conn.invalidate()
    return DBAPIError.instance(sql, None, exc, dialect.loaded_dbapi.Error, connection_invalidated=lost)


def _driver_parts(conn: Connection, sql: str, params: tuple, size: int):
    """The rows of ``sql`` (its parameters as ``?``) read straight from the driver, ``size`` at a
    time, as tuples, within ``conn``'s transaction; None for a driver this does not know.

    SQLAlchemy's rows cost more than reading them: 1.6 of 4.3 s for the 1,000,000 markings of a
    city's index. PostgreSQL's are read through a server-side cursor, a part at a time.
    """
    dialect = conn.dialect
    pg = dialect.name == "postgresql" and dialect.driver == "psycopg"
    if not pg and not (dialect.name == "sqlite" and dialect.paramstyle == "qmark"):
        return None

    def parts():
        raw = conn.connection.dbapi_connection
        text_ = sql.replace("?", "%s") if pg else sql
        try:
            cur = raw.cursor(name="lanemap_rows") if pg else raw.cursor()
            try:
                cur.execute(text_, params)
                while rows := cur.fetchmany(size):
                    yield rows
            finally:
                cur.close()
        except dialect.loaded_dbapi.Error as exc:
            raise _driver_error(conn, raw, text_, exc) from None

    return parts()


#: Ids per ``IN (...)`` of a statement: a changeset's ids would pass the drivers' limits on
#: parameters (PostgreSQL 65,535; SQLite 250,000 as Debian builds it, 999 before 3.32).
ID_CHUNK = 900

#: How far a lon/lat box's search reaches past the box in the storage CRS, metres; the markings'
#: stored lon/lat then decide exactly.
BOX_PAD_M = 0.01

#: How far past a map's lon/lat bounds a box must reach to be read as the whole map, degrees
#: (about 10 cm): the bounds are those of its storage CRS's box, drawn on 21 points a side.
COVER_MARGIN_DEG = 1e-6

#: Markings written per statement (or ``COPY``) of an import.
INSERT_BATCH = 5000

#: Share of a map's lon/lat bounds from which a box is read through the map's ids in order, each
#: marking tested against the box, rather than through the grid and sorted (:meth:`Store._selection`).
WIDE_BOX_SHARE = 0.05

#: Counts of boxes a store keeps, each for one state of its map (:meth:`Store._box_count`).
BOX_COUNTS_KEPT = 256

#: A load of at least this many markings has PostgreSQL count the table again (``ANALYZE``).
ANALYZE_FROM = 10_000

#: Updates of at least this many markings go to PostgreSQL by ``COPY`` and one ``UPDATE``.
PG_COPY_UPDATE_FROM = 200

#: Longest map title, characters.
MAX_TITLE_LENGTH = 500
#: How far a map speaks for the ground, for localization's check at its edge:
#: ``"hull"``, everything painted within its markings' convex hull is in it (an
#: area mapped whole); ``"markings"``, only the ground between its markings (a
#: route, or parts of a city whose streets go on unmapped inside that hull);
#: ``"imagery"``, the ground its builds imaged (:meth:`Store.imaged_footprint`)
#: and the ground between its markings beyond it (a map built from imagery).
MAP_COVERAGES = ("hull", "markings", "imagery")


def check_coverage(coverage: str | None) -> None:
    """Refuse a map coverage that is not one of :data:`MAP_COVERAGES` (None: the server's)."""
    if coverage is not None and coverage not in MAP_COVERAGES:
        raise StoreError(f"coverage: must be one of {', '.join(MAP_COVERAGES)}, got {coverage!r}")

#: What a Marking is read from in bulk: no timestamps (parsing them dominates big
#: reads) and ``extra`` as raw text, decoded only when it holds something.
_READ_COLUMNS = [
    type_coerce(c, Text).label("extra") if c.name == "extra" else c
    for c in markings.c
    if c.name not in ("created_at", "updated_at", "map_id", "gx", "gy", "revision")
]
_READ_NAMES = [c.name for c in _READ_COLUMNS]


def _markings_from_rows(rows) -> list[Marking]:
    out = []
    for row in rows:
        d = dict(zip(_READ_NAMES, row))
        e = d["extra"]
        if isinstance(e, str):
            d["extra"] = loads_json(e) if e not in ("{}", "") else {}
        elif e is None:
            d["extra"] = {}
        out.append(Marking(**d))
    return out


def _marking_from_row(r) -> Marking:
    return Marking(
        id=r.id, x=r.x, y=r.y, lon=r.lon, lat=r.lat, length_m=r.length_m, width_m=r.width_m,
        bearing_deg=r.bearing_deg, weight=r.weight, score=r.score, kind=r.kind,
        source=r.source, status=r.status, x0=r.x0, y0=r.y0, x1=r.x1, y1=r.y1,
        tile_key=r.tile_key, extra=dict(r.extra or {}), version=r.version,
    )  # fmt: skip


def marking_to_json(m: Marking) -> dict[str, Any]:
    """A marking as a JSON-safe dict (the edit log's before/after)."""
    return {k: getattr(m, k) for k in _JSON_FIELDS}


def _row_json(r) -> dict[str, Any]:
    """``marking_to_json(_marking_from_row(r))`` without the Marking: a large changeset's log
    converts every marking it touches. ``r`` is a row of ``select(markings)``, whose values
    are taken by position (by name they cost 6 s of a review of 300,000 detections), or the
    values a change wrote (:func:`_row_obj`)."""
    if isinstance(r, _RowObj):
        d = {k: getattr(r, k) for k in _JSON_FIELDS}
    else:
        d = dict(zip(_JSON_FIELDS, _MARKING_ROW_JSON(r)))
    d["extra"] = dict(d["extra"] or {})
    return d


#: A marking's id in the reads of a box, as an expression, so that no index of ids serves them.
#: With the column, SQLite (no statistics) would rather walk the whole map in id order
#: (``ix_markings_map``) and test every marking against the box than read the box through the
#: grid index and sort it: 221 ms instead of 3 ms for a page of a box of 54 markings among
#: 1,000,000.
_BOXED_ID = markings.c.id + literal_column("0")


#: The lower edges of the summary's score bins.
_BIN_EDGES = [k / SCORE_BINS for k in range(SCORE_BINS)]


def _count_key(status: str, source: str, kind: str | None, score: float | None) -> tuple[str, str, str, int]:
    """A marking's row of ``marking_counts``: its status, source, kind ('' where unknown) and
    score bin, k where ``k / SCORE_BINS <= score < (k + 1) / SCORE_BINS`` (the last bin open
    above, as the summary compares), -1 without a score or below 0."""
    b = -1 if score is None or score < 0 else bisect_right(_BIN_EDGES, score) - 1
    return status, source, kind or "", b


def _dict_key(d: dict[str, Any]) -> tuple[str, str, str, int]:
    """:func:`_count_key` of a marking as a dict: a row to write, or a state the edit log holds."""
    return _count_key(d["status"], d["source"], d["kind"], d["score"])


def _tally(conn: Connection, map_id: str, delta: Counter) -> None:
    """Add ``delta`` ({count key: markings more or fewer}) to the map's ``marking_counts``, in
    the transaction that wrote those markings."""
    rows = [dict(map_id=map_id, status=k[0], source=k[1], kind=k[2], score_bin=k[3], n=n)
            for k, n in delta.items() if n]  # fmt: skip
    if not rows:
        return
    upsert = postgresql.insert if conn.dialect.name == "postgresql" else sqlite.insert
    stmt = upsert(marking_counts)
    stmt = stmt.on_conflict_do_update(index_elements=list(marking_counts.primary_key.columns),
                                      set_={"n": marking_counts.c.n + stmt.excluded.n})  # fmt: skip
    conn.execute(stmt, rows)


def _changed_fields(pairs: Iterable[tuple[dict[str, Any], dict[str, Any]]]) -> list[str]:
    """The editable fields (:data:`_MARKING_FIELDS`) that differ between the states of any
    (before, after) pair: compared as tuples of the fields not yet found changed, so that a
    review's 200,000 pairs cost a tuple comparison each, not sixteen."""
    rest, changed = list(_MARKING_FIELDS), set()
    get = itemgetter(*rest)
    for b, a in pairs:
        if get(b) != get(a):
            changed.update(k for k in rest if b[k] != a[k])
            rest = [k for k in rest if k not in changed]
            if not rest:
                break
            get = itemgetter(*rest)
    return [k for k in _MARKING_FIELDS if k in changed]


def _bounds_of(xs: Sequence[float], ys: Sequence[float]) -> tuple[float, float, float, float]:
    return (min(xs), min(ys), max(xs), max(ys))


def _changeset_info(r) -> ChangesetInfo:
    return ChangesetInfo(r.id, r.map_id, r.who, _utc(r.at), r.comment, r.n_create, r.n_update,
                         r.n_delete, r.reverts)  # fmt: skip


def _edit_info(r) -> EditInfo:
    return EditInfo(r.id, r.changeset_id, r.marking_id, r.op, r.who, _utc(r.at), r.before, r.after,
                    r.comment)  # fmt: skip


class Store:
    """Access to the map database.

    Parameters
    ----------
    url : str, optional
        SQLAlchemy URL; default from :class:`~mapbuilder.settings.Settings`.
    upgrade : bool
        Apply the schema to an empty database (default). A database at an older
        schema revision is never changed implicitly: :meth:`upgrade` does that.
    """

    def __init__(self, url: str | None = None, *, upgrade: bool = True):
        self.url = normalize_url(url or Settings().resolved_database_url())
        self.engine = self._make_engine(self.url)
        self.dialect = self.engine.dialect.name
        self._counts: OrderedDict[tuple, int] = OrderedDict()
        self._counts_lock = threading.Lock()
        if upgrade:
            self._ensure_schema()

    # ------------------------------------------------------------------ engine
    @staticmethod
    def _make_engine(url: str) -> Engine:
        try:
            parsed = make_url(url)
        except Exception as exc:
            raise StoreError(f"invalid database URL {url!r}") from exc
        if parsed.get_backend_name() == "sqlite":
            if parsed.database and parsed.database != ":memory:":
                Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
            engine = create_engine(url, connect_args={"timeout": 60}, json_serializer=dumps_json,
                                   json_deserializer=loads_json)

            @event.listens_for(engine, "connect")
            def _sqlite_connect(dbapi_conn, _record):
                # Let SQLAlchemy's "begin" event below decide how transactions start.
                dbapi_conn.isolation_level = None
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA foreign_keys=ON")
                cur.execute("PRAGMA busy_timeout=60000")
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.close()

            @event.listens_for(engine, "begin")
            def _sqlite_begin(conn):
                # Writers take the lock up front: a deferred transaction that later
                # writes can fail with "database is locked" instead of waiting.
                write = conn.get_execution_options().get("lanemap_write", False)
                conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

            return engine
        if parsed.get_backend_name() == "postgresql":
            # pre-ping: a connection the server dropped (restart, failover) is replaced
            # before use instead of failing a request. connect_timeout: an unreachable
            # host fails a request in seconds, not after the OS's TCP timeout.
            connect_args = {}
            if "connect_timeout" not in parsed.query:
                connect_args["connect_timeout"] = PG_CONNECT_TIMEOUT_S
            return create_engine(url, pool_pre_ping=True, connect_args=connect_args, json_serializer=dumps_json,
                                 json_deserializer=loads_json)
        raise StoreError(f"unsupported database {parsed.get_backend_name()!r}: use sqlite or postgresql")

    @contextmanager
    def _tx(self, write: bool, snapshot: bool = False) -> Iterator[Connection]:
        try:
            with self.engine.connect() as conn:
                conn = conn.execution_options(lanemap_write=write)
                if snapshot and self.dialect == "postgresql":
                    conn = conn.execution_options(isolation_level="REPEATABLE READ")
                with conn.begin():
                    if snapshot and self.dialect == "postgresql":
                        conn.exec_driver_sql("SET TRANSACTION READ ONLY")
                    yield conn
        except DBAPIError as exc:
            if exc.connection_invalidated or isinstance(exc.orig, (OSError,)) or _is_connect_error(exc):
                raise StoreUnavailableError(f"database unavailable: {exc.orig}") from exc
            raise

    def _read(self):
        return self._tx(write=False)

    def _write(self):
        return self._tx(write=True)

    def snapshot(self):
        """A read-only transaction that sees one state of the whole database throughout
        (REPEATABLE READ on PostgreSQL; on SQLite in WAL mode every read transaction does)."""
        return self._tx(write=False, snapshot=True)

    def transaction(self):
        """A write transaction: all that is written in it is committed together, or nothing."""
        return self._tx(write=True)

    def close(self) -> None:
        self.engine.dispose()

    # ------------------------------------------------------------------ schema
    def _lock_for_migration(self, conn: Connection) -> None:
        if self.dialect == "postgresql":
            conn.exec_driver_sql("SELECT pg_advisory_xact_lock(727256)")  # 'lanemap' schema lock

    def schema_revision(self) -> str | None:
        with self._read() as conn:
            return migrate.current_revision(conn)

    @property
    def display_url(self) -> str:
        """The database's URL without its password, for messages."""
        return self._safe_url()

    def check_schema(self, current: str | None = None) -> None:
        """Raise :class:`SchemaError` unless the database (at schema revision ``current``, read
        when not given) is at this lanemap's schema revision."""
        head = migrate.head_revision(self.url)
        if current is None:
            current = self.schema_revision()
        if current != head:
            raise SchemaError(
                f"database {self._safe_url()} is at schema revision {current or '(empty)'}, this lanemap "
                f"needs {head}: run `lanemap db upgrade`"
            )

    def _ensure_schema(self) -> None:
        try:
            current = self.schema_revision()
        except DBAPIError as exc:
            raise StoreUnavailableError(f"cannot open database {self._safe_url()}: {exc.orig}") from exc
        if current is None:
            self.upgrade()
        else:
            self.check_schema(current)

    def upgrade(self, revision: str = "head") -> tuple[str | None, str | None]:
        """Apply migrations up to ``revision``; returns (before, after)."""
        with self._write() as conn:
            self._lock_for_migration(conn)
            before = migrate.current_revision(conn)
            migrate.upgrade(conn, self.url, revision)
            after = migrate.current_revision(conn)
        log.info("database schema %s -> %s", before, after)
        return before, after

    def _safe_url(self) -> str:
        return make_url(self.url).render_as_string(hide_password=True)

    # ------------------------------------------------------------------ maps
    def create_map(self, map_id: str, title: str = "", crs: str | None = None,
                   coverage: str | None = None) -> MapInfo:  # fmt: skip
        """Create an empty map. ``crs`` must be metric; None: chosen at the first import or build.
        ``coverage``: :data:`MAP_COVERAGES`, or None for the server's setting."""
        check_map_id(map_id)
        check_coverage(coverage)
        if len(title or "") > MAX_TITLE_LENGTH:
            raise StoreError(f"title: at most {MAX_TITLE_LENGTH} characters, got {len(title)}")
        if crs is not None:
            try:
                metric_crs(crs)
            except CRSError as exc:
                raise StoreError(str(exc)) from exc
        now = _now()
        try:
            with self._write() as conn:
                # A map made anew under the id of a deleted one goes on past its last
                # revision, and its change feed answers only from there: a copy or a
                # cache of the old map is never taken for the new one.
                retired = conn.execute(select(retired_maps.c.revision).where(retired_maps.c.id == map_id)).scalar()
                start = 0 if retired is None else int(retired) + 1
                conn.execute(
                    insert(maps).values(
                        id=map_id, title=title or "", crs=crs, revision=start, feed_since=start,
                        coverage=coverage, created_at=now, updated_at=now,
                    )
                )  # fmt: skip
                if retired is not None:
                    conn.execute(delete(retired_maps).where(retired_maps.c.id == map_id))
        except IntegrityError:
            raise MapExistsError(map_id) from None
        return self.get_map(map_id)

    def update_map(self, map_id: str, *, title: str | None = None, coverage: str | None = None,
                   set_coverage: bool = False) -> MapInfo:  # fmt: skip
        """Give a map a new ``title`` (None: keep it) and, with ``set_coverage``, a new ``coverage``
        (:data:`MAP_COVERAGES`; None: as the server is set), in one transaction and both checked
        before either is written. Its id, CRS, markings and revision stay; a localization index
        follows the coverage (:meth:`map_head`)."""
        if title is not None and len(title) > MAX_TITLE_LENGTH:
            raise StoreError(f"title: at most {MAX_TITLE_LENGTH} characters, got {len(title)}")
        if set_coverage:
            check_coverage(coverage)
        values = {"updated_at": _now()}
        if title is not None:
            values["title"] = title
        if set_coverage:
            values["coverage"] = coverage
        with self._write() as conn:
            self._map_row(conn, map_id, lock=True)
            conn.execute(update(maps).where(maps.c.id == map_id).values(**values))
        return self.get_map(map_id)

    def set_title(self, map_id: str, title: str) -> MapInfo:
        """Give a map a new title (its id, which addresses it, stays)."""
        return self.update_map(map_id, title=title)

    def set_coverage(self, map_id: str, coverage: str | None) -> MapInfo:
        """Say how far the map speaks for the ground (:data:`MAP_COVERAGES`; None: as the server
        is set)."""
        return self.update_map(map_id, coverage=coverage, set_coverage=True)

    def adopt_crs(self, map_id: str, crs: str) -> str:
        """Give a map that has no storage CRS yet ``crs`` (metric); the map's CRS.

        A map created without a CRS takes one from the first data written to
        it; a build takes its image's (:func:`mapbuilder.raster.default_storage_crs`).
        A map that already has a CRS keeps it.
        """
        try:
            metric_crs(crs)
        except CRSError as exc:
            raise StoreError(str(exc)) from exc
        with self._write() as conn:
            return self._crs_for_write(conn, map_id, crs=crs)

    def adopt_coverage(self, map_id: str, coverage: str) -> str | None:
        """Give a map that holds nothing yet and has no coverage set ``coverage``; the map's coverage.

        A map made empty and then first built from imagery speaks for the ground
        its imagery shows, as a map a build creates does (``mapbuilder.build``),
        in the way such a map takes its first build's CRS. A map that holds
        markings (of any status) or recorded ground, or whose coverage was set,
        keeps what it has: ``None`` there means as the server is set.
        """
        check_coverage(coverage)
        with self._write() as conn:
            row = self._map_row(conn, map_id, lock=True)
            if row.coverage is not None:
                return row.coverage
            holds = conn.execute(select(markings.c.id).where(markings.c.map_id == map_id).limit(1)).first()
            imaged = conn.execute(select(imaged_ground.c.tile_key).where(imaged_ground.c.map_id == map_id)
                                  .limit(1)).first()  # fmt: skip
            if holds is not None or imaged is not None:
                return None
            conn.execute(update(maps).where(maps.c.id == map_id).values(coverage=coverage, updated_at=_now()))
        log.info("map %s: coverage %s, taken at its first build", map_id, coverage)
        return coverage

    def _map_row(self, conn: Connection, map_id: str, *, lock: bool = False):
        q = select(maps).where(maps.c.id == map_id)
        if lock and self.dialect == "postgresql":
            q = q.with_for_update()
        row = conn.execute(q).first()
        if row is None:
            raise UnknownMapError(map_id)
        return row

    @staticmethod
    def _map_info(row, count: int | None = None) -> MapInfo:
        bounds = None
        if row.minx is not None:
            bounds = (row.minx, row.miny, row.maxx, row.maxy)
        return MapInfo(
            id=row.id, title=row.title, crs=row.crs, bounds=bounds, revision=row.revision,
            created_at=_utc(row.created_at), updated_at=_utc(row.updated_at), count=count,
            feed_since=int(row.feed_since), coverage=row.coverage,
        )  # fmt: skip

    def get_map(self, map_id: str, *, with_count: bool = False) -> MapInfo:
        with self._read() as conn:
            row = self._map_row(conn, map_id)
            count = self._kept_count(conn, map_id) if with_count else None
        return self._map_info(row, count)

    def list_maps(self) -> list[MapInfo]:
        with self._read() as conn:
            rows = conn.execute(select(maps).order_by(maps.c.id)).all()
            mc = marking_counts.c
            counts = {m: n for m, n in conn.execute(select(mc.map_id, func.sum(mc.n)).group_by(mc.map_id))}
            return [self._map_info(r, int(counts.get(r.id, 0))) for r in rows]

    def _kept_count(self, conn: Connection, map_id: str, statuses=None, source: str | None = None) -> int:
        """How many of the map's markings have one of ``statuses`` (None: any) and ``source``
        (None: any), from the counts every write keeps (``marking_counts``): a sum over a few
        rows where a count of the markings read them all (a scan on PostgreSQL)."""
        mc = marking_counts.c
        q = select(func.coalesce(func.sum(mc.n), 0)).where(mc.map_id == map_id)
        if statuses:
            q = q.where(mc.status.in_(list(statuses)))
        if source is not None:
            q = q.where(mc.source == source)
        return int(conn.execute(q).scalar_one())

    def map_extents(self) -> list[tuple[str, str | None, tuple[float, float, float, float] | None]]:
        """Every map's id, storage CRS and bounds in it (None while it has none), by id: one
        read of the maps alone, for picking a map by position."""
        m = maps.c
        with self._read() as conn:
            rows = conn.execute(select(m.id, m.crs, m.minx, m.miny, m.maxx, m.maxy).order_by(m.id)).all()
        return [(r.id, r.crs, None if r.minx is None else (r.minx, r.miny, r.maxx, r.maxy)) for r in rows]

    def delete_map(self, map_id: str) -> None:
        """Delete a map with its markings, edit log, imagery records and jobs."""
        with self._write() as conn:
            row = self._map_row(conn, map_id, lock=True)
            conn.execute(delete(maps).where(maps.c.id == map_id))
            conn.execute(delete(retired_maps).where(retired_maps.c.id == map_id))
            conn.execute(insert(retired_maps).values(id=map_id, revision=int(row.revision), deleted_at=_now()))

    def map_revision(self, map_id: str) -> int:
        """The map's revision (it grows with every change of its markings)."""
        return self.map_head(map_id)[0]

    def map_head(self, map_id: str) -> MapHead:
        """The map's revision, coverage (None: as the server is set), and when it was made and last changed.

        Every localization asks for them (the service rebuilds its cached index
        when either moved on, and tells a map made anew under a deleted one's id
        by ``created``), so it is one statement on a pooled driver connection,
        without SQLAlchemy's transaction round trips: a single SELECT reads one
        committed snapshot by itself. Any driver failure takes the regular path,
        which reports it as every other read does.
        """
        row = None
        try:
            conn = self.engine.raw_connection()
            try:
                cur = conn.cursor()
                cur.execute(self._head_sql, (map_id,))
                row = cur.fetchone()
                cur.close()
            finally:
                conn.close()
        except Exception:  # noqa: BLE001 - the regular path raises the store's own errors
            with self._read() as c:
                r = self._map_row(c, map_id)
                return MapHead(int(r.revision), r.coverage, _stamp(r.created_at), _stamp(r.updated_at))
        if row is None:
            raise UnknownMapError(map_id)
        return MapHead(int(row[0]), row[1], _stamp(row[2]), _stamp(row[3]))

    @property
    def _head_sql(self) -> str:
        mark = "?" if self.dialect == "sqlite" else "%s"
        return f"SELECT revision, coverage, created_at, updated_at FROM maps WHERE id = {mark}"

    def _next_revision(self, conn: Connection, map_id: str) -> int:
        """Move the map on to its next revision and return it: the first write of a
        transaction that changes markings, which stamp it on what they write.

        The map's row stays locked until the transaction ends, so the writers of
        a map take their revisions in the order they commit: once a revision is
        visible, every marking stamped with it or an earlier one is too, and a
        reader of the changes since a revision misses none.
        """
        rev = conn.execute(
            update(maps).where(maps.c.id == map_id).values(revision=maps.c.revision + 1, updated_at=_now())
            .returning(maps.c.revision)
        ).scalar()  # fmt: skip
        if rev is None:
            raise UnknownMapError(map_id)
        return int(rev)

    def _removed(self, conn: Connection, map_id: str, ids: Sequence[int], revision: int) -> None:
        """Record markings ``ids`` as deleted at ``revision`` (for the change feed)."""
        if not ids:
            return
        # A deleted id was live, and a live id has no deletion recorded (re-creating one under its
        # id drops it, _apply_one): these rows are new.
        now = _now()
        _insert_many(conn, removed_markings,
                     [{"map_id": map_id, "marking_id": i, "revision": revision, "removed_at": now} for i in ids])

    def _touch_map(self, conn: Connection, map_id: str, xs=(), ys=()) -> None:
        """Widen the map's bounds to take in ``xs``, ``ys`` (its revision moved on already)."""
        row = self._map_row(conn, map_id)
        values: dict[str, Any] = {"updated_at": _now()}
        if len(xs):
            b = _bounds_of(xs, ys)
            if row.minx is not None:
                b = (min(b[0], row.minx), min(b[1], row.miny), max(b[2], row.maxx), max(b[3], row.maxy))
            values.update(minx=b[0], miny=b[1], maxx=b[2], maxy=b[3])
        conn.execute(update(maps).where(maps.c.id == map_id).values(**values))

    def _crs_for_write(self, conn: Connection, map_id: str, lonlat_hint=None, crs: str | None = None) -> str:
        """The map's CRS; a map without one takes ``crs``, else the UTM zone of ``lonlat_hint``."""
        row = self._map_row(conn, map_id, lock=True)
        if row.crs:
            return row.crs
        if crs is None:
            if lonlat_hint is None:
                raise StoreError(
                    f"map {map_id!r} has no CRS yet: create it with a CRS or import lon/lat data first"
                )
            crs = utm_crs_for(*lonlat_hint)
        conn.execute(update(maps).where(maps.c.id == map_id).values(crs=crs, updated_at=_now()))
        log.info("map %s: storage CRS set to %s", map_id, crs)
        return crs

    # ------------------------------------------------------------------ markings
    def add_markings(
        self,
        map_id: str,
        items: Iterable[Marking],
        who: str = "cli",
        comment: str = "",
        *,
        lonlat: bool = False,
        progress: Callable[[int, int], None] | None = None,
        job_id: int | None = None,
    ) -> list[int]:
        """Insert markings in one transaction and log it as one ``import`` changeset.

        Parameters
        ----------
        lonlat : bool
            The markings' ``lon``/``lat`` hold their position (WGS84); ``x``/``y``
            are computed in the map's CRS, which is chosen from the data when the
            map has none yet.
        progress : callable, optional
            Called with the markings inserted so far and their total after
            each batch (up to :data:`INSERT_BATCH`).
        job_id : int, optional
            The import job this is: it is recorded ``successful``, with what was imported
            (``params["result"]``), in the same transaction, so a job still active after a
            crash imported nothing and can run again.

        Each batch is checked, turned into rows and written before the next: a city's
        import holds its markings, not their rows too (built whole, the rows of 1,000,000
        markings took an import's peak from 0.8 to 2.0 GB).
        A marking found invalid rolls back the whole transaction.
        """
        items = list(items)
        if not items:
            return []
        now = _now()
        with self._write() as conn:
            hint = None
            if lonlat:
                hint = (
                    float(np.mean([m.lon for m in items])),
                    float(np.mean([m.lat for m in items])),
                )
            crs = self._crs_for_write(conn, map_id, hint)
            rev = self._next_revision(conn, map_id)
            if lonlat:
                xs, ys = from_wgs84(crs).transform(
                    np.array([m.lon for m in items], float), np.array([m.lat for m in items], float)
                )
                for m, x, y in zip(items, np.atleast_1d(xs), np.atleast_1d(ys)):
                    m.x, m.y = float(x), float(y)
            insert_batch = self._batch_inserter(conn, len(items))
            ids: list[int] = []

            def write(rows):
                ids.extend(insert_batch(rows))
                if progress is not None:
                    progress(len(ids), len(items))

            self._write_new(conn, map_id, items, crs, rev, now, write, INSERT_BATCH)
            cs = conn.execute(
                insert(changesets).values(
                    map_id=map_id, who=who, at=now, comment=comment, n_create=len(ids),
                    n_update=0, n_delete=0,
                )
            ).inserted_primary_key[0]  # fmt: skip
            conn.execute(
                insert(edits).values(
                    map_id=map_id, changeset_id=cs, marking_id=None, op="import", who=who, at=now,
                    before=None, after={"count": len(ids), "first_id": min(ids), "last_id": max(ids)},
                    comment=comment,
                )
            )  # fmt: skip
            if job_id is not None:
                self._finish_import_job(conn, job_id, {"imported": len(ids), "first_id": min(ids),
                                                       "last_id": max(ids), "changeset": int(cs)})  # fmt: skip
        self._analyze_after(len(ids))
        return ids

    @staticmethod
    def _finish_import_job(conn: Connection, job_id: int, result: dict[str, Any]) -> None:
        row = conn.execute(select(jobs.c.status, jobs.c.params).where(jobs.c.id == job_id)).first()
        if row is None:
            raise UnknownJobError(job_id)
        if row.status not in ("accepted", "running"):
            raise StoreError(f"job {job_id} is {row.status}; the import is not written")
        now = _now()
        conn.execute(update(jobs).where(jobs.c.id == job_id).values(
            status="successful", progress=100.0, params={**dict(row.params or {}), "result": result},
            updated_at=now, finished_at=now))  # fmt: skip

    def _write_new(self, conn: Connection, map_id: str, items: Iterable[Marking], crs: str, rev: int,
                   now: datetime, write: Callable[[list[dict[str, Any]]], Any], batch: int) -> int:  # fmt: skip
        """Check new markings and turn them into rows of revision ``rev``, ``batch`` at a time,
        each batch handed to ``write`` before the next is built (a city's rows are never held
        at once); then count them into ``marking_counts`` and widen the map's bounds. How many
        were written; an invalid marking raises :class:`InvalidMarkingError` naming its index."""
        counts: Counter = Counter()

        def batches() -> Iterator[list[dict[str, Any]]]:
            rows = []
            for i, m in enumerate(items):
                try:
                    row = marking_row(m, crs, now)
                except InvalidMarkingError as exc:
                    raise InvalidMarkingError(f"marking {i}: {exc}") from None
                row["map_id"], row["version"], row["revision"] = map_id, 1, rev
                counts[_dict_key(row)] += 1
                rows.append(row)
                if len(rows) >= batch:
                    yield rows
                    rows = []
            if rows:
                yield rows

        lo, hi = [math.inf, math.inf], [-math.inf, -math.inf]
        n = 0
        for rows in batches():
            x, y = [r["x"] for r in rows], [r["y"] for r in rows]
            lo = [min(lo[0], *x), min(lo[1], *y)]
            hi = [max(hi[0], *x), max(hi[1], *y)]
            write(rows)
            n += len(rows)
        if n:
            _tally(conn, map_id, counts)
            self._touch_map(conn, map_id, [lo[0], hi[0]], [lo[1], hi[1]])
        return n

    def _analyze_after(self, n: int) -> None:
        """After ``n`` markings were loaded at once, have PostgreSQL count the table again
        (``ANALYZE``, a sample: a fraction of a second) rather than wait for autovacuum, or for
        ever where it is off. On a count from before, a map's id looks rare enough for the
        planner to read a box through ``ix_markings_map`` and test the whole map: 190 ms
        instead of 16 ms for a box of 1,000 among 1,000,000 just loaded. SQLite plans by
        the shape of a query, and is not counted (:data:`_BOXED_ID`)."""
        if self.dialect != "postgresql" or n < ANALYZE_FROM:
            return
        try:
            with self.engine.connect() as conn:
                conn.exec_driver_sql("ANALYZE markings")
                conn.commit()
        except DBAPIError as exc:
            log.warning("ANALYZE markings after loading %d markings failed: %s", n, exc)

    @staticmethod
    def _batch_inserter(conn: Connection, n: int) -> Callable[[list[dict[str, Any]]], list[int]]:
        """A function inserting a batch of marking rows and answering their ids in order, for ``n`` rows in all."""
        dialect = conn.dialect
        if dialect.name == "postgresql" and dialect.driver == "psycopg":
            # A batched RETURNING statement (1,000 rows, 24,000 placeholders) is
            # parsed anew by psycopg at every execution: 0.4 ms a marking. The
            # column's sequence hands out every id in one statement instead,
            # and the rows go by COPY with them.
            seq = conn.execute(text("SELECT pg_get_serial_sequence('markings', 'id')")).scalar_one()
            reserved = iter(sorted(conn.execute(text("SELECT nextval(:seq) FROM generate_series(1, :n)"),
                                                {"seq": seq, "n": n}).scalars()))  # fmt: skip

            def copy_with_ids(batch):
                with_ids = [{"id": next(reserved), **r} for r in batch]
                _insert_many(conn, markings, with_ids)
                return [r["id"] for r in with_ids]

            return copy_with_ids
        if dialect.name == "sqlite":
            # SQLite promises no order for RETURNING, so SQLAlchemy would insert
            # the rows one statement each (three times slower). It has one writer
            # at a time and new rowids only grow: the ids above the largest one
            # before a batch are the batch's, in its order.
            floor = [conn.execute(select(func.coalesce(func.max(markings.c.id), 0))).scalar_one()]

            def bulk_then_read_ids(batch):
                _insert_many(conn, markings, batch)
                new = conn.execute(
                    select(markings.c.id).where(markings.c.id > floor[0]).order_by(markings.c.id)
                ).scalars().all()  # fmt: skip
                if len(new) != len(batch):  # another writer in this transaction: cannot happen
                    raise RuntimeError(f"inserted {len(batch)} markings but found {len(new)} new ids")
                floor[0] = new[-1]
                return new

            return bulk_then_read_ids

        def returning(batch):
            result = conn.execute(insert(markings).returning(markings.c.id, sort_by_parameter_order=True), batch)
            return [r[0] for r in result]

        return returning

    def bulk_load(self, map_id: str, items: Iterable[Marking], chunk: int = 20000) -> int:
        """Insert many markings fast (benchmarks, large imports): no edit log, one transaction."""
        now = _now()
        with self._write() as conn:
            crs = self._crs_for_write(conn, map_id)
            rev = self._next_revision(conn, map_id)
            n = self._write_new(conn, map_id, items, crs, rev, now,
                                lambda rows: _insert_many(conn, markings, rows), chunk)  # fmt: skip
        self._analyze_after(n)
        return n

    def _bbox_clause(self, map_id: str, minx: float, miny: float, maxx: float, maxy: float):
        for name, v in (("minx", minx), ("miny", miny), ("maxx", maxx), ("maxy", maxy)):
            if not math.isfinite(v):
                raise StoreError(f"bbox {name} must be finite")
        if minx > maxx or miny > maxy:
            raise StoreError("bbox must be (minx, miny, maxx, maxy) with min <= max")
        # Clamp to the 32-bit range of the grid columns: a huge box must not overflow them.
        lim = 2**31 - 1
        gx0, gx1 = (max(-lim, min(lim, math.floor(v / GRID_CELL_M))) for v in (minx, maxx))
        gy0, gy1 = (max(-lim, min(lim, math.floor(v / GRID_CELL_M))) for v in (miny, maxy))
        c = markings.c
        # Listing the grid columns turns one long range scan into one short
        # index seek per column (gx = ? AND gy BETWEEN ...): 8x faster at 1M rows.
        gx = c.gx.in_(range(gx0, gx1 + 1)) if gx1 - gx0 < 256 else c.gx.between(gx0, gx1)
        return and_(
            c.map_id == map_id,
            gx,
            c.gy.between(gy0, gy1),
            c.x.between(minx, maxx),
            c.y.between(miny, maxy),
        )

    def query_bbox(
        self,
        map_id: str,
        minx: float,
        miny: float,
        maxx: float,
        maxy: float,
        statuses: Sequence[str] | None = None,
        limit: int | None = None,
        offset: int = 0,
    ) -> list[Marking]:
        """Markings whose centroid lies in a box of the storage CRS, ordered by id."""
        where = self._bbox_clause(map_id, minx, miny, maxx, maxy)
        if statuses:
            where = and_(where, markings.c.status.in_(list(statuses)))
        q = select(*_READ_COLUMNS).where(where).order_by(_BOXED_ID).offset(offset)
        if limit is not None:
            q = q.limit(limit)
        with self._read() as conn:
            self._map_row(conn, map_id)
            return _markings_from_rows(conn.execute(q))

    def count_bbox(self, map_id, minx, miny, maxx, maxy, statuses=None) -> int:
        where = self._bbox_clause(map_id, minx, miny, maxx, maxy)
        if statuses:
            where = and_(where, markings.c.status.in_(list(statuses)))
        with self._read() as conn:
            return conn.execute(select(func.count()).select_from(markings).where(where)).scalar_one()

    def _lonlat_clause(self, info: MapInfo, mb, lonlat_box: tuple[float, float, float, float], wide: bool = False):
        """Markings of ``info``'s map, whose lon/lat bounds are ``mb``, whose centroid lies in a
        lon/lat box (degrees), or None when none can (the box misses the map, or the map has no
        CRS yet).

        The box becomes a larger one in the storage CRS (its edges are curves there); the grid
        keys narrow the search to that, and the stored ``lon``/``lat`` keep exactly the
        markings inside the requested box, so that counts and pages agree with what is read.
        A ``wide`` box is tested on the stored ``lon``/``lat`` alone, with no grid keys for the
        database to read it by (:data:`WIDE_BOX_SHARE`).
        """
        if mb is None or info.crs is None:
            return None
        w, s, e, n = (max(lonlat_box[0], mb[0]), max(lonlat_box[1], mb[1]),
                      min(lonlat_box[2], mb[2]), min(lonlat_box[3], mb[3]))  # fmt: skip
        if w > e or s > n:
            return None
        if wide:
            c = markings.c
            return and_(c.map_id == info.id, c.lon.between(w, e), c.lat.between(s, n))
        minx, miny, maxx, maxy = from_wgs84(info.crs).transform_bounds(w, s, e, n, densify_pts=21)
        if not all(math.isfinite(v) for v in (minx, miny, maxx, maxy)):
            return None
        # The box in the storage CRS only narrows the search, and the way there and back rounds:
        # a box reaching just to the map's last marking could end a nanometre short of it.
        pad, c = BOX_PAD_M, markings.c
        return and_(self._bbox_clause(info.id, minx - pad, miny - pad, maxx + pad, maxy + pad),
                    c.lon.between(w, e), c.lat.between(s, n))  # fmt: skip

    @staticmethod
    def _box_within(mb, lonlat_box):
        """``lonlat_box`` (minLon, minLat, maxLon, maxLat; degrees), or None where it holds the
        whole map (lon/lat bounds ``mb``) with :data:`COVER_MARGIN_DEG` to spare: then the map
        is read whole (in its ids' index order, its counts kept) rather than grid cell by grid cell, as a
        client zoomed out past the map asks (on 1,000,000 markings, SQLite counted such a box
        in 4.9 s where the kept counts answer in 2 ms)."""
        m = COVER_MARGIN_DEG
        if mb is not None and lonlat_box is not None:
            w, s, e, n = lonlat_box
            if w <= mb[0] - m and s <= mb[1] - m and e >= mb[2] + m and n >= mb[3] + m:
                return None
        return lonlat_box

    @staticmethod
    def _box_share(mb, lonlat_box) -> float:
        """How much of a map's lon/lat bounds ``mb`` the box ``lonlat_box`` covers, 0 to 1."""
        if mb is None:
            return 0.0
        w, s = max(lonlat_box[0], mb[0]), max(lonlat_box[1], mb[1])
        e, n = min(lonlat_box[2], mb[2]), min(lonlat_box[3], mb[3])
        if w > e or s > n:
            return 0.0
        dx, dy = mb[2] - mb[0], mb[3] - mb[1]
        # A map on a line (or a point) has no area: its share is what the box holds of its length.
        return (((e - w) / dx) if dx > 0 else 1.0) * (((n - s) / dy) if dy > 0 else 1.0)

    def _selection(self, conn: Connection, map_id: str, statuses, lonlat_box) -> _Selection:
        """What a read of a map's markings with these statuses inside ``lonlat_box`` (either
        None: all) reads, as a :class:`_Selection`.

        A box is read through the grid index and its markings sorted by id, unless it covers
        :data:`WIDE_BOX_SHARE` of the map or more: then the map's markings are walked in id
        order (``ix_markings_map``), each tested against the box, and a page stops when it is
        full. At 1,000,000 markings on SQLite the grid's way took 4.8 s for the first page of
        a box over 95 % of the map and 11.6 s half-way through it, the walk 0.2 and 0.3 s. The
        walk costs at most a pass over the map (about 0.2 s per million markings), the grid's
        way a read and sort of the whole box for every page."""
        info = self._map_info(self._map_row(conn, map_id))
        mb = None if lonlat_box is None else info.bounds_wgs84()  # once a read: 21 points a side through PROJ
        box = self._box_within(mb, lonlat_box)
        where, key = markings.c.map_id == map_id, markings.c.id
        if box is not None:
            wide = self._box_share(mb, box) >= WIDE_BOX_SHARE
            where = self._lonlat_clause(info, mb, box, wide=wide)
            if where is None:
                return _Selection(None, box, key, _state_of(info), ())
            if not wide:
                key = _BOXED_ID
        if statuses:
            where = and_(where, markings.c.status.in_(list(statuses)))
        return _Selection(where, box, key, _state_of(info), tuple(sorted(statuses or ())), box is not None and wide)

    def _box_count(self, conn: Connection, map_id: str, sel: _Selection, where, what: str = "markings") -> int:
        """How many markings ``where`` (``sel.where`` or narrower, as ``what`` names) selects
        in ``sel.box``, counted once per revision of the map: a client paging through a box
        (the editor loads a view 5,000 at a time) asks with every page, and a box over 3 %
        of 1,000,000 markings took 0.15 s to count. Every write of markings moves the map's
        revision on (:func:`_state_of`), so a count is kept only for as long as it is right."""
        key = (map_id, sel.state, sel.box, sel.statuses, what)
        with self._counts_lock:
            n = self._counts.get(key)
            if n is not None:
                self._counts.move_to_end(key)
                return n
        n = int(conn.execute(select(func.count()).select_from(markings).where(where)).scalar_one())
        with self._counts_lock:
            self._counts[key] = n
            while len(self._counts) > BOX_COUNTS_KEPT:
                self._counts.popitem(last=False)
        return n

    def query_lonlat_box(
        self,
        map_id: str,
        lonlat_box: tuple[float, float, float, float],
        statuses: Sequence[str] | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> tuple[list[Marking], int]:
        """A page of the markings whose centroid lies in ``lonlat_box`` (minLon, minLat, maxLon,
        maxLat; degrees), by id, and how many there are in all."""
        with self._read() as conn:
            sel = self._selection(conn, map_id, statuses, lonlat_box)
            if sel.box is None:
                return self._page(conn, map_id, limit, offset, statuses)
            if sel.where is None:
                return [], 0
            total = self._box_count(conn, map_id, sel, sel.where)
            rows = conn.execute(
                select(*_READ_COLUMNS).where(sel.where).order_by(sel.key).limit(limit).offset(offset)
            ).all()
        return _markings_from_rows(rows), total

    def count_markings(
        self, map_id: str, statuses: Sequence[str] | None = None,
        lonlat_box: tuple[float, float, float, float] | None = None,
    ) -> int:  # fmt: skip
        """How many of a map's markings :meth:`iter_markings` would give for the same filters."""
        with self._read() as conn:
            sel = self._selection(conn, map_id, statuses, lonlat_box)
            if sel.where is None:
                return 0
            if sel.box is None:
                return self._kept_count(conn, map_id, statuses)
            return self._box_count(conn, map_id, sel, sel.where)

    def summary(self, map_id: str, lonlat_box: tuple[float, float, float, float] | None = None) -> MapSummary:
        """Count a map's markings by status, source and kind, and its unreviewed detections
        by score, in one snapshot; only those inside ``lonlat_box`` (minLon, minLat, maxLon,
        maxLat; degrees) when given, such as a district a team reviews.

        The whole map's counts are read from ``marking_counts``, which every write keeps
        (milliseconds; every open editor asks whenever the map moves on). A box's are counted
        from its markings (about a second per million).
        """
        c, mc = markings.c, marking_counts.c
        hist = [0] * SCORE_BINS
        with self.snapshot() as conn:
            row = self._map_row(conn, map_id)
            sel = self._selection(conn, map_id, None, lonlat_box)
            where, box = sel.where, sel.box
            if box is None:
                kept = conn.execute(select(mc.status, mc.source, mc.kind, mc.score_bin, mc.n)
                                    .where(mc.map_id == map_id, mc.n != 0)).all()  # fmt: skip
                groups = [(st, src, kind or None, n) for st, src, kind, _, n in kept]
                for st, src, _, b, n in kept:
                    if src == "detected" and st == "unreviewed" and b >= 0:
                        hist[b] += n
            elif where is None:  # the box misses the map
                groups = []
            else:
                edges = _BIN_EDGES + [math.inf]
                per_bin = [func.coalesce(func.sum(case((and_(c.score >= lo, c.score < hi), 1), else_=0)), 0)
                           for lo, hi in zip(edges[:-1], edges[1:])]  # fmt: skip
                groups = conn.execute(
                    select(c.status, c.source, c.kind, func.count()).where(where).group_by(c.status, c.source, c.kind)
                ).all()  # fmt: skip
                hist = [int(n) for n in conn.execute(
                    select(*per_bin).where(where, c.source == "detected", c.status == "unreviewed")
                ).one()]  # fmt: skip
        by_status: dict[str, int] = {}
        by_source: dict[str, int] = {}
        by_kind: dict[str, int] = {}
        detections = dict.fromkeys(STATUSES, 0)
        for status, source, kind, n in groups:
            by_status[status] = by_status.get(status, 0) + n
            by_source[source] = by_source.get(source, 0) + n
            by_kind[kind or "unknown"] = by_kind.get(kind or "unknown", 0) + n
            if source == "detected":
                detections[status] += n
        return MapSummary(
            revision=int(row.revision), count=sum(by_status.values()),
            by_status=dict(sorted(by_status.items())), by_source=dict(sorted(by_source.items())),
            by_kind=dict(sorted(by_kind.items())), detections=detections, unreviewed_scores=hist,
        )

    def changes(
        self, map_id: str, since: int, *, statuses: Sequence[str] | None = None,
        after: tuple[int, int] | None = None, limit: int = 1000,
    ) -> Changes:  # fmt: skip
        """What changed in a map after revision ``since``: the markings written and the
        markings deleted, in the order of the revisions that did it, a page of up to
        ``limit`` changes from ``after`` (a page's :attr:`Changes.after`) on.

        With ``statuses``, a copy holds only markings of those statuses: a marking
        written since whose status is another one is listed as removed.

        Raises
        ------
        StaleRevisionError
            If ``since`` is beyond the map's revision, or before the deletions the map
            keeps (:meth:`prune_removed`); ``since=0`` (a copy from nothing) always works.
        """
        if since < 0:
            raise StoreError(f"since must be >= 0, got {since}")
        c, rm = markings.c, removed_markings.c
        r0, i0 = after if after is not None else (since, -1)
        with self._read() as conn:
            row = self._map_row(conn, map_id)
            upto = int(row.revision)
            if since > upto:
                raise StaleRevisionError(
                    f"map {map_id!r} is at revision {upto}, not yet at {since}: that copy is of "
                    "another map of this id (the database was restored from an older backup); read it whole")  # fmt: skip
            if 0 < since < row.feed_since:
                raise StaleRevisionError(
                    f"map {map_id!r} answers changes from revision {row.feed_since} on (it was made "
                    f"anew, or its older deletions were pruned), and this copy is at {since}: read it whole")  # fmt: skip
            window = [c.map_id == map_id, c.revision > since, c.revision <= upto,
                      or_(c.revision > r0, and_(c.revision == r0, c.id > i0))]  # fmt: skip
            rows = conn.execute(
                select(c.revision, *_READ_COLUMNS).where(*window).order_by(c.revision, c.id).limit(limit + 1)
            ).all()
            gone = conn.execute(
                select(rm.revision, rm.marking_id)
                .where(rm.map_id == map_id, rm.revision > since, rm.revision <= upto,
                       or_(rm.revision > r0, and_(rm.revision == r0, rm.marking_id > i0)))
                .order_by(rm.revision, rm.marking_id).limit(limit + 1)
            ).all()  # fmt: skip
        written = [(int(r[0]), m) for r, m in zip(rows, _markings_from_rows([r[1:] for r in rows]))]
        records = sorted([(rev, m.id, m) for rev, m in written] + [(int(rev), int(i), None) for rev, i in gone],
                         key=lambda t: (t[0], t[1]))  # fmt: skip
        more = len(records) > limit
        records = records[:limit]
        keep = set(statuses) if statuses else None
        changed, removed = [], []
        for rev, i, m in records:
            if m is not None and (keep is None or m.status in keep):
                changed.append((rev, m))
            else:
                removed.append((rev, i))
        last = (records[-1][0], records[-1][1]) if records else None
        return Changes(revision=upto, changed=changed, removed=removed, more=more, after=last, crs=row.crs)

    def count_changes(self, map_id: str, since: int) -> int:
        """How many markings :meth:`changes` lists after revision ``since``, written or
        removed (each once), without reading them: two counts over the feed's indexes.

        Raises
        ------
        UnknownMapError
            If the map does not exist.
        """
        c, rm = markings.c, removed_markings.c
        with self._read() as conn:
            self._map_row(conn, map_id)
            written = conn.execute(select(func.count()).select_from(markings)
                                   .where(c.map_id == map_id, c.revision > since)).scalar_one()
            gone = conn.execute(select(func.count()).select_from(removed_markings)
                                .where(rm.map_id == map_id, rm.revision > since)).scalar_one()
        return int(written) + int(gone)

    def prune_removed(self, map_id: str, older_than: datetime) -> tuple[int, int]:
        """Forget the deletions recorded before ``older_than`` (an aware datetime).

        The change feed then answers from the newest revision among them on: a
        copy older than that is told to read the map whole. Returns the number of
        deletions forgotten and the revision the feed now answers from.
        """
        rm = removed_markings.c
        with self._write() as conn:
            row = self._map_row(conn, map_id, lock=True)
            old = [rm.map_id == map_id, rm.removed_at < older_than]
            newest = conn.execute(select(func.max(rm.revision)).where(*old)).scalar()
            if newest is None:
                return 0, int(row.feed_since)
            # Every deletion up to that revision goes, whatever its clock said: a copy at the
            # horizon or later needs none of them, and one before it reads the map whole.
            n = conn.execute(delete(removed_markings).where(rm.map_id == map_id, rm.revision <= newest)).rowcount
            horizon = max(int(row.feed_since), int(newest))
            conn.execute(update(maps).where(maps.c.id == map_id).values(feed_since=horizon))
        log.info("map %s: %d deletions before %s forgotten; the change feed answers from revision %d",
                 map_id, n, older_than.isoformat(), horizon)
        return int(n), horizon

    def prune_all_removed(self, older_than: datetime) -> dict[str, tuple[int, int]]:
        """:meth:`prune_removed` for every map that recorded deletions before ``older_than``.

        Each map is pruned in a transaction of its own; a map deleted meanwhile is
        skipped. Returns ``{map id: (deletions forgotten, revision the feed answers from)}``
        for the maps pruned.
        """
        rm = removed_markings.c
        with self._read() as conn:
            ids = conn.execute(
                select(rm.map_id).where(rm.removed_at < older_than).distinct().order_by(rm.map_id)
            ).scalars().all()  # fmt: skip
        out = {}
        for map_id in ids:
            try:
                out[map_id] = self.prune_removed(map_id, older_than)
            except UnknownMapError:
                continue
        return out

    def iter_markings(
        self, map_id: str, batch: int = 5000, *, statuses: Sequence[str] | None = None,
        lonlat_box: tuple[float, float, float, float] | None = None,
    ) -> Iterator[Marking]:  # fmt: skip
        """A map's markings by id, in batches (keyset pagination): all of them, or those with
        one of ``statuses`` and a centroid inside ``lonlat_box`` (minLon, minLat, maxLon,
        maxLat; degrees)."""
        last = -1
        while True:
            with self._read() as conn:
                sel = self._selection(conn, map_id, statuses, lonlat_box)
                if sel.where is None:
                    return
                rows = conn.execute(
                    select(*_READ_COLUMNS).where(sel.where, sel.key > last).order_by(sel.key).limit(batch)
                ).all()
            if not rows:
                return
            yield from _markings_from_rows(rows)
            last = rows[-1].id

    def list_markings(
        self, map_id: str, limit: int = 100, offset: int = 0, statuses=None
    ) -> tuple[list[Marking], int]:
        """A page of a map's markings by id, and the total count (from the counts every write
        keeps, :meth:`_kept_count`)."""
        with self._read() as conn:
            return self._page(conn, map_id, limit, offset, statuses)

    def _page(self, conn: Connection, map_id: str, limit: int, offset: int, statuses) -> tuple[list[Marking], int]:
        where = markings.c.map_id == map_id
        if statuses:
            where = and_(where, markings.c.status.in_(list(statuses)))
        self._map_row(conn, map_id)
        total = self._kept_count(conn, map_id, statuses)
        rows = conn.execute(
            select(*_READ_COLUMNS).where(where).order_by(markings.c.id).limit(limit).offset(offset)
        ).all()
        return _markings_from_rows(rows), total

    def review_queue(
        self, map_id: str, *, after: tuple[float | None, int] | None = None, limit: int = 500,
        lonlat_box: tuple[float, float, float, float] | None = None,
    ) -> tuple[list[Marking], int]:  # fmt: skip
        """The next ``limit`` unreviewed detections of a map (those inside ``lonlat_box`` only,
        when given) in the order a person reviews them: lowest score first, those without a
        score last, then by id; and how many there are in all.

        ``after`` is the (score, id) of the last detection of the page before (keyset
        pagination): a detection decided meanwhile leaves the queue without moving the rest,
        which an offset would.
        """
        c = markings.c
        with self._read() as conn:
            sel = self._selection(conn, map_id, ["unreviewed"], lonlat_box)
            if sel.where is None:
                return [], 0
            if sel.box is None:
                total = self._kept_count(conn, map_id, ["unreviewed"], "detected")
                return self._queue_page(conn, map_id, after, limit), int(total)
            where = and_(sel.where, c.source == "detected")
            total = self._box_count(conn, map_id, sel, where, "detected")
            if sel.wide:
                return self._queue_page(conn, map_id, after, limit, sel.where), total
            if after is not None:
                score, last = after
                if score is None:
                    where = and_(where, c.score.is_(None), c.id > last)
                else:
                    where = and_(where, or_(c.score > score, and_(c.score == score, c.id > last), c.score.is_(None)))
            rows = conn.execute(
                select(*_READ_COLUMNS).where(where).order_by(c.score.is_(None), c.score, c.id).limit(limit)
            ).all()  # fmt: skip
        return _markings_from_rows(rows), int(total)

    @staticmethod
    def _queue_page(conn: Connection, map_id: str, after: tuple[float | None, int] | None,
                    limit: int, within=None) -> list[Marking]:  # fmt: skip
        """A page of a map's review queue read in the order of ``ix_markings_queue``: the
        scored detections after ``after`` by (score, id), then those without a score by id. Its
        predicate is written out as the index's (:data:`QUEUED`), which lets SQLite read it; a
        page of 500 among 1,000,000 took 15 ms instead of 0.3 s sorted.

        ``within`` narrows it to a wide box (:meth:`_selection`): the queue is walked in its
        order and each detection tested, as a wide box's markings are along their ids, and a
        page stops once it is full."""
        c = markings.c
        queued = and_(c.map_id == map_id, text(QUEUED))
        if within is not None:
            queued = and_(queued, within)
        rows: list = []
        if after is None or after[0] is not None:
            scored = and_(queued, c.score.is_not(None))
            if after is not None:
                scored = and_(scored, tuple_(c.score, c.id) > tuple_(literal(float(after[0])), literal(int(after[1]))))
            rows = conn.execute(select(*_READ_COLUMNS).where(scored).order_by(c.score, c.id).limit(limit)).all()
        if len(rows) < limit:
            unscored = and_(queued, c.score.is_(None))
            if after is not None and after[0] is None:
                unscored = and_(unscored, c.id > after[1])
            rows += conn.execute(
                select(*_READ_COLUMNS).where(unscored).order_by(c.id).limit(limit - len(rows))
            ).all()  # fmt: skip
        return _markings_from_rows(rows)

    def get_marking(self, map_id: str, marking_id: int) -> Marking:
        with self._read() as conn:
            self._map_row(conn, map_id)
            row = conn.execute(
                select(markings).where(markings.c.map_id == map_id, markings.c.id == marking_id)
            ).first()
        if row is None:
            raise UnknownMarkingError(map_id, marking_id)
        return _marking_from_row(row)

    def marking_arrays(
        self, map_id: str, statuses: Sequence[str] = ("unreviewed", "accepted")
    ) -> MarkingArrays:
        c = markings.c
        statuses = list(statuses)
        q = select(c.id, c.x, c.y, c.weight, c.length_m, c.bearing_deg, c.kind, c.source).where(
            c.map_id == map_id, c.status.in_(statuses)
        )
        sql = ("SELECT id, x, y, weight, length_m, bearing_deg, kind, source FROM markings "
               f"WHERE map_id = ? AND status IN ({', '.join('?' * len(statuses))}) ORDER BY id")
        # In parts: a city's markings read and converted at once held the GIL for
        # a tenth of a second at a time, and a server's localizations with it.
        parts, kinds, sources = [], [], []
        with self._read() as conn:
            self._map_row(conn, map_id)
            read = _driver_parts(conn, sql, (map_id, *statuses), _ARRAYS_PART) if statuses else None
            if read is None:
                read = conn.execute(q.order_by(c.id).execution_options(yield_per=_ARRAYS_PART)).partitions()
            for rows in read:
                parts.append(np.array([r[:6] for r in rows], dtype=float).reshape(-1, 6))
                kinds.extend(r[6] for r in rows)
                sources.extend(r[7] for r in rows)
        a = np.concatenate(parts) if parts else np.zeros((0, 6))
        kind = np.empty(len(a), object)
        kind[:] = kinds
        source = np.empty(len(a), object)
        source[:] = sources
        return MarkingArrays(
            id=a[:, 0].astype(np.int64), x=a[:, 1], y=a[:, 2], weight=a[:, 3],
            length_m=a[:, 4], bearing_deg=a[:, 5], kind=kind, source=source,
        )  # fmt: skip

    # ------------------------------------------------------------------ edits
    def apply_changeset(
        self, map_id: str, changes: Sequence[Change], who: str, comment: str = "",
        *, reverts: int | None = None,
    ) -> ChangesetResult:  # fmt: skip
        """Apply creates, updates and deletes atomically: all of them or none.

        Raises
        ------
        ConflictError
            If a marking to update or delete is missing or its version differs
            from the expected one; nothing is written.
        InvalidMarkingError
            If a created or updated marking has values out of range.
        """
        if not changes:
            raise StoreError("a changeset needs at least one change")
        now = _now()
        with self._write() as conn:
            crs = self._crs_for_write(conn, map_id, _lonlat_hint(changes))
            ids = [c.id for c in changes if c.op in ("update", "delete")]
            seen: set[int] = set()
            for i in ids:
                if i in seen:
                    raise StoreError(f"marking {i} appears more than once in the changeset")
                seen.add(i)
            current = self._current(conn, map_id, ids, select(markings))
            conflicts = []
            for c in changes:
                if c.op not in ("create", "update", "delete"):
                    raise StoreError(f"unknown change op {c.op!r}")
                if c.op == "create":
                    continue
                row = current.get(c.id)
                if row is None:
                    conflicts.append(Conflict(id=c.id, reason="missing", expected_version=c.version))
                elif c.version is not None and c.version != row.version:
                    conflicts.append(
                        Conflict(c.id, "version", expected_version=c.version, actual_version=row.version)
                    )
            if conflicts:
                raise ConflictError(conflicts)

            rev = self._next_revision(conn, map_id)
            cs_id = conn.execute(
                insert(changesets).values(
                    map_id=map_id, who=who, at=now, comment=comment or "",
                    n_create=sum(c.op == "create" for c in changes),
                    n_update=sum(c.op == "update" for c in changes),
                    n_delete=sum(c.op == "delete" for c in changes),
                    reverts=reverts,
                )
            ).inserted_primary_key[0]  # fmt: skip
            results, xs, ys, log_rows, written, updates, counts = [], [], [], [], {}, [], Counter()
            for i, c in enumerate(changes):
                try:
                    res, before, after = self._apply_one(conn, map_id, crs, c, current, now, rev, updates)
                except InvalidMarkingError as exc:
                    raise InvalidMarkingError(f"change {i} ({c.op}): {exc}") from None
                results.append(res)
                if before is not None:
                    counts[_dict_key(before)] -= 1
                if after is not None:
                    counts[_dict_key(after)] += 1
                    written[res["id"]] = _marking_from_json(after)
                    written[res["id"]].id, written[res["id"]].version = res["id"], res["version"]
                    xs.append(after["x"])
                    ys.append(after["y"])
                log_rows.append(
                    dict(
                        map_id=map_id, changeset_id=cs_id, marking_id=res["id"], op=c.op, who=who,
                        at=now, before=before, after=after, comment=comment or "",
                    )
                )  # fmt: skip
            _update_many(conn, updates)
            _insert_many(conn, edits, log_rows)
            _tally(conn, map_id, counts)
            self._touch_map(conn, map_id, xs, ys)
        return ChangesetResult(changeset_id=cs_id, results=results, markings=written)

    def _current(self, conn: Connection, map_id: str, ids: Sequence[int], query) -> dict[int, Any]:
        """The rows ``query`` (a select of ``markings`` columns, ``id`` and ``map_id`` among them)
        reads of the map's markings ``ids``, by id, locked for this transaction.

        Read by id alone, ``ID_CHUNK`` at a time: with the map's id beside the list, SQLite
        (no statistics) reads the whole map through its index once per statement, from five
        ids on: 30 s of a profiled revert's 92 s at 1,000,000 markings, 127 ms of a changeset
        of 20 updates. Other maps' rows are dropped here.
        """
        out = {}
        for at in range(0, len(ids), ID_CHUNK):
            q = query.where(markings.c.id.in_(ids[at:at + ID_CHUNK]))
            if self.dialect == "postgresql":
                q = q.with_for_update()
            out.update((r.id, r) for r in conn.execute(q) if r.map_id == map_id)
        return out

    def review_by_score(
        self, map_id: str, *, accept_from: float | None = None, reject_below: float | None = None,
        lonlat_box: tuple[float, float, float, float] | None = None, who: str, comment: str = "",
        dry_run: bool = False,
    ) -> ReviewResult:  # fmt: skip
        """Accept the unreviewed detections scoring at least ``accept_from`` and reject those
        scoring below ``reject_below`` (those inside ``lonlat_box`` only, when given), as one
        changeset: recorded, attributed and revertible like any other.

        What a team does before reviewing the doubtful detections one by one. Detections
        without a score, and markings a person decided on, are left as they are.
        ``dry_run`` counts without writing.

        Raises
        ------
        StoreError
            If neither threshold is given, one lies outside [0, 1], or ``reject_below``
            is above ``accept_from``.
        """
        for name, v in (("accept_from", accept_from), ("reject_below", reject_below)):
            if v is not None and not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise StoreError(f"{name} must lie in [0, 1], got {v!r}")
        if accept_from is None and reject_below is None:
            raise StoreError("give accept_from, reject_below or both")
        if accept_from is not None and reject_below is not None and reject_below > accept_from:
            raise StoreError(f"reject_below ({reject_below}) is above accept_from ({accept_from})")
        c = markings.c
        pick = []
        if accept_from is not None:
            pick.append(c.score >= accept_from)
        if reject_below is not None:
            pick.append(c.score < reject_below)
        with self._write() as conn:
            row = self._map_row(conn, map_id, lock=True)
            where = self._selection(conn, map_id, ["unreviewed"], lonlat_box).where
            rows = [] if where is None else conn.execute(
                select(markings).where(where, c.source == "detected", c.score.is_not(None), or_(*pick))
                .order_by(c.id)
            ).all()  # fmt: skip
            new = ["accepted" if accept_from is not None and r.score >= accept_from else "rejected" for r in rows]
            n_acc = new.count("accepted")
            if dry_run or not rows:
                return ReviewResult(n_acc, len(rows) - n_acc, None, int(row.revision))
            now = _now()
            rev = self._next_revision(conn, map_id)
            thresholds = ", ".join(
                ([f"accept from {accept_from:g}"] if accept_from is not None else [])
                + ([f"reject below {reject_below:g}"] if reject_below is not None else []))  # fmt: skip
            comment = comment or f"review by score: {thresholds}"
            cs_id = conn.execute(
                insert(changesets).values(map_id=map_id, who=who, at=now, n_create=0, n_update=len(rows),
                                          n_delete=0, comment=comment)
            ).inserted_primary_key[0]  # fmt: skip
            _update_many(conn, [{"_id": r.id, "_v_status": st, "_v_version": r.version + 1, "_v_revision": rev,
                                 "_v_updated_at": now} for r, st in zip(rows, new)])  # fmt: skip
            log_rows = []
            for r, st in zip(rows, new):
                before = _row_json(r)
                log_rows.append(dict(map_id=map_id, changeset_id=cs_id, marking_id=r.id, op="update", who=who,
                                     at=now, before=before, after={**before, "status": st, "version": r.version + 1},
                                     comment=comment))  # fmt: skip
            _insert_many(conn, edits, log_rows)
            counts = Counter()
            for r, st in zip(rows, new):
                counts[_count_key(r.status, r.source, r.kind, r.score)] -= 1
                counts[_count_key(st, r.source, r.kind, r.score)] += 1
            _tally(conn, map_id, counts)
            self._touch_map(conn, map_id)
        log.info("map %s: %d detections accepted and %d rejected by score (%s) by %s, changeset %d",
                 map_id, n_acc, len(rows) - n_acc, thresholds, who, cs_id)  # fmt: skip
        return ReviewResult(n_acc, len(rows) - n_acc, int(cs_id), rev)

    def _apply_one(self, conn, map_id, crs, c: Change, current, now, rev: int, updates: list):
        """Apply one change; an update's new values are appended to ``updates`` instead, for
        :func:`_update_many` (a statement built per row cost most of a large changeset's time)."""
        if c.op == "create":
            if c.marking is None:
                raise StoreError("a create change needs a marking")
            m = c.marking
            if m.lon is not None and m.lat is not None and not _is_position(m.x, m.y):
                m.x, m.y = from_wgs84(crs).transform(float(m.lon), float(m.lat))
            row = marking_row(m, crs, now)
            row["map_id"] = map_id
            row["version"] = 1
            row["revision"] = rev
            if c.id is not None:
                # Re-creating a deleted marking (a revert) keeps its id, and its
                # version moves on so that old ETags stay stale.
                row["id"] = c.id
                taken = conn.execute(select(markings.c.id).where(markings.c.id == c.id)).first()
                if taken is not None:
                    raise ConflictError([Conflict(id=c.id, reason="exists")])
                row["version"] = (m.version or 0) + 1
                conn.execute(delete(removed_markings).where(removed_markings.c.map_id == map_id,
                                                            removed_markings.c.marking_id == c.id))
            new_id = conn.execute(insert(markings).values(**row).returning(markings.c.id)).scalar_one()
            after = _row_json(_row_obj(row, new_id))
            return {"op": "create", "id": new_id, "version": row["version"]}, None, after
        row = current[c.id]
        before = _row_json(row)
        if c.op == "delete":
            conn.execute(delete(markings).where(markings.c.id == c.id))
            self._removed(conn, map_id, [c.id], rev)
            return {"op": "delete", "id": c.id, "version": None}, before, None
        unknown = set(c.fields) - EDITABLE_FIELDS
        if unknown:
            raise InvalidMarkingError(f"cannot change field(s) {', '.join(sorted(unknown))}")
        m = _marking_from_row(row)
        patch = dict(c.fields)
        if "lon" in patch or "lat" in patch:
            lon = _finite("lon", patch.pop("lon", m.lon))
            lat = _finite("lat", patch.pop("lat", m.lat))
            if not (-180 <= lon <= 180 and -90 <= lat <= 90):
                raise InvalidMarkingError(f"lon/lat out of range: {lon}, {lat}")
            patch["x"], patch["y"] = from_wgs84(crs).transform(lon, lat)
        for k, v in patch.items():
            setattr(m, k, v)
        values = marking_row(m, crs, now)
        values.pop("created_at")
        values["version"] = row.version + 1
        values["revision"] = rev
        updates.append({"_id": c.id, **{f"_v_{k}": v for k, v in values.items()}})
        after = _row_json(_row_obj(values, c.id, map_id))
        return {"op": "update", "id": c.id, "version": row.version + 1}, before, after

    def changesets(self, map_id: str, limit: int = 50, offset: int = 0) -> tuple[list[ChangesetInfo], int]:
        with self._read() as conn:
            self._map_row(conn, map_id)
            total = conn.execute(
                select(func.count()).select_from(changesets).where(changesets.c.map_id == map_id)
            ).scalar_one()
            rows = conn.execute(
                select(changesets).where(changesets.c.map_id == map_id)
                .order_by(changesets.c.id.desc()).limit(limit).offset(offset)
            ).all()  # fmt: skip
        return [_changeset_info(r) for r in rows], total

    def get_changeset(self, map_id: str, changeset_id: int) -> ChangesetInfo | None:
        """One changeset of a map, or None when the map has none of that id."""
        with self._read() as conn:
            self._map_row(conn, map_id)
            r = conn.execute(
                select(changesets).where(changesets.c.id == changeset_id, changesets.c.map_id == map_id)
            ).first()
        return _changeset_info(r) if r is not None else None

    def history(
        self, map_id: str, limit: int = 50, offset: int = 0, changeset_id: int | None = None,
        marking_id: int | None = None,
    ) -> tuple[list[EditInfo], int]:  # fmt: skip
        """The edit log of a map, newest first, with the total count."""
        where = edits.c.map_id == map_id
        if changeset_id is not None:
            where = and_(where, edits.c.changeset_id == changeset_id)
        if marking_id is not None:
            where = and_(where, edits.c.marking_id == marking_id)
        with self._read() as conn:
            self._map_row(conn, map_id)
            total = conn.execute(select(func.count()).select_from(edits).where(where)).scalar_one()
            rows = conn.execute(
                select(edits).where(where).order_by(edits.c.id.desc()).limit(limit).offset(offset)
            ).all()
        return [_edit_info(r) for r in rows], total

    def get_edit(self, map_id: str, edit_id: int) -> EditInfo | None:
        """One entry of a map's edit log, or None when the map has none of that id."""
        with self._read() as conn:
            self._map_row(conn, map_id)
            r = conn.execute(select(edits).where(edits.c.id == edit_id, edits.c.map_id == map_id)).first()
        return _edit_info(r) if r is not None else None

    def revert_changeset(self, map_id: str, changeset_id: int, who: str, comment: str = "") -> ChangesetResult:
        """Undo a changeset with a new changeset; conflicts if its markings changed since.

        Raises
        ------
        UnknownChangesetError
            If the map has no changeset of that id.
        ConflictError
            If a marking it wrote was changed or deleted since; nothing is written.
        """
        e = edits.c
        with self._read() as conn:
            self._map_row(conn, map_id)
            log_rows = [_edit_info(r) for r in conn.execute(
                select(edits).where(e.map_id == map_id, e.changeset_id == changeset_id).order_by(e.id.desc())
            )]  # fmt: skip
        if not log_rows:
            raise UnknownChangesetError(map_id, changeset_id)
        comment = comment or f"revert changeset {changeset_id}"
        if all(e.op == "update" for e in log_rows):
            return self._restore(map_id, changeset_id, log_rows, who, comment)
        inverse: list[Change] = []
        for e in log_rows:
            if e.op == "import":
                raise StoreError(
                    f"changeset {changeset_id} is an import; delete the map or its markings instead"
                )
            if e.op == "create":
                inverse.append(Change("delete", id=e.marking_id, version=e.after["version"]))
            elif e.op == "delete":
                m = _marking_from_json(e.before)
                m.version = e.before["version"]
                inverse.append(Change("create", id=e.marking_id, marking=m))
            else:
                fields_ = {k: e.before[k] for k in _MARKING_FIELDS}
                inverse.append(Change("update", id=e.marking_id, version=e.after["version"], fields=fields_))
        return self.apply_changeset(map_id, inverse, who, comment, reverts=changeset_id)

    def _restore(self, map_id: str, changeset_id: int, log_rows: list[EditInfo], who: str,
                 comment: str) -> ChangesetResult:  # fmt: skip
        """Revert a changeset of updates alone (a review by score, a bulk edit): each marking
        gets back the state logged before its edit, in as many statements as a review takes.

        A marking still at the version its edit left is in the state logged after it: every
        write of a marking moves its version on. So the revert reads versions, not markings,
        writes only the columns the changeset changed, and logs the states it already has,
        where :meth:`apply_changeset` checks and converts each marking as an edit of its own.
        """
        now = _now()
        c = markings.c
        with self._write() as conn:
            self._map_row(conn, map_id, lock=True)
            ids = [e.marking_id for e in log_rows]
            current = self._current(conn, map_id, ids, select(c.id, c.map_id, c.version))
            conflicts = []
            for e in log_rows:
                row, expected = current.get(e.marking_id), e.after["version"]
                if row is None:
                    conflicts.append(Conflict(id=e.marking_id, reason="missing", expected_version=expected))
                elif row.version != expected:
                    conflicts.append(Conflict(e.marking_id, "version", expected_version=expected,
                                              actual_version=row.version))  # fmt: skip
            if conflicts:
                raise ConflictError(conflicts)
            rev = self._next_revision(conn, map_id)
            cs_id = conn.execute(
                insert(changesets).values(map_id=map_id, who=who, at=now, comment=comment, n_create=0,
                                          n_update=len(log_rows), n_delete=0, reverts=changeset_id)
            ).inserted_primary_key[0]  # fmt: skip
            changed = _changed_fields((e.before, e.after) for e in log_rows)
            moved = "x" in changed or "y" in changed
            if moved:
                changed += ["lon", "lat"]
            updates, log_new, results, xs, ys, counts = [], [], [], [], [], Counter()
            for e in log_rows:
                counts[_dict_key(e.after)] -= 1
                counts[_dict_key(e.before)] += 1
                version = e.after["version"] + 1
                after = {**e.before, "version": version}
                u = {"_id": e.marking_id, **{f"_v_{k}": after[k] for k in changed}}
                if moved:
                    u["_v_gx"] = math.floor(after["x"] / GRID_CELL_M)
                    u["_v_gy"] = math.floor(after["y"] / GRID_CELL_M)
                    xs.append(after["x"])
                    ys.append(after["y"])
                u.update(_v_version=version, _v_revision=rev, _v_updated_at=now)
                updates.append(u)
                log_new.append(dict(map_id=map_id, changeset_id=cs_id, marking_id=e.marking_id, op="update",
                                    who=who, at=now, before=e.after, after=after, comment=comment))  # fmt: skip
                results.append({"op": "update", "id": e.marking_id, "version": version})
            _update_many(conn, updates)
            _insert_many(conn, edits, log_new)
            _tally(conn, map_id, counts)
            self._touch_map(conn, map_id, xs, ys)
        written = _LoggedMarkings({r["marking_id"]: r["after"] for r in log_new})
        log.info("map %s: changeset %d reverted by %s (%d markings), changeset %d",
                 map_id, changeset_id, who, len(log_rows), cs_id)  # fmt: skip
        return ChangesetResult(changeset_id=cs_id, results=results, markings=written)

    # ------------------------------------------------------------------ builds
    def replace_detected(
        self, map_id: str, tile_key: str, items: list[Marking], job_id: int | None = None,
        ground: bytes | None = None,
    ) -> int:
        """Replace a tile's unreviewed detections with a new set, in one transaction.

        Markings a person decided on (source ``manual``, or status ``accepted`` or
        ``rejected``) are never touched, and new detections within
        :data:`SUPPRESS_RADIUS_M` of one are dropped: a rebuild keeps manual edits.
        With ``job_id``, the tile is recorded as done for that job in the same
        transaction, so a resumed build neither repeats nor loses it. ``ground``
        (WKB of a polygon in the map's CRS) is the ground the tile's imagery
        shows, recorded with it for :meth:`imaged_footprint`.

        Returns
        -------
        int
            The number of markings inserted.
        """
        now = _now()
        c = markings.c
        if ground is not None:
            import shapely

            try:
                shapely.from_wkb(bytes(ground))
            except (shapely.errors.GEOSException, TypeError, ValueError) as exc:
                raise StoreError(f"tile {tile_key}: its ground is not WKB: {exc}") from None
        with self._write() as conn:
            crs = self._crs_for_write(conn, map_id)
            rev = self._next_revision(conn, map_id)
            gone = conn.execute(
                delete(markings).where(
                    c.map_id == map_id, c.tile_key == tile_key, c.source == "detected",
                    c.status == "unreviewed",
                ).returning(c.id, c.kind, c.score)
            ).all()  # fmt: skip
            self._removed(conn, map_id, [r.id for r in gone], rev)
            counts = Counter()
            for r in gone:
                counts[_count_key("unreviewed", "detected", r.kind, r.score)] -= 1
            rows = []
            for i, m in enumerate(items):
                m.source, m.status, m.tile_key = "detected", "unreviewed", tile_key
                try:
                    row = marking_row(m, crs, now)
                except InvalidMarkingError as exc:
                    raise InvalidMarkingError(f"tile {tile_key}, marking {i}: {exc}") from None
                row["map_id"], row["version"], row["revision"] = map_id, 1, rev
                rows.append(row)
            if rows:
                xs = np.array([r["x"] for r in rows])
                ys = np.array([r["y"] for r in rows])
                r = SUPPRESS_RADIUS_M
                kept = conn.execute(
                    select(c.x, c.y).where(
                        self._bbox_clause(map_id, xs.min() - r, ys.min() - r, xs.max() + r, ys.max() + r),
                        or_(c.source == "manual", c.status.in_(["accepted", "rejected"])),
                    )
                ).all()
                if kept:
                    k = np.array(kept, float)
                    d2 = (xs[:, None] - k[None, :, 0]) ** 2 + (ys[:, None] - k[None, :, 1]) ** 2
                    keep = d2.min(axis=1) > r * r
                    rows = [row for row, ok in zip(rows, keep) if ok]
            _insert_many(conn, markings, rows)
            counts.update(_dict_key(r) for r in rows)
            _tally(conn, map_id, counts)
            if job_id is not None:
                conn.execute(
                    delete(job_tiles).where(job_tiles.c.job_id == job_id, job_tiles.c.tile_key == tile_key)
                )
                conn.execute(
                    insert(job_tiles).values(job_id=job_id, tile_key=tile_key, n_markings=len(rows), done_at=now)
                )
            if ground is not None:
                g = imaged_ground.c
                conn.execute(delete(imaged_ground).where(g.map_id == map_id, g.tile_key == tile_key))
                conn.execute(insert(imaged_ground).values(map_id=map_id, tile_key=tile_key, footprint=bytes(ground),
                                                          built_at=now))
            self._touch_map(conn, map_id, [r["x"] for r in rows], [r["y"] for r in rows])
        return len(rows)

    def imaged_footprint(self, map_id: str) -> "shapely.Geometry | None":  # noqa: F821 (imported on use)
        """The ground the map's builds imaged: the union of its tiles' recorded ground.

        Returns
        -------
        shapely.Polygon or shapely.MultiPolygon or None
            In the map's CRS, metres; None when no build recorded any ground
            (no build yet, or only builds of schema revisions before 0005).
        """
        import shapely

        with self._read() as conn:
            self._map_row(conn, map_id)
            blobs = conn.execute(
                select(imaged_ground.c.footprint).where(imaged_ground.c.map_id == map_id)
            ).scalars().all()  # fmt: skip
        if not blobs:
            return None
        # On a millimetre grid: neighbouring tiles' borders, each computed from its own
        # window, differ in the last bits and would leave slivers between them.
        ground = shapely.union_all(shapely.from_wkb(np.array([bytes(b) for b in blobs], dtype=object)),
                                   grid_size=GROUND_GRID_M)
        return None if ground.is_empty else ground

    def done_tiles(self, job_id: int) -> set[str]:
        with self._read() as conn:
            return set(conn.execute(select(job_tiles.c.tile_key).where(job_tiles.c.job_id == job_id)).scalars())

    # ------------------------------------------------------------------ jobs
    def create_job(self, kind: str, map_id: str | None, params: dict[str, Any] | None = None) -> int:
        now = _now()
        with self._write() as conn:
            if map_id is not None:
                self._map_row(conn, map_id)
            return conn.execute(
                insert(jobs).values(
                    kind=kind, map_id=map_id, status="accepted", progress=0.0, params=params or {},
                    created_at=now, updated_at=now,
                )
            ).inserted_primary_key[0]  # fmt: skip

    def update_job(
        self, job_id: int, *, status: str | None = None, progress: float | None = None,
        error: str | None = None,
    ) -> JobInfo:  # fmt: skip
        now = _now()
        values: dict[str, Any] = {"updated_at": now}
        if status is not None:
            if status not in JOB_STATUSES:
                raise StoreError(f"job status must be one of {', '.join(JOB_STATUSES)}")
            values["status"] = status
            if status == "running":
                values["started_at"] = func.coalesce(jobs.c.started_at, now)
            if status in ("successful", "failed", "dismissed"):
                values["finished_at"] = now
        if progress is not None:
            values["progress"] = max(0.0, min(100.0, float(progress)))
        if error is not None:
            values["error"] = error
        with self._write() as conn:
            n = conn.execute(update(jobs).where(jobs.c.id == job_id).values(**values)).rowcount
            if not n:
                raise UnknownJobError(job_id)
        return self.get_job(job_id)

    @staticmethod
    def _job_info(r) -> JobInfo:
        return JobInfo(
            id=r.id, kind=r.kind, map_id=r.map_id, status=r.status, progress=r.progress,
            params=dict(r.params or {}), error=r.error, created_at=_utc(r.created_at),
            updated_at=_utc(r.updated_at), started_at=_utc(r.started_at),
            finished_at=_utc(r.finished_at),
        )  # fmt: skip

    def get_job(self, job_id: int) -> JobInfo:
        with self._read() as conn:
            r = conn.execute(select(jobs).where(jobs.c.id == job_id)).first()
        if r is None:
            raise UnknownJobError(job_id)
        return self._job_info(r)

    def find_jobs(self, kind: str | None = None, map_id: str | None = None, status=None) -> list[JobInfo]:
        q = select(jobs).order_by(jobs.c.id)
        if kind is not None:
            q = q.where(jobs.c.kind == kind)
        if map_id is not None:
            q = q.where(jobs.c.map_id == map_id)
        if status is not None:
            q = q.where(jobs.c.status.in_([status] if isinstance(status, str) else list(status)))
        with self._read() as conn:
            return [self._job_info(r) for r in conn.execute(q)]

    # ------------------------------------------------------------------ imagery
    def add_imagery(
        self, map_id: str, path: str, crs: str, bounds: tuple[float, float, float, float],
        resolution_m: float,
    ) -> int:  # fmt: skip
        with self._write() as conn:
            self._map_row(conn, map_id)
            return conn.execute(
                insert(imagery).values(
                    map_id=map_id, path=str(path), crs=crs, minx=bounds[0], miny=bounds[1],
                    maxx=bounds[2], maxy=bounds[3], resolution_m=float(resolution_m),
                    created_at=_now(),
                )
            ).inserted_primary_key[0]  # fmt: skip

    @staticmethod
    def _imagery_info(r) -> ImageryInfo:
        return ImageryInfo(r.id, r.map_id, r.path, r.crs, (r.minx, r.miny, r.maxx, r.maxy),
                           r.resolution_m, _utc(r.created_at))  # fmt: skip

    def get_imagery(self, imagery_id: int) -> ImageryInfo:
        with self._read() as conn:
            r = conn.execute(select(imagery).where(imagery.c.id == imagery_id)).first()
        if r is None:
            raise UnknownImageryError(imagery_id)
        return self._imagery_info(r)

    def list_imagery(self, map_id: str) -> list[ImageryInfo]:
        with self._read() as conn:
            self._map_row(conn, map_id)
            rows = conn.execute(select(imagery).where(imagery.c.map_id == map_id).order_by(imagery.c.id))
            return [self._imagery_info(r) for r in rows]


def _is_connect_error(exc: DBAPIError) -> bool:
    text = str(exc.orig).lower()
    return any(s in text for s in ("could not connect", "connection refused", "server closed", "terminating connection", "unable to open database"))


def _is_position(x, y) -> bool:
    return x is not None and y is not None and math.isfinite(x) and math.isfinite(y)


def _lonlat_hint(changes: Sequence[Change]):
    for c in changes:
        if c.marking is not None and c.marking.lon is not None and c.marking.lat is not None:
            return (float(c.marking.lon), float(c.marking.lat))
    return None


class _RowObj:
    def __init__(self, d: dict[str, Any]):
        self.__dict__.update(d)


def _row_obj(values: dict[str, Any], marking_id: int, map_id: str | None = None) -> _RowObj:
    d = dict(values)
    d["id"] = marking_id
    if map_id is not None:
        d["map_id"] = map_id
    return _RowObj(d)


def _marking_from_json(d: dict[str, Any]) -> Marking:
    return Marking(**{k: v for k, v in d.items() if k in _FROM_JSON_FIELDS})


# ``dataclasses.fields`` costs more than the rest of a conversion: a large changeset converts
# every marking several times.
_JSON_FIELDS = tuple(f.name for f in fields(Marking))
#: :data:`_JSON_FIELDS` of a row of ``select(markings)``, by position.
_MARKING_ROW_JSON = itemgetter(*(list(markings.c.keys()).index(k) for k in _JSON_FIELDS))
_FROM_JSON_FIELDS = frozenset(_JSON_FIELDS) - {"id", "version"}


__all__ = [
    "Change", "Changes", "ChangesetInfo", "ChangesetResult", "Conflict", "ConflictError", "EditInfo",
    "ImageryInfo", "InvalidMarkingError", "JobInfo", "MapExistsError", "MapInfo", "MarkingArrays",
    "SchemaError", "StaleRevisionError", "Store", "StoreError", "StoreUnavailableError", "UnknownChangesetError",
    "UnknownImageryError", "UnknownJobError", "UnknownMapError", "UnknownMarkingError",
    "marking_to_json",
]  # fmt: skip

"""Copying a whole lanemap database into another one.

Deployments start on the SQLite default and move to PostgreSQL when they
grow; backups want one consistent file. :func:`copy_database` reads the source
in one snapshot and writes the target in one transaction, table by table in
the order their foreign keys need, keeping every id: maps, markings with their
versions and revisions, the change feed's deletions, changesets and the edit
log, imagery records and build jobs. The target's id counters continue where
the source's stopped, so no id is ever given twice (feature ids are ETag
scopes, and the edit log names deleted markings by id).

Imagery files are not copied: their records keep their paths, which the
servers of the target database must see as well.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime

from sqlalchemy import DateTime, Integer, Table, func, select, text
from sqlalchemy.engine import Connection
from sqlalchemy.exc import DBAPIError

from .schema import edits, markings, metadata, removed_markings
from .store import Store, StoreError, _insert_many

log = logging.getLogger(__name__)

#: The tables in the order their foreign keys need (maps first).
TABLES: list[Table] = list(metadata.sorted_tables)

#: Other places a table's ids are named, which its counter must pass as well.
_ID_REFERENCES = {markings.name: [removed_markings.c.marking_id, edits.c.marking_id]}


class CopyError(StoreError):
    """The database cannot be copied there (the same database, a target that holds data)."""


@dataclass
class CopyReport:
    """What :func:`copy_database` copied: rows per table, and how long it took (seconds)."""

    rows: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0


def _counter_tables() -> list[Table]:
    """Tables whose single integer key the database counts up (and never gives twice)."""
    out = []
    for t in TABLES:
        cols = list(t.primary_key.columns)
        if len(cols) == 1 and isinstance(cols[0].type, Integer) and cols[0].autoincrement in (True, "auto"):
            out.append(t)
    return out


def _portable(value: datetime | None, dialect: str) -> datetime | None:
    """A timestamp as the target keeps it: aware UTC on PostgreSQL, naive UTC on SQLite
    (where the store writes UTC and reads it back without a zone)."""
    if value is None:
        return None
    value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
    return value.replace(tzinfo=None) if dialect == "sqlite" else value


def _last_id(conn: Connection, dialect: str, table: Table) -> int:
    """The highest id ``table`` has given out: its counter, its rows, and where else its ids are named."""
    key = list(table.primary_key.columns)[0]
    ids = [conn.execute(select(func.max(key))).scalar()]
    ids += [conn.execute(select(func.max(c))).scalar() for c in _ID_REFERENCES.get(table.name, [])]
    if dialect == "sqlite":
        ids.append(conn.execute(text("SELECT seq FROM sqlite_sequence WHERE name = :t"), {"t": table.name}).scalar())
    else:
        ids.append(conn.execute(text("SELECT pg_sequence_last_value(pg_get_serial_sequence(:t, :c))"),
                                {"t": table.name, "c": key.name}).scalar())  # fmt: skip
    return max((int(v) for v in ids if v is not None), default=0)


def _continue_ids(conn: Connection, dialect: str, table: Table, last: int) -> None:
    """Make ``table``'s counter give ids above ``last`` from now on."""
    if last <= 0:
        return
    if dialect == "sqlite":
        conn.execute(text("DELETE FROM sqlite_sequence WHERE name = :t"), {"t": table.name})
        conn.execute(text("INSERT INTO sqlite_sequence (name, seq) VALUES (:t, :v)"), {"t": table.name, "v": last})
    else:
        key = list(table.primary_key.columns)[0].name
        conn.execute(text("SELECT setval(pg_get_serial_sequence(:t, :c), :v, true)"),
                     {"t": table.name, "c": key, "v": last})  # fmt: skip


def copy_database(
    source: Store, target: Store, *, batch: int = 5000,
    progress: Callable[[str, int, int], None] | None = None,
) -> CopyReport:  # fmt: skip
    """Copy everything ``source`` holds into the empty database ``target``.

    Both must be at this lanemap's schema revision (``lanemap db upgrade``).
    The source is read in one snapshot, so writes during the copy are either
    in it whole or not at all; the target is written in one transaction, so a
    copy that fails leaves it empty.

    Parameters
    ----------
    progress : callable, optional
        Called with a table's name, the rows copied of it so far and its row count.

    Raises
    ------
    CopyError
        If the two are the same database, or the target holds data.
    """
    if source.url == target.url:
        raise CopyError("the source and the target are the same database")
    t0 = time.perf_counter()
    try:
        report = _copy(source, target, batch, progress)
    except DBAPIError as exc:  # a full disk, a lost connection: the target's transaction rolled back
        raise CopyError(f"the copy to {target.display_url} failed and wrote nothing: "
                        f"{str(exc.orig).strip() or exc.orig.__class__.__name__}") from exc  # fmt: skip
    report.seconds = time.perf_counter() - t0
    log.info("copied %s in %.1f s", ", ".join(f"{n} {k}" for k, n in report.rows.items()), report.seconds)
    return report


def _copy(source: Store, target: Store, batch: int, progress) -> CopyReport:
    report = CopyReport()
    with source.snapshot() as src, target.transaction() as dst:
        for t in TABLES:
            held = dst.execute(select(func.count()).select_from(t)).scalar_one()
            if held:
                raise CopyError(f"the target database is not empty (table {t.name} holds {held} rows): "
                                "copy into a new one")  # fmt: skip
        totals = {t.name: src.execute(select(func.count()).select_from(t)).scalar_one() for t in TABLES}
        for t in TABLES:
            stamps = [c.name for c in t.columns if isinstance(c.type, DateTime)]
            done = 0
            if progress is not None:
                progress(t.name, 0, totals[t.name])
            result = src.execution_options(yield_per=batch).execute(select(t).order_by(*t.primary_key.columns))
            for part in result.partitions(batch):
                rows = [dict(r._mapping) for r in part]
                for row in rows:
                    for name in stamps:
                        row[name] = _portable(row[name], target.dialect)
                _insert_many(dst, t, rows)
                done += len(rows)
                if progress is not None:
                    progress(t.name, done, totals[t.name])
            report.rows[t.name] = done
        for t in _counter_tables():
            _continue_ids(dst, target.dialect, t, _last_id(src, source.dialect, t))
    return report

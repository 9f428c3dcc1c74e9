"""``/health``: is this server able to serve? For container health checks and load balancers.

It answers without a token (a health check has none) and tells little: the
version, whether the database answers a trivial query within a short time,
and its schema revision. 200 when the database answers at the schema this
version needs; otherwise 503 problem+json with ``Retry-After``.
"""

from __future__ import annotations

import asyncio
import functools
import socket
import time
from dataclasses import asdict, dataclass
from urllib.parse import urlsplit

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError

from mapbuilder import migrate
from mapbuilder.store import Store, StoreError

from .. import package_version
from ..deps import Context, get_ctx
from ..problems import problem_response

router = APIRouter(tags=["Health"])

#: Seconds a client should wait before asking again while unhealthy.
RETRY_AFTER_S = 5


@dataclass
class DatabaseHealth:
    """Outcome of one database probe.

    Attributes
    ----------
    ok : bool
        The database answered, at the schema revision this version needs.
    dialect : str
        ``sqlite`` or ``postgresql``.
    revision, expected_revision : str or None
        Schema revision found and the one this version needs.
    latency_ms : float or None
        Round trip of the probe, milliseconds (None when it failed).
    error : str or None
        Why the probe failed.
    """

    ok: bool
    dialect: str
    revision: str | None = None
    expected_revision: str | None = None
    latency_ms: float | None = None
    error: str | None = None


@functools.lru_cache(maxsize=4)
def _head_revision(url: str) -> str:
    return migrate.head_revision(url)


def probe_database(store: Store, timeout_s: float) -> DatabaseHealth:
    """Run ``SELECT 1`` and read the schema revision, bounded by ``timeout_s`` on PostgreSQL."""
    expected = _head_revision(store.url)
    t0 = time.perf_counter()
    try:
        with store.engine.connect() as conn:
            with conn.begin():
                if store.dialect == "postgresql":
                    conn.exec_driver_sql(f"SET LOCAL statement_timeout = {max(1, int(timeout_s * 1000))}")
                conn.exec_driver_sql("SELECT 1")
                revision = migrate.current_revision(conn)
    except (DBAPIError, StoreError, OSError) as exc:
        orig = getattr(exc, "orig", None) or exc
        text = str(orig).strip().splitlines()[0] if str(orig).strip() else exc.__class__.__name__
        return DatabaseHealth(False, store.dialect, expected_revision=expected, error=text)
    latency = round((time.perf_counter() - t0) * 1000.0, 2)
    ok = revision == expected
    error = None if ok else f"schema revision {revision}, this version needs {expected}"
    return DatabaseHealth(ok, store.dialect, revision, expected, latency, error)


def tcp_reachable(address: str, timeout_s: float) -> bool:
    """Whether a TCP connection to ``tcp://host:port`` (or ``host:port``) opens."""
    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    if not parts.hostname or not parts.port:
        return False
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout_s):
            return True
    except OSError:
        return False


@router.get(
    "/health", summary="Health of this server: database reachable, schema revision, version",
    responses={503: {"description": "The database is unreachable or at another schema revision",
                     "content": {"application/problem+json": {}}}},
)  # fmt: skip
async def health(request: Request, ctx: Context = Depends(get_ctx)):
    timeout = ctx.settings.health_timeout_s
    try:
        db = await asyncio.wait_for(run_in_threadpool(probe_database, ctx.store, timeout), timeout)
    except asyncio.TimeoutError:
        db = DatabaseHealth(False, ctx.store.dialect, error=f"no answer within {timeout:g} s")
    body = {"version": package_version(), "database": asdict(db)}
    # This process's: reported, not judged (a map's requests wait for its build).
    body["indexes"] = ctx.indexes.status()
    scheduler = ctx.settings.dask_scheduler
    if scheduler:
        # Reported, not judged: builds wait for the cluster, reads and edits do not need it.
        reachable = await run_in_threadpool(tcp_reachable, scheduler, min(1.0, timeout))
        body["dask_scheduler"] = {"address": scheduler, "reachable": reachable}
    headers = {"Cache-Control": "no-store"}
    if db.ok:
        return JSONResponse({"status": "ok", **body}, headers=headers)
    headers["Retry-After"] = str(RETRY_AFTER_S)
    slug = "store-unavailable" if db.latency_ms is None else "schema-mismatch"
    return problem_response(request, 503, f"database: {db.error}", slug, headers=headers, **body)

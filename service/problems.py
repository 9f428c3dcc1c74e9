"""RFC 9457 problem details: every error of the API is ``application/problem+json``.

Library errors keep their messages (they name the field and the problem); this
module only decides the HTTP status for each kind of error.
"""

from __future__ import annotations

import errno
import logging
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DBAPIError, IntegrityError, InterfaceError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException

from mapbuilder import store as st

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"
TYPE_PREFIX = "urn:lanemap:problem:"


class Problem(Exception):
    """An error answered as problem details.

    Parameters
    ----------
    status : int
        HTTP status.
    detail : str
        What went wrong, naming the field or resource.
    slug : str, optional
        Last part of the ``type`` URI; default from the status.
    headers : dict, optional
        Extra response headers (``WWW-Authenticate``, ``Allow``...).
    title : str, optional
        Title of the problem type; default the status phrase.
    **extra
        Extension members of the problem object.
    """

    def __init__(self, status: int, detail: str, slug: str | None = None,
                 headers: dict[str, str] | None = None, title: str | None = None,
                 **extra: Any):  # fmt: skip
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.slug = slug or _slug(status)
        self.headers = headers or {}
        self.title = title
        self.extra = extra


def _slug(status: int) -> str:
    try:
        return HTTPStatus(status).phrase.lower().replace(" ", "-").replace("'", "")
    except ValueError:
        return "error"


def _title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def problem_response(request: Request | None, status: int, detail: str, slug: str | None = None,
                     headers: dict[str, str] | None = None, title: str | None = None,
                     **extra: Any) -> JSONResponse:  # fmt: skip
    body: dict[str, Any] = {
        "type": TYPE_PREFIX + (slug or _slug(status)),
        "title": title or _title(status),
        "status": status,
        "detail": detail,
    }
    if request is not None:
        body["instance"] = request.url.path
    body.update(extra)
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_JSON)


#: Library errors and their HTTP status, most specific first.
ERROR_STATUS: list[tuple[type[BaseException], int, str]] = [
    (st.UnknownMapError, 404, "unknown-map"),
    (st.UnknownMarkingError, 404, "unknown-feature"),
    (st.UnknownJobError, 404, "unknown-job"),
    (st.UnknownImageryError, 404, "unknown-imagery"),
    (st.UnknownChangesetError, 404, "unknown-changeset"),
    (st.MapExistsError, 409, "map-exists"),
    (st.ConflictError, 409, "conflict"),
    (st.StaleRevisionError, 409, "stale-revision"),
    (st.InvalidMarkingError, 422, "invalid-feature"),
    (st.SchemaError, 503, "schema-outdated"),
    (st.StoreUnavailableError, 503, "store-unavailable"),
    (st.StoreError, 400, "bad-request"),
]


def _register_optional(module: str, name: str, status: int, slug: str) -> None:
    """Map an error class of a module that may not be importable in every install."""
    try:
        mod = __import__(module, fromlist=[name])
        cls = getattr(mod, name)
    except (ImportError, AttributeError):
        return
    ERROR_STATUS.insert(len(ERROR_STATUS) - 1, (cls, status, slug))


_register_optional("mapbuilder.geojson", "GeoJSONError", 422, "invalid-geojson")
_register_optional("mapbuilder.raster", "ImageryError", 422, "invalid-imagery")
_register_optional("localizer.errors", "LocalizationInputError", 422, "invalid-localization-input")


#: Seconds a client should wait before retrying while the database is unavailable.
RETRY_AFTER_S = 5
#: errno values that mean the disk (or the process's file size limit) is full.
FULL_ERRNOS = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}
#: errno values that mean a folder of the server cannot be written.
UNWRITABLE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS}


def unavailable(request: Request | None, detail: str | None = None) -> JSONResponse:
    """503 for a database that cannot be reached; the client may retry."""
    return problem_response(request, 503, detail or "the database is busy or unavailable; retry later",
                            "store-unavailable", headers={"Retry-After": str(RETRY_AFTER_S)},
                            title="Database unavailable")  # fmt: skip


def storage_problem(exc: OSError, what: str) -> Problem | None:
    """The problem for a failed write of the server's files, or None if it is no storage error.

    A full disk (ENOSPC, EDQUOT) or a file size limit (EFBIG) is 507; a folder
    the server may not write (EACCES, EPERM, EROFS) is 500 with its own type:
    both are the operator's to fix, neither is the client's fault.
    """
    if exc.errno in FULL_ERRNOS:
        return Problem(507, f"{what}: the server's storage is full ({exc.strerror})", "insufficient-storage",
                       title="Insufficient storage")  # fmt: skip
    if exc.errno in UNWRITABLE_ERRNOS:
        return Problem(500, f"{what}: the server cannot write its storage folder ({exc.strerror})",
                       "storage-not-writable", title="Storage not writable")  # fmt: skip
    return None


def _is_disconnect(exc: DBAPIError) -> bool:
    return bool(exc.connection_invalidated) or isinstance(exc, (OperationalError, InterfaceError))


def status_of(exc: BaseException) -> tuple[int, str]:
    for cls, status, slug in ERROR_STATUS:
        if isinstance(exc, cls):
            return status, slug
    if isinstance(exc, ValueError):
        return 400, "bad-request"
    return 500, "internal-server-error"


def conflict_members(exc: st.ConflictError) -> dict[str, Any]:
    return {
        "conflicts": [
            {
                "id": str(c.id),
                "reason": c.reason,
                "expected_version": None if c.expected_version is None else str(c.expected_version),
                "actual_version": None if c.actual_version is None else str(c.actual_version),
            }
            for c in exc.conflicts
        ],
        "conflicting_ids": [str(c.id) for c in exc.conflicts],
    }


def _loc(loc: tuple | list) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header"):
        where, rest = parts[0], parts[1:]
        return f"{where} {'.'.join(rest)}" if rest else where
    return ".".join(parts)


def install(app: FastAPI) -> None:
    """Answer every error of ``app`` as problem details."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        return problem_response(request, exc.status, exc.detail, exc.slug, exc.headers, exc.title, **exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = []
        for e in exc.errors():
            field = _loc(e.get("loc", ()))
            errors.append({"field": field, "message": e.get("msg", "invalid"), "type": e.get("type")})
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors[:5]) or "invalid request"
        if len(errors) > 5:
            detail += f" (and {len(errors) - 5} more)"
        return problem_response(request, 422, detail, "validation-error", errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, str) else _title(exc.status_code)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no resource at {request.url.path}"
        if exc.status_code == 405:
            detail = f"method {request.method} is not allowed on {request.url.path}"
        return problem_response(request, exc.status_code, detail, headers=getattr(exc, "headers", None))

    @app.exception_handler(st.ConflictError)
    async def _conflict(request: Request, exc: st.ConflictError):
        return problem_response(request, 409, str(exc), "conflict", **conflict_members(exc))

    @app.exception_handler(IntegrityError)
    async def _integrity(request: Request, exc: IntegrityError):
        log.info("integrity error on %s %s: %s", request.method, request.url.path, exc.orig)
        return problem_response(request, 409, "the change conflicts with data already stored", "conflict")

    @app.exception_handler(st.StoreUnavailableError)
    async def _store_unavailable(request: Request, exc: st.StoreUnavailableError):
        log.warning("database unavailable on %s %s: %s", request.method, request.url.path, exc)
        return unavailable(request)

    @app.exception_handler(DBAPIError)
    async def _dbapi(request: Request, exc: DBAPIError):
        # A lost or refused connection (the server restarting, a network cut) or a
        # busy SQLite file is temporary: 503, and the pool reconnects by itself.
        if _is_disconnect(exc):
            log.warning("database error on %s %s: %s", request.method, request.url.path, exc.orig)
            return unavailable(request)
        log.exception("database error on %s %s", request.method, request.url.path)
        return problem_response(request, 500, "internal error; the server log has the details")

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError):
        problem = storage_problem(exc, "storage")
        if problem is None:
            log.exception("unhandled error on %s %s", request.method, request.url.path)
            return problem_response(request, 500, "internal error; the server log has the details")
        log.error("storage error on %s %s: %s", request.method, request.url.path, exc)
        return problem_response(request, problem.status, problem.detail, problem.slug, title=problem.title)

    @app.exception_handler(ValueError)
    async def _value(request: Request, exc: ValueError):
        status, slug = status_of(exc)
        return problem_response(request, status, str(exc) or exc.__class__.__name__, slug)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(request, 500, "internal error; the server log has the details")

"""Request-scoped access to the app's context, and bearer-token checks."""

from __future__ import annotations

import hmac
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from mapbuilder.store import Store

from .problems import Problem
from .request_id import set_client
from .settings import ServiceSettings, Token

#: The token of a write: one of ``LANEMAP_API_TOKENS`` (or the generated one).
write_bearer = HTTPBearer(scheme_name="WriteToken", auto_error=False,
                          description="A write token (LANEMAP_API_TOKENS, or the one `lanemap serve` generates)")
#: The token of a read, needed only when ``LANEMAP_READ_TOKEN_REQUIRED=1``: any token.
read_bearer = HTTPBearer(scheme_name="ReadToken", auto_error=False,
                         description="Any token, a read token (LANEMAP_READ_TOKENS) or a write token; "
                                     "needed only on a server with LANEMAP_READ_TOKEN_REQUIRED=1")


@dataclass
class Context:
    """What every route needs: the store, the settings and the job runner."""

    store: Store
    settings: ServiceSettings
    data_dir: Path
    tokens: list[Token]
    jobs: Any = None  # service.jobs.JobRunner
    indexes: Any = None  # service.index_cache.IndexCache, made by create_app with the context
    #: localizations admitted and not yet answered (changed on the event loop only)
    localize_pending: int = 0
    localize_limiter: Any = None  # anyio.CapacityLimiter, made on the event loop at first use


# The dependencies are coroutines: FastAPI runs a plain ``def`` dependency in
# its thread pool, two thread hops per request for nothing that blocks.
async def get_ctx(request: Request) -> Context:
    return request.app.state.ctx


def _token(ctx: Context, cred: HTTPAuthorizationCredentials | None) -> Token | None:
    if cred is None or not cred.credentials:
        return None
    given = cred.credentials.encode()
    match = None
    for t in ctx.tokens:
        # Compare against every token so timing does not tell which one matched.
        if hmac.compare_digest(given, t.secret.encode()) and match is None:
            match = t
    return match


def _unauthorized(detail: str) -> Problem:
    return Problem(401, detail, "unauthorized", headers={"WWW-Authenticate": 'Bearer realm="lanemap"'})


async def require_write(
    ctx: Context = Depends(get_ctx), cred: HTTPAuthorizationCredentials | None = Depends(write_bearer)
) -> str:
    """Check the bearer token of a write; returns who is writing (for the edit log).

    401 without a token or with an unknown one; 403 with a read token, which
    the server knows but which may not change data.
    """
    if cred is None:
        raise _unauthorized("this request changes data: send Authorization: Bearer <token>")
    token = _token(ctx, cred)
    if token is None:
        raise _unauthorized("the bearer token is not valid")
    set_client(token.who)
    if not token.write:
        raise Problem(403, f"the token of {token.who!r} may only read: this request changes data "
                           "and needs a write token", "forbidden")  # fmt: skip
    return token.who


async def require_read(
    ctx: Context = Depends(get_ctx), cred: HTTPAuthorizationCredentials | None = Depends(read_bearer)
) -> None:
    """Reads are open unless ``LANEMAP_READ_TOKEN_REQUIRED=1``; then any token the server knows.

    A token sent where reads are open still names the request's client (its log line, the
    localization metrics); one the server does not know is ignored there.
    """
    token = _token(ctx, cred)
    if token is not None:
        set_client(token.who)
    if not ctx.settings.read_token_required:
        return
    if cred is None:
        raise _unauthorized("reads need a token on this server: send Authorization: Bearer <token>")
    if token is None:
        raise _unauthorized("the bearer token is not valid")

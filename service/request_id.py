"""Request IDs: every answer carries ``X-Request-ID``, and the server's log lines of that request show it.

A client that reports a doubtful answer (a vehicle's pose, a refused edit)
quotes the header; the operator finds the request's access line and
whatever the server logged while answering it. A client may send its own
``X-Request-ID`` (up to 128 letters, digits and ``._:/+=-``, so that it
cannot forge log lines); anything else is replaced by a fresh one.

The ID lives in a context variable, which the localization thread inherits
(``anyio.to_thread`` runs in a copy of the request's context), and
:class:`RequestIdFilter` writes it into every log record as ``request_id``
(``-`` outside a request); :mod:`service.logs` puts it into the server's
log lines.
"""

from __future__ import annotations

import logging
import re
import uuid
from contextvars import ContextVar

from .middleware import HttpMiddleware

HEADER = b"x-request-id"
_VALID = re.compile(r"[A-Za-z0-9._:/+=-]{1,128}")

current: ContextVar[str] = ContextVar("lanemap_request_id", default="-")
#: The name of the token a request came with (``-`` without one), in a holder that the
#: request's middleware makes: the token is checked deeper down (a route's dependency, in
#: a copy of this context), and the access line and the metrics read it back up here.
_client: ContextVar[list[str] | None] = ContextVar("lanemap_client", default=None)


def set_client(name: str) -> None:
    """Record the name of the token the current request came with."""
    holder = _client.get()
    if holder is not None:
        holder[0] = name


def client() -> str:
    """The name of the token the current request came with, ``-`` without one."""
    holder = _client.get()
    return "-" if holder is None else holder[0]


def _from_client(headers) -> str | None:
    for key, value in headers:
        if key == HEADER:
            try:
                text = value.decode("ascii")
            except UnicodeDecodeError:
                return None
            return text if _VALID.fullmatch(text) else None
    return None


class RequestId(HttpMiddleware):
    """ASGI middleware: take the client's ``X-Request-ID`` or make one, and send it back."""

    async def handle(self, scope, receive, send) -> None:
        rid = _from_client(scope["headers"]) or uuid.uuid4().hex
        token = current.set(rid)
        who = _client.set(["-"])

        async def send_with_id(message) -> None:
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", ()) if k.lower() != HEADER]
                message = {**message, "headers": headers + [(HEADER, rid.encode())]}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            _client.reset(who)
            current.reset(token)


class RequestIdFilter(logging.Filter):
    """Adds ``request_id`` and ``client`` (the token's name) to every record a handler emits
    (``-`` outside a request, or for a request without a token)."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = current.get()
        record.client_name = client()
        return True

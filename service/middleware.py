"""ASGI middleware: the shape they share, and the checks of request bodies.

:class:`HttpMiddleware` passes everything but HTTP requests (lifespan
events) straight through; the service's middleware act in its ``handle``.
JSON bodies are limited in size, must be sent with a JSON content type, and
must be strict JSON: ``NaN``, ``Infinity`` and numbers that overflow a double
are refused (Python's ``json`` module would accept them).
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from .problems import PROBLEM_JSON, TYPE_PREFIX

_BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}


def is_json_type(content_type: str) -> bool:
    mime = content_type.split(";", 1)[0].strip().lower()
    return mime == "application/json" or (mime.startswith("application/") and mime.endswith("+json"))


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON (numbers must be finite)")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"number {text[:40]} is out of range")
    return v


def strict_json_loads(data: bytes | str) -> Any:
    """Parse JSON refusing NaN, Infinity and overflowing numbers (``ValueError``)."""
    try:
        return json.loads(data, parse_constant=_reject_constant, parse_float=_finite_float)
    except RecursionError:
        raise ValueError("JSON is nested too deeply") from None


class HttpMiddleware:
    """ASGI middleware acting on HTTP requests only, in :meth:`handle`; anything else
    (lifespan events) goes straight to the wrapped app."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        await self.handle(scope, receive, send)

    async def handle(self, scope, receive, send) -> None:
        raise NotImplementedError


class BodyGuard(HttpMiddleware):
    """Buffer and check request bodies.

    Parameters
    ----------
    app : ASGI app
    max_bytes : int
        Largest body accepted (413 above).
    stream_paths : str
        Regular expression of paths whose body is streamed by the route itself
        (uploads); those are passed through untouched.
    """

    def __init__(self, app, max_bytes: int, stream_paths: str = r"$^"):
        super().__init__(app)
        self.max_bytes = max_bytes
        self.stream_paths = re.compile(stream_paths)

    async def handle(self, scope, receive, send):
        if scope["method"] not in _BODY_METHODS or self.stream_paths.search(scope["path"]):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        length = headers.get("content-length")
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                return await _problem(scope, send, 400, "Content-Length is not a number")
            if n > self.max_bytes:
                return await _problem(
                    scope, send, 413, f"request body of {n} bytes exceeds the limit of {self.max_bytes} bytes"
                )
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                return await _problem(
                    scope, send, 413, f"request body exceeds the limit of {self.max_bytes} bytes"
                )
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if body:
            ctype = headers.get("content-type", "")
            if not is_json_type(ctype):
                return await _problem(
                    scope, send, 415,
                    f"Content-Type {ctype or '(none)'!s} is not accepted here: send application/json",
                )  # fmt: skip
            try:
                strict_json_loads(body)
            except (ValueError, UnicodeDecodeError) as exc:
                return await _problem(scope, send, 400, f"request body is not valid JSON: {exc}")

        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, send)


async def _problem(scope, send, status: int, detail: str) -> None:
    from http import HTTPStatus

    phrase = HTTPStatus(status).phrase
    body = json.dumps(
        {
            "type": TYPE_PREFIX + phrase.lower().replace(" ", "-"),
            "title": phrase,
            "status": status,
            "detail": detail,
            "instance": scope["path"],
        }
    ).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", PROBLEM_JSON.encode()),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class HeadAsGet(HttpMiddleware):
    """Answer ``HEAD`` like ``GET`` without the body (RFC 9110), for every GET route."""

    async def handle(self, scope, receive, send):
        if scope["method"] != "HEAD":
            return await self.app(scope, receive, send)
        scope = dict(scope, method="GET")

        async def send_headers_only(message):
            if message["type"] == "http.response.body":
                if not message.get("more_body", False):
                    await send({"type": "http.response.body", "body": b"", "more_body": False})
                return
            await send(message)

        return await self.app(scope, receive, send_headers_only)

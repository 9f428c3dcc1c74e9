"""Prometheus metrics: ``GET /metrics`` in the text exposition format.

What an operator watches: requests by route and status and how long they
took, localizations by outcome (a rising share of ``failed`` or ``ambiguous``
on a map says the road has changed under it), how long the localizer itself
took, and requests shed under load (the 503s of
``LANEMAP_LOCALIZE_MAX_PENDING``). Routes are labelled by their template
(``/collections/{mapId}/localize``), never by the path a client sent, so the
number of series stays bounded.

With several server processes (``lanemap serve --workers N``) each counts in
files of one directory that all of them share (prometheus_client's
multiprocess mode, ``PROMETHEUS_MULTIPROC_DIR``; ``lanemap serve`` makes a
fresh one unless the variable is set), and whichever process answers
``/metrics`` sums them all. The variable has to be set before this module is
first imported in a process, which is why ``lanemap serve`` sets it before it
starts its server processes.
"""

from __future__ import annotations

import os
import time

from fastapi import APIRouter, Depends
from fastapi.responses import Response
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    REGISTRY,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from prometheus_client import multiprocess as _multiprocess

from .deps import require_read
from .middleware import HttpMiddleware
from .settings import PROMETHEUS_MULTIPROC_ENV

_SECONDS = (0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

http_requests = Counter(
    "lanemap_http_requests", "HTTP requests answered, by method, route template and status code",
    ["method", "route", "status"],
)
http_seconds = Histogram(
    "lanemap_http_request_duration_seconds", "Time from a request's arrival to its answer's start, seconds",
    ["route"], buckets=_SECONDS,
)
# By map too: a map whose share of failed or ambiguous answers rises is one whose
# road has changed. Only maps that exist are counted (an unknown one is a 404
# before any localization), so the series grow with the maps, not the requests.
# By token: which fleet (one read token each) sends what, and how its answers fare;
# the names are the configured ones ("-" without a token), so they stay few.
localizations = Counter(
    "lanemap_localizations", "Localization answers by map, endpoint (frame, or each frame of a drive), method, "
    "status and the name of the request's token", ["map", "endpoint", "method", "status", "token"],
)
localizer_seconds = Histogram(
    "lanemap_localizer_duration_seconds", "Time the localizer took per request, without HTTP and queueing, "
    "seconds", ["endpoint"], buckets=_SECONDS,
)
index_build_seconds = Histogram(
    "lanemap_index_build_duration_seconds", "Time a map's localization index took to build from its markings, "
    "seconds", buckets=_SECONDS,
)
index_update_seconds = Histogram(
    "lanemap_index_update_duration_seconds", "Time a map's localization index took to update with the markings "
    "changed since it was built, instead of being built anew, seconds", buckets=_SECONDS,
)
index_file_loads = Counter(
    "lanemap_index_file_loads", "Localization indexes read from a file (LANEMAP_INDEX_DIR) instead of built, by "
    "whether they were at the map's revision (current) or older (stale, answering while the newest is built)",
    ["revision"],
)
index_file_saves = Counter(
    "lanemap_index_file_saves", "Localization indexes kept in a file (LANEMAP_INDEX_DIR), by what they came from: "
    "a build, or updates (a start's catch-up, a twentieth of the map written, or an hour since the last)",
    ["after"],
)
stale_localizations = Counter(
    "lanemap_localizations_stale", "Localization answers from a map's previous index while the index of its "
    "newest revision was built, by map", ["map"],
)
shed = Counter("lanemap_localizations_shed", "Localization requests refused with 503 while too many were pending")
drive_handovers = Counter(
    "lanemap_drive_handovers", "Drives streamed through POST /localize/sequence handed from their map to another, "
    "by the maps they left and joined", ["source", "target"],
)

router = APIRouter(tags=["Health"])


@router.get("/metrics", include_in_schema=False, dependencies=[Depends(require_read)])
def metrics() -> Response:
    """The counters of every server process, in Prometheus's text format."""
    if os.environ.get(PROMETHEUS_MULTIPROC_ENV):
        registry = CollectorRegistry()
        _multiprocess.MultiProcessCollector(registry)
    else:
        registry = REGISTRY
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


class RequestMetrics(HttpMiddleware):
    """ASGI middleware counting every HTTP request by route template and status, and timing it."""

    async def handle(self, scope, receive, send) -> None:
        t0 = time.perf_counter()
        status = [500]

        async def send_status(message) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
                # Timed to the answer's start: a streamed tile or export is not the server's wait.
                http_seconds.labels(_route(scope)).observe(time.perf_counter() - t0)
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            http_requests.labels(scope["method"], _route(scope), str(status[0])).inc()


def _route(scope) -> str:
    """The template of the route that answered (``unmatched`` when none did)."""
    route = scope.get("route")
    path = getattr(route, "path_format", None) or getattr(route, "path", None)
    return path or "unmatched"

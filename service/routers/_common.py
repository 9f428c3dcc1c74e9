"""Helpers shared by the routers: links, ETags, merge patches, feature conversion, bodies read to files."""

from __future__ import annotations

import copy
import logging
import math
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from mapbuilder.crs import from_wgs84
from mapbuilder.geojson import (
    KNOWN_PROPERTIES, GeoJSONError, feature_to_marking, marking_to_feature, read_feature_collection,
)  # fmt: skip
from mapbuilder.model import Marking

from ..filters import parse_bbox, parse_statuses
from ..problems import Problem, storage_problem

log = logging.getLogger(__name__)

CRS84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84"
GEOJSON = "application/geo+json"
JSON = "application/json"
MAX_ID = 2**63 - 1

#: Fields of a marking a feature edit may set.
FEATURE_FIELDS = ("weight", "length_m", "width_m", "bearing_deg", "score", "kind", "source", "status", "extra")


def crs_uri(crs: str | None) -> str | None:
    if crs is None:
        return None
    m = re.fullmatch(r"(?i)EPSG:(\d+)", crs.strip())
    return f"http://www.opengis.net/def/crs/EPSG/0/{m.group(1)}" if m else crs


def base_url(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def link(href: str, rel: str, type_: str | None = None, title: str | None = None) -> dict[str, str]:
    out = {"href": href, "rel": rel}
    if type_:
        out["type"] = type_
    if title:
        out["title"] = title
    return out


#: Bodies are written to their files in pieces of this size, off the event loop
#: (:func:`receive_to_file`): a slow disk must not hold up the localizations the same
#: server process answers meanwhile.
WRITE_BLOCK_BYTES = 1 << 20


async def receive_to_file(request: Request, path: Path, limit: int, what: str) -> int:
    """Write the request's body to ``path`` as it arrives, a block at a time; its size in bytes.

    413 once it passes ``limit``, 400 when the client breaks off (``what`` names the body in
    both). A write that fails (a full disk) removes the file and reads the rest of the body
    (up to the limit) before its ``OSError`` is raised, so that the client gets an answer
    rather than a reset connection. The caller removes ``path`` on any error.
    """
    size = 0
    write_error: OSError | None = None
    pending = bytearray()
    fh = await run_in_threadpool(open, path, "wb")

    async def write_pending() -> None:
        nonlocal write_error
        if write_error is None and pending:
            try:
                await run_in_threadpool(fh.write, pending)
            except OSError as exc:
                write_error = exc  # free the space at once
                await run_in_threadpool(path.unlink, missing_ok=True)
        pending.clear()

    try:
        try:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise Problem(413, f"{what} exceeds the limit of {limit} bytes", "too-large")
                if write_error is None:
                    pending += chunk
                    if len(pending) >= WRITE_BLOCK_BYTES:
                        await write_pending()
            await write_pending()
        except ClientDisconnect:
            log.info("%s aborted by the client after %d bytes", what, size)
            raise Problem(400, f"the {what} was interrupted", "truncated-upload") from None
        if write_error is not None:
            raise write_error
    finally:
        await run_in_threadpool(fh.close)
    return size


@contextmanager
def storage_failures(what: str, partial: Path, *, also: tuple[Path, ...] = ()) -> Iterator[None]:
    """Answer a failed write of the server's files as its problem (:func:`storage_problem`: 507
    for a full disk, 500 for a folder the server may not write), removing ``also`` then, and
    ``partial`` whatever happens: nothing half-written stays."""
    try:
        yield
    except OSError as exc:
        for p in also:
            p.unlink(missing_ok=True)
        problem = storage_problem(exc, what)
        if problem is None:
            raise
        log.error("%s failed: %s", what, exc)
        raise problem from None
    finally:
        try:
            partial.unlink(missing_ok=True)
        except OSError:  # an unwritable folder holds no partial file either
            log.warning("could not remove %s", partial)


def declared_length(request: Request, limit: int, what: str = "request body") -> int | None:
    """The ``Content-Length`` of a body a route reads itself (an upload, an import), or None where
    it is not given; 413 where it passes ``limit`` bytes, 400 where it is not a number."""
    declared = request.headers.get("content-length")
    if declared is None:
        return None
    try:
        n = int(declared)
    except ValueError:
        raise Problem(400, "Content-Length is not a number") from None
    if n > limit:
        raise Problem(413, f"{what} of {n} bytes exceeds the limit of {limit} bytes", "too-large")
    return n


def parse_id(value: str | int, field: str = "featureId") -> int:
    """A feature, job, changeset or imagery id as an integer (they are strings in URLs)."""
    if isinstance(value, bool):
        raise Problem(422, f"{field}: must be an integer id, got {value!r}", "invalid-id")
    if isinstance(value, int):
        n = value
    else:
        text = str(value).strip()
        if not re.fullmatch(r"\d{1,19}", text):
            raise Problem(404 if field.endswith("Id") else 422,
                          f"{field}: {str(value)[:40]!r} is not an id of this server", "invalid-id")
        n = int(text)
    if not 0 < n <= MAX_ID:
        raise Problem(404 if field.endswith("Id") else 422, f"{field}: {n} is out of range", "invalid-id")
    return n


def etag(version: int | None) -> str:
    return f'"{version}"'


def parse_version(value: str | int | None, field: str = "version") -> int | None:
    """An expected version given as ``3``, ``"3"``, ``"\\"3\\""`` or ``W/"3"``."""
    if value is None:
        return None
    if isinstance(value, bool):
        raise Problem(422, f"{field}: must be the feature's ETag value, got {value!r}", "invalid-version")
    if isinstance(value, int):
        return value
    text = str(value).strip()
    text = text.removeprefix("W/")
    text = text.strip('"')
    if not re.fullmatch(r"\d{1,19}", text):
        raise Problem(422, f"{field}: {str(value)[:40]!r} is not an ETag of this server", "invalid-version")
    return int(text)


def if_match_versions(header: str | None) -> list[int] | None:
    """Versions listed in ``If-Match``; None when absent or ``*`` (any version)."""
    if header is None or header.strip() == "*" or not header.strip():
        return None
    out = []
    for part in header.split(","):
        part = part.strip()
        part = part.removeprefix("W/")
        part = part.strip('"')
        if re.fullmatch(r"\d{1,19}", part):
            out.append(int(part))
        else:
            out.append(-1)  # matches nothing: the precondition fails
    return out


def merge_patch(target: Any, patch: Any) -> Any:
    """Apply an RFC 7396 JSON merge patch."""
    if not isinstance(patch, dict):
        return copy.deepcopy(patch)
    result = copy.deepcopy(target) if isinstance(target, dict) else {}
    for key, value in patch.items():
        if value is None:
            result.pop(key, None)
        else:
            result[key] = merge_patch(result.get(key), value)
    return result


def feature_of(m: Marking, request: Request | None = None, map_id: str | None = None) -> dict[str, Any]:
    f = marking_to_feature(m)
    if request is not None and map_id is not None:
        f["links"] = [
            link(f"{base_url(request)}/collections/{map_id}/items/{m.id}", "self", GEOJSON),
            link(f"{base_url(request)}/collections/{map_id}", "collection", JSON),
        ]
    return f


def marking_from_feature(feature: Any, crs: str | None, *, default_source: str = "manual",
                         where: str = "body") -> Marking:  # fmt: skip
    """A validated marking from a feature, positioned in ``crs`` (when known)."""
    from mapbuilder.geojson import GeoJSONError

    if isinstance(feature, dict) and isinstance(feature.get("properties"), dict):
        # GIS clients (QGIS) send every attribute, null where unset: null means "not given".
        props = {k: v for k, v in feature["properties"].items() if not (v is None and k in KNOWN_PROPERTIES)}
        feature = {**feature, "properties": props}
    try:
        m = feature_to_marking(feature, default_source=default_source)
    except GeoJSONError as exc:
        raise Problem(422, f"{where}: {exc}", "invalid-geojson") from None
    if crs is not None:
        x, y = from_wgs84(crs).transform(m.lon, m.lat)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise Problem(422, f"{where}: position {m.lon}, {m.lat} is outside the map's CRS {crs}",
                          "invalid-geojson")  # fmt: skip
        m.x, m.y = float(x), float(y)
    else:
        m.x = m.y = None  # the store picks the CRS from lon/lat
    return m


def update_fields(current: Marking, new: Marking) -> dict[str, Any]:
    """Store fields that turn ``current`` into ``new`` (feature-level values only).

    A moved marking keeps its shape: its end points move with it.
    """
    fields: dict[str, Any] = {}
    for name in FEATURE_FIELDS:
        if getattr(new, name) != getattr(current, name):
            fields[name] = getattr(new, name)
    moved = new.lon != current.lon or new.lat != current.lat
    # Unmoved markings keep x/y exactly (a lon/lat round trip would drift them).
    if moved and new.x is not None and (new.x != current.x or new.y != current.y):
        dx, dy = new.x - current.x, new.y - current.y
        fields["x"], fields["y"] = new.x, new.y
        for a, b in (("x0", "y0"), ("x1", "y1")):
            if getattr(current, a) is not None and getattr(current, b) is not None:
                fields[a] = getattr(current, a) + dx
                fields[b] = getattr(current, b) + dy
    return fields


def patched_marking(current: Marking, patch: Any, crs: str, where: str = "body") -> Marking:
    """The marking ``current`` with a merge patch of its feature applied (validated)."""
    if not isinstance(patch, dict):
        raise Problem(422, f"{where}: a merge patch must be a JSON object", "invalid-patch")
    for key in ("type",):
        if key in patch and patch[key] != "Feature":
            raise Problem(422, f"{where}: 'type' must stay 'Feature'", "invalid-patch")
    base = marking_to_feature(current)
    merged = merge_patch(base, patch)
    return marking_from_feature(merged, crs, default_source=current.source, where=where)


def markings_of_body(body: Any) -> list[Marking]:
    """The markings of a request body that must be a non-empty GeoJSON FeatureCollection."""
    try:
        items = read_feature_collection(body)
    except GeoJSONError as exc:
        raise Problem(422, f"body: {exc}", "invalid-geojson") from None
    if not items:
        raise Problem(422, "body: the FeatureCollection has no features", "invalid-geojson")
    return items


def statuses_param(text: str | None) -> list[str] | None:
    """A ``status`` query parameter: comma-separated review statuses (None: all)."""
    try:
        return parse_statuses(text)
    except ValueError as exc:
        raise Problem(400, str(exc), "invalid-parameter") from None


def bbox_param(text: str | None, status: int = 400) -> tuple[float, float, float, float] | None:
    """A ``bbox`` (``minLon,minLat,maxLon,maxLat``) given as text, None when not given: a query
    parameter (400) or a field of a request body (422) that names its problem."""
    if text is None:
        return None
    try:
        return parse_bbox(text)
    except ValueError as exc:
        raise Problem(status, str(exc), "invalid-bbox") from None

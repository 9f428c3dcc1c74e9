"""Maps as OGC API Features collections: read (Part 1), edit (Part 4), admin and import."""

from __future__ import annotations

import logging
import math
import uuid
from datetime import UTC
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Body, Depends, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from mapbuilder.model import STATUSES
from mapbuilder.store import MAX_TITLE_LENGTH, Change, ConflictError, MapInfo, Marking, UnknownMarkingError

from ..deps import Context, get_ctx, require_read, require_write
from ..jobs import ImportBodyError, import_files, read_import
from ..middleware import is_json_type
from ..problems import Problem
from ..settings import MapCoverage
from ._common import (
    CRS84,
    GEOJSON,
    JSON,
    base_url,
    bbox_param,
    crs_uri,
    declared_length,
    etag,
    feature_of,
    if_match_versions,
    link,
    marking_from_feature,
    parse_id,
    patched_marking,
    receive_to_file,
    statuses_param,
    storage_failures,
    update_fields,
)  # fmt: skip

log = logging.getLogger(__name__)

router = APIRouter(dependencies=[Depends(require_read)])

MapId = PathParam(..., description="The map's id", max_length=64)
FeatureId = PathParam(..., description="A marking id (an integer as a string)", max_length=40)

COLLECTION_ALLOW = "GET, HEAD, POST, OPTIONS"
ITEM_ALLOW = "GET, HEAD, PUT, PATCH, DELETE, OPTIONS"

FEATURE_SCHEMA = {
    "type": "object",
    "required": ["type", "geometry"],
    "properties": {
        "type": {"type": "string", "enum": ["Feature"]},
        "geometry": {
            "type": "object",
            "required": ["type", "coordinates"],
            "properties": {
                "type": {"type": "string", "enum": ["Point"]},
                "coordinates": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 3},
            },
        },
        "properties": {
            "type": "object",
            "properties": {
                "weight": {"type": "number", "exclusiveMinimum": 0},
                "length_m": {"type": "number", "minimum": 0},
                "width_m": {"type": "number", "minimum": 0},
                "bearing_deg": {"type": "number"},
                "score": {"type": ["number", "null"]},
                "kind": {"type": ["string", "null"]},
                "source": {"type": "string", "enum": ["detected", "manual", "imported"]},
                "status": {"type": "string", "enum": list(STATUSES)},
            },
        },
    },
}
FEATURE_EXAMPLE = {
    "type": "Feature",
    "geometry": {"type": "Point", "coordinates": [8.4280, 49.0071]},
    "properties": {"weight": 140, "length_m": 3.0, "width_m": 0.15, "bearing_deg": 87.5,
                   "kind": "dash", "status": "accepted"},
}  # fmt: skip


COVERAGE_DOC = (
    "How far the map speaks for the ground, for localization at its edge: `hull`, everything painted within "
    "its markings' convex hull is in it (an area mapped whole); `markings`, only the ground between its "
    "markings (a route, or parts of a city whose streets go on unmapped inside that hull); `imagery`, the "
    "ground its builds imaged, and beyond it the ground between its markings (a map built from imagery). "
    "Default (null): as the server is set (`LANEMAP_MAP_COVERAGE`); a map created empty with null takes "
    "`imagery` at its first build, as a map a build creates has it."
)


class CollectionIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: str = Field(..., description="1-64 letters, digits, '.', '_' or '-', starting with a letter or digit",
                    pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    title: str = Field("", max_length=MAX_TITLE_LENGTH)
    crs: str | None = Field(
        None, description="Metric storage CRS, e.g. EPSG:25832; default: the UTM zone of the first data",
        max_length=100,
    )
    coverage: MapCoverage | None = Field(None, description=COVERAGE_DOC)


# ---------------------------------------------------------------------------- collections
def collection_of(info: MapInfo, request: Request, default_coverage: str) -> dict[str, Any]:
    base = f"{base_url(request)}/collections/{info.id}"
    out: dict[str, Any] = {
        "id": info.id,
        "title": info.title or info.id,
        "description": f"Lane markings of map {info.id}"
        + (f" ({info.count} markings)" if info.count is not None else ""),
        "itemType": "feature",
        "crs": [CRS84],
        "storageCrs": crs_uri(info.crs),
        "revision": info.revision,
        # A copy at a revision before this one cannot follow the change feed: it reads the map whole.
        "changesSince": info.feed_since,
        # As localization takes it; coverageSet: the map's own (false: the server's setting).
        "coverage": info.coverage or default_coverage,
        "coverageSet": info.coverage is not None,
        "links": [
            link(base, "self", JSON),
            link(f"{base}/items", "items", GEOJSON, "Markings"),
            link(f"{base}/changes?since=0", "changes", GEOJSON, "Changes since a revision (keeping a copy)"),
            link(f"{base}/summary", "summary", JSON, "Markings counted; how far the review has come"),
            link(f"{base}/changesets", "changesets", JSON, "Changesets"),
            link(f"{base}/history", "history", JSON, "Edit history"),
            link(f"{base}/imagery", "imagery", JSON, "Imagery"),
            link(f"{base}/imagery/tiles/WebMercatorQuad/{{z}}/{{x}}/{{y}}.png", "tiles", "image/png",
                 "Imagery tiles"),
        ],  # fmt: skip
    }
    if info.count is not None:
        out["numberOfFeatures"] = info.count
    bounds = info.bounds_wgs84()
    if bounds is not None and all(math.isfinite(v) for v in bounds):
        out["extent"] = {"spatial": {"bbox": [list(bounds)], "crs": CRS84}}
    return out


@router.get("/collections", tags=["Maps"], summary="The maps")
def list_collections(request: Request, ctx: Context = Depends(get_ctx)) -> dict:
    maps = ctx.store.list_maps()
    return {
        "links": [link(f"{base_url(request)}/collections", "self", JSON)],
        "collections": [collection_of(m, request, ctx.settings.map_coverage) for m in maps],
    }


@router.post("/collections", tags=["Maps"], summary="Create a map", status_code=201)
def create_collection(
    body: CollectionIn, request: Request, ctx: Context = Depends(get_ctx), who: str = Depends(require_write)
):
    info = ctx.store.create_map(body.id, body.title, body.crs, body.coverage)
    info.count = 0
    url = f"{base_url(request)}/collections/{info.id}"
    return JSONResponse(collection_of(info, request, ctx.settings.map_coverage), status_code=201,
                        headers={"Location": url})  # fmt: skip


@router.get("/collections/{mapId}", tags=["Maps"], summary="One map")
def get_collection(request: Request, mapId: str = MapId, ctx: Context = Depends(get_ctx)) -> dict:
    return collection_of(ctx.store.get_map(mapId, with_count=True), request, ctx.settings.map_coverage)


@router.get(
    "/collections/{mapId}/summary", tags=["Maps"], summary="A map's markings counted, and its review",
    description=(
        "Markings per status, source and kind; the detections per status (`review.detections`) "
        "and the share of them accepted or rejected (`review.reviewedShare`, null without "
        "detections); the unreviewed detections per score, in ten bins from 0 to 1 "
        "(`review.unreviewedScores`), to see how much of the review queue is doubtful. Read in one "
        "snapshot at `revision` (also the `X-Map-Revision` header), once per revision of the map: "
        "0.7-1.4 s for a million markings, then kept until the map changes."
    ),
)  # fmt: skip
def get_summary(
    request: Request, mapId: str = MapId, ctx: Context = Depends(get_ctx),
    bbox: str | None = Query(None, max_length=200, description="Only the markings inside minLon,minLat,maxLon,maxLat "
                                                               "(WGS84), such as a district a team reviews"),
) -> JSONResponse:  # fmt: skip
    sm = ctx.store.summary(mapId, bbox_param(bbox))
    n = len(sm.unreviewed_scores)
    body = {
        "id": mapId,
        "revision": sm.revision,
        "numberOfFeatures": sm.count,
        "byStatus": sm.by_status,
        "bySource": sm.by_source,
        "byKind": sm.by_kind,
        "review": {
            "detections": sm.detections,
            "reviewedShare": sm.reviewed_share,
            "unreviewedScores": [{"min": k / n, "max": (k + 1) / n, "count": c}
                                 for k, c in enumerate(sm.unreviewed_scores)],
        },
        "links": [link(str(request.url), "self", JSON),
                  link(f"{base_url(request)}/collections/{mapId}", "collection", JSON)],
    }  # fmt: skip
    return JSONResponse(body, headers={"X-Map-Revision": str(sm.revision)})


class CollectionPatch(BaseModel):
    model_config = ConfigDict(extra="forbid")
    title: str | None = Field(None, max_length=MAX_TITLE_LENGTH, description="The map's new title")
    coverage: MapCoverage | None = Field(None, description=COVERAGE_DOC + " null sets it back to the server's.")


@router.patch("/collections/{mapId}", tags=["Maps"], summary="Retitle a map, or say how far it covers the ground")
def patch_collection(
    body: CollectionPatch, request: Request, mapId: str = MapId, ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
) -> dict:
    """Change the map's title or coverage (the members given); its id, CRS and markings stay as they are."""
    given = body.model_fields_set
    if not given:
        raise Problem(422, "give the map's new title, coverage or both", "nothing-to-change")
    if "title" in given and body.title is None:
        raise Problem(422, "title: a map's title is a string (\"\" for none)", "invalid-title")
    ctx.store.update_map(mapId, title=body.title, coverage=body.coverage, set_coverage="coverage" in given)
    if "title" in given:
        log.info("map %s retitled by %s", mapId, who)
    if "coverage" in given:
        log.info("map %s: coverage %s, set by %s", mapId, body.coverage or "as the server is set", who)
    return collection_of(ctx.store.get_map(mapId, with_count=True), request, ctx.settings.map_coverage)


@router.delete("/collections/{mapId}", tags=["Maps"], summary="Delete a map", status_code=204)
def delete_collection(mapId: str = MapId, ctx: Context = Depends(get_ctx), who: str = Depends(require_write)):
    files = [Path(i.path) for i in ctx.store.list_imagery(mapId)]
    if ctx.jobs is not None:
        for job in ctx.store.find_jobs(map_id=mapId, status=("accepted", "running")):
            ctx.jobs.cancel(job.id)
    created = ctx.store.map_head(mapId).created
    ctx.store.delete_map(mapId)
    ctx.indexes.drop(mapId, created)  # the kept files hold the map's markings too
    imagery_root = (ctx.data_dir / "imagery").resolve()
    for f in files:
        # Only files the server wrote itself are removed.
        if f.resolve().is_relative_to(imagery_root):
            f.unlink(missing_ok=True)
    return Response(status_code=204)


@router.post(
    "/collections/{mapId}/import", tags=["Maps"], summary="Import a GeoJSON FeatureCollection",
    status_code=201,
    responses={202: {"description": "With `Prefer: respond-async`: the job that imports it, at `Location`"}},
    openapi_extra={"requestBody": {"required": True, "content": {GEOJSON: {"schema": {"type": "object"}},
                                                                  JSON: {"schema": {"type": "object"}}}}},
)  # fmt: skip
async def import_features(
    request: Request,
    mapId: str = MapId,
    comment: str = Query("", max_length=2000, description="Comment of the import changeset"),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    """Import a GeoJSON FeatureCollection of markings (Points, WGS84) in one transaction: all of
    them or none. The body may be up to ``LANEMAP_MAX_IMPORT_BYTES`` long (a city's map; other
    JSON bodies are bounded by ``LANEMAP_MAX_BODY_BYTES``), is written to the data folder as it
    arrives, and is read from there a feature at a time.
    With ``Prefer: respond-async`` the answer is 202 and a job (``/jobs/{id}``) that shows the
    import's progress and, once successful, what it imported."""
    limit = ctx.settings.max_import_bytes
    ctype = request.headers.get("content-type", "")
    if not is_json_type(ctype):
        raise Problem(415, f"Content-Type {ctype or '(none)'} is not accepted here: send application/json",
                      "unsupported-media-type")  # fmt: skip
    declared = declared_length(request, limit)
    await run_in_threadpool(ctx.store.get_map, mapId)
    as_job = respond_async(request) and ctx.jobs is not None
    # Both ways the body goes to the data folder as it arrives (a city's is about 250 MB),
    # and is read from there: by this request, or by the job that imports it.
    folder = import_files(ctx.data_dir)
    token = uuid.uuid4().hex
    part, path = folder / f"{token}.part", folder / f"{token}.geojson"
    with storage_failures("import", part):
        await run_in_threadpool(folder.mkdir, parents=True, exist_ok=True)
        size = await receive_to_file(request, part, limit, "request body")
        if declared is not None and size != declared:
            raise Problem(400, f"request body is truncated: {size} of {declared} bytes arrived", "truncated-upload")
        if size == 0 or (size < 4096 and (await run_in_threadpool(part.read_bytes)).isspace()):
            raise Problem(422, "body: empty; send a GeoJSON FeatureCollection", "invalid-geojson")
        if as_job:
            await run_in_threadpool(part.replace, path)
        else:
            try:
                items = await run_in_threadpool(read_import, part)
            except ImportBodyError as exc:
                raise Problem(exc.status, exc.detail, exc.slug) from None
    if as_job:
        return await _import_as_job(request, ctx, mapId, path, size, who, comment)
    ids = await run_in_threadpool(ctx.store.add_markings, mapId, items, who, comment or "import", lonlat=True)
    return JSONResponse(
        {"imported": len(ids), "first_id": str(min(ids)), "last_id": str(max(ids))},
        status_code=201,
        headers={"Location": f"{base_url(request)}/collections/{mapId}/items"},
    )


def respond_async(request: Request) -> bool:
    """Whether the client prefers an answer before the work is done (RFC 7240 ``respond-async``)."""
    prefs = ",".join(request.headers.getlist("prefer")).replace(";", ",")
    return any(p.strip().lower() == "respond-async" for p in prefs.split(","))


async def _import_as_job(request: Request, ctx: Context, map_id: str, path: Path, size: int, who: str,
                         comment: str) -> JSONResponse:  # fmt: skip
    """Answer 202 with the job that imports the body kept at ``path``: a city's import takes
    about a minute, longer than a proxy may hold a request open, and the job shows its
    progress. The job fails with the error the synchronous import would answer."""
    from .jobs import job_json

    try:
        job_id = await run_in_threadpool(ctx.store.create_job, "import", map_id,
                                         {"file": str(path.resolve()), "bytes": size, "who": who,
                                          "comment": comment or "import"})  # fmt: skip
    except Exception:
        path.unlink(missing_ok=True)
        raise
    ctx.jobs.submit(job_id)
    job = await run_in_threadpool(ctx.store.get_job, job_id)
    url = f"{base_url(request)}/jobs/{job_id}"
    return JSONResponse(job_json(job, request), status_code=202,
                        headers={"Location": url, "Preference-Applied": "respond-async"})  # fmt: skip


# ---------------------------------------------------------------------------- items (Part 1)


@router.get(
    "/collections/{mapId}/items", tags=["Features"], summary="Markings of a map (GeoJSON)",
    responses={200: {"content": {GEOJSON: {}}}},
)  # fmt: skip
def get_items(
    request: Request,
    mapId: str = MapId,
    bbox: str | None = Query(None, description="minLon,minLat,maxLon,maxLat (WGS84)", max_length=200),
    limit: int | None = Query(None, ge=1, description="Page size (clamped to the server's maximum)"),
    offset: int = Query(0, ge=0, le=10**12),
    status: str | None = Query(None, description="Comma-separated statuses to keep", max_length=100),
    ctx: Context = Depends(get_ctx),
):
    s = ctx.settings
    lim = min(limit if limit is not None else s.items_default_limit, s.items_max_limit)
    statuses = statuses_param(status)
    if bbox is not None:
        items, matched = ctx.store.query_lonlat_box(mapId, bbox_param(bbox), statuses, lim, offset)
    else:
        items, matched = ctx.store.list_markings(mapId, limit=lim, offset=offset, statuses=statuses)
    url = request.url
    links = [link(str(url), "self", GEOJSON), link(f"{base_url(request)}/collections/{mapId}", "collection", JSON)]
    if offset + len(items) < matched:
        links.append(link(str(url.include_query_params(offset=offset + lim, limit=lim)), "next", GEOJSON))
    if offset > 0:
        links.append(link(str(url.include_query_params(offset=max(0, offset - lim), limit=lim)), "prev", GEOJSON))
    from datetime import datetime

    body = {
        "type": "FeatureCollection",
        "features": [feature_of(m) for m in items],
        "numberMatched": matched,
        "numberReturned": len(items),
        "timeStamp": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "links": links,
    }
    return JSONResponse(body, media_type=GEOJSON)


def _feature_response(m: Marking, request: Request, map_id: str, status_code: int = 200,
                      location: bool = False) -> JSONResponse:  # fmt: skip
    headers = {"ETag": etag(m.version)}
    if location:
        headers["Location"] = f"{base_url(request)}/collections/{map_id}/items/{m.id}"
    return JSONResponse(feature_of(m, request, map_id), status_code=status_code, headers=headers,
                        media_type=GEOJSON)  # fmt: skip


@router.get(
    "/collections/{mapId}/items/{featureId}", tags=["Features"], summary="One marking",
    responses={200: {"content": {GEOJSON: {}}, "headers": {"ETag": {"schema": {"type": "string"}}}}},
)  # fmt: skip
def get_item(request: Request, mapId: str = MapId, featureId: str = FeatureId, ctx: Context = Depends(get_ctx)):
    m = ctx.store.get_marking(mapId, parse_id(featureId))
    return _feature_response(m, request, mapId)


@router.options("/collections/{mapId}/items", tags=["Features"], summary="Methods allowed on the items",
                status_code=204)  # fmt: skip
def options_items(mapId: str = MapId, ctx: Context = Depends(get_ctx)):
    ctx.store.get_map(mapId)
    return Response(status_code=204, headers={"Allow": COLLECTION_ALLOW})


@router.options("/collections/{mapId}/items/{featureId}", tags=["Features"], summary="Methods allowed on a marking",
                status_code=204)  # fmt: skip
def options_item(mapId: str = MapId, featureId: str = FeatureId, ctx: Context = Depends(get_ctx)):
    ctx.store.get_marking(mapId, parse_id(featureId))
    return Response(status_code=204, headers={"Allow": ITEM_ALLOW})


# ---------------------------------------------------------------------------- editing (Part 4)
_FEATURE_BODY = {"requestBody": {"required": True, "content": {
    GEOJSON: {"schema": FEATURE_SCHEMA, "example": FEATURE_EXAMPLE},
    JSON: {"schema": FEATURE_SCHEMA, "example": FEATURE_EXAMPLE},
}}}  # fmt: skip
_PATCH_BODY = {"requestBody": {"required": True, "content": {
    "application/merge-patch+json": {"schema": {"type": "object"},
                                     "example": {"properties": {"status": "accepted"}}},
    JSON: {"schema": {"type": "object"}},
}}}  # fmt: skip


#: A marking written by PUT/PATCH/POST is answered as a GeoJSON Feature with its ETag.
_FEATURE_OUT = {"content": {GEOJSON: {}}, "headers": {"ETag": {"schema": {"type": "string"}}}}


def _single(ctx: Context, map_id: str, change: Change, who: str, if_match: bool):
    try:
        return ctx.store.apply_changeset(map_id, [change], who, "")
    except ConflictError as exc:
        c = exc.conflicts[0]
        if c.reason == "missing":
            raise UnknownMarkingError(map_id, c.id) from None
        if if_match:
            raise Problem(412, f"If-Match: feature {c.id} is at version {c.actual_version}, "
                          f"not {c.expected_version}", "precondition-failed",
                          current_version=str(c.actual_version)) from None  # fmt: skip
        raise


def _expected_version(ctx: Context, map_id: str, marking_id: int, header: str | None) -> int | None:
    versions = if_match_versions(header)
    if versions is None:
        if header is not None:  # "*": the feature must exist
            ctx.store.get_marking(map_id, marking_id)
        return None
    if len(versions) == 1:
        return versions[0]
    current = ctx.store.get_marking(map_id, marking_id)
    if current.version not in versions:
        raise Problem(412, f"If-Match: feature {marking_id} is at version {current.version}",
                      "precondition-failed", current_version=str(current.version))  # fmt: skip
    return current.version


@router.post(
    "/collections/{mapId}/items", tags=["Features"], summary="Add a marking", status_code=201,
    openapi_extra=_FEATURE_BODY, responses={201: _FEATURE_OUT},
)  # fmt: skip
def create_item(
    request: Request,
    mapId: str = MapId,
    feature: Any = Body(..., media_type=GEOJSON),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    info = ctx.store.get_map(mapId)
    m = marking_from_feature(feature, info.crs, default_source="manual")
    res = _single(ctx, mapId, Change("create", marking=m), who, False)
    return _feature_response(res.markings[res.results[0]["id"]], request, mapId, 201, location=True)


@router.put(
    "/collections/{mapId}/items/{featureId}", tags=["Features"], summary="Replace a marking",
    openapi_extra=_FEATURE_BODY, responses={200: _FEATURE_OUT},
)  # fmt: skip
def replace_item(
    request: Request,
    mapId: str = MapId,
    featureId: str = FeatureId,
    feature: Any = Body(..., media_type=GEOJSON),
    if_match: str | None = Header(None, alias="If-Match"),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    marking_id = parse_id(featureId)
    expected = _expected_version(ctx, mapId, marking_id, if_match)
    current = ctx.store.get_marking(mapId, marking_id)
    info = ctx.store.get_map(mapId)
    new = marking_from_feature(feature, info.crs, default_source=current.source)
    fields = update_fields(current, new)
    if not fields:
        if expected is not None and expected != current.version:
            raise Problem(412, f"If-Match: feature {marking_id} is at version {current.version}",
                          "precondition-failed", current_version=str(current.version))  # fmt: skip
        return _feature_response(current, request, mapId)
    version = expected if expected is not None else current.version
    try:
        res = _single(ctx, mapId, Change("update", id=marking_id, version=version, fields=fields), who,
                      expected is not None)  # fmt: skip
    except ConflictError:
        raise Problem(409, f"feature {marking_id} changed while it was being replaced; retry",
                      "conflict", conflicting_ids=[str(marking_id)]) from None  # fmt: skip
    return _feature_response(res.markings[marking_id], request, mapId)


@router.patch(
    "/collections/{mapId}/items/{featureId}", tags=["Features"],
    summary="Change a marking with a JSON merge patch (RFC 7396) of its feature",
    openapi_extra=_PATCH_BODY, responses={200: _FEATURE_OUT},
)  # fmt: skip
def patch_item(
    request: Request,
    mapId: str = MapId,
    featureId: str = FeatureId,
    patch: Any = Body(..., media_type="application/merge-patch+json"),
    if_match: str | None = Header(None, alias="If-Match"),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    marking_id = parse_id(featureId)
    expected = _expected_version(ctx, mapId, marking_id, if_match)
    info = ctx.store.get_map(mapId)
    for _attempt in range(3):
        current = ctx.store.get_marking(mapId, marking_id)
        if expected is not None and expected != current.version:
            raise Problem(412, f"If-Match: feature {marking_id} is at version {current.version}, not {expected}",
                          "precondition-failed", current_version=str(current.version))  # fmt: skip
        new = patched_marking(current, patch, info.crs, where="body")
        fields = update_fields(current, new)
        if not fields:
            return _feature_response(current, request, mapId)
        try:
            res = _single(ctx, mapId, Change("update", id=marking_id, version=current.version, fields=fields),
                          who, expected is not None)  # fmt: skip
        except ConflictError:
            continue  # changed between our read and write: merge again on the new version
        # The answer (body and ETag) is this write's result; a re-read could show a later one.
        return _feature_response(res.markings[marking_id], request, mapId)
    raise Problem(409, f"feature {marking_id} keeps changing; retry", "conflict",
                  conflicting_ids=[str(marking_id)])  # fmt: skip


@router.delete("/collections/{mapId}/items/{featureId}", tags=["Features"], summary="Delete a marking",
               status_code=204)  # fmt: skip
def delete_item(
    mapId: str = MapId,
    featureId: str = FeatureId,
    if_match: str | None = Header(None, alias="If-Match"),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    marking_id = parse_id(featureId)
    expected = _expected_version(ctx, mapId, marking_id, if_match)
    _single(ctx, mapId, Change("delete", id=marking_id, version=expected), who, expected is not None)
    return Response(status_code=204)

"""Atomic changesets of many features, the edit history, and reverts."""

from __future__ import annotations

import math
from typing import Any, Literal

from fastapi import APIRouter, Body, Depends, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from mapbuilder.model import Marking
from mapbuilder.store import (
    Change,
    ChangesetInfo,
    ChangesetResult,
    Conflict,
    ConflictError,
    EditInfo,
    StoreError,
    UnknownMarkingError,
)  # fmt: skip

from ..deps import Context, get_ctx, require_read, require_write
from ..problems import Problem
from ._common import (
    GEOJSON,
    JSON,
    MAX_ID,
    base_url,
    bbox_param,
    feature_of,
    link,
    marking_from_feature,
    parse_id,
    parse_version,
    patched_marking,
    update_fields,
)

router = APIRouter(tags=["Changesets"], dependencies=[Depends(require_read)])

MapId = PathParam(..., description="The map's id", max_length=64)
MAX_CHANGES = 10_000


class ChangeIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    op: Literal["create", "update", "delete"]
    id: str | int | None = Field(None, description="The feature id (update, delete)")
    version: str | int | None = Field(
        None, description="Expected version: the feature's ETag value (update, delete); optional"
    )
    feature: dict[str, Any] | None = Field(None, description="A GeoJSON Feature (create)")
    patch: dict[str, Any] | None = Field(None, description="A JSON merge patch of the feature (update)")


class ChangesetIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    comment: str = Field("", max_length=2000)
    changes: list[ChangeIn] = Field(..., min_length=1, max_length=MAX_CHANGES)


class RevertIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    comment: str = Field("", max_length=2000)


def _result_body(res: ChangesetResult, map_id: str, request: Request) -> dict[str, Any]:
    url = f"{base_url(request)}/collections/{map_id}/changesets/{res.changeset_id}"
    return {
        "changeset": str(res.changeset_id),
        "results": [
            {"op": r["op"], "id": str(r["id"]), "version": None if r["version"] is None else str(r["version"])}
            for r in res.results
        ],
        "links": [link(url, "self", JSON)],
    }


def _created(res: ChangesetResult, map_id: str, request: Request) -> JSONResponse:
    body = _result_body(res, map_id, request)
    return JSONResponse(body, status_code=201, headers={"Location": body["links"][0]["href"]})


@router.post("/collections/{mapId}/changesets", summary="Apply many edits atomically", status_code=201)
def post_changeset(
    body: ChangesetIn,
    request: Request,
    mapId: str = MapId,
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    info = ctx.store.get_map(mapId)
    crs = info.crs
    changes: list[Change] = []
    conflicts: list[Conflict] = []
    for i, c in enumerate(body.changes):
        where = f"changes[{i}]"
        if c.op == "create":
            if c.feature is None:
                raise Problem(422, f"{where}.feature: a create needs a GeoJSON Feature", "invalid-change")
            changes.append(Change("create", marking=marking_from_feature(c.feature, crs, where=f"{where}.feature")))
            continue
        if c.id is None:
            raise Problem(422, f"{where}.id: an {c.op} needs the feature id", "invalid-change")
        mid = parse_id(c.id, f"{where}.id")
        version = parse_version(c.version, f"{where}.version")
        if c.op == "delete":
            changes.append(Change("delete", id=mid, version=version))
            continue
        if c.patch is None:
            raise Problem(422, f"{where}.patch: an update needs a merge patch of the feature", "invalid-change")
        if crs is None:
            raise Problem(409, f"{where}: map {mapId!r} has no markings to update", "conflict")
        try:
            current = ctx.store.get_marking(mapId, mid)
        except UnknownMarkingError:
            conflicts.append(Conflict(id=mid, reason="missing", expected_version=version))
            continue
        if version is not None and version != current.version:
            conflicts.append(Conflict(mid, "version", expected_version=version, actual_version=current.version))
            continue
        new = patched_marking(current, c.patch, crs, where=f"{where}.patch")
        fields = update_fields(current, new)
        # The patch was merged onto this version: apply it only to that version.
        changes.append(Change("update", id=mid, version=current.version, fields=fields))
    if conflicts:
        # Report the deletes that would conflict too, so the client sees every one at once.
        for ch in changes:
            if ch.op != "delete":
                continue
            try:
                current = ctx.store.get_marking(mapId, ch.id)
            except UnknownMarkingError:
                conflicts.append(Conflict(id=ch.id, reason="missing", expected_version=ch.version))
                continue
            if ch.version is not None and ch.version != current.version:
                conflicts.append(Conflict(ch.id, "version", expected_version=ch.version,
                                          actual_version=current.version))  # fmt: skip
        raise ConflictError(conflicts)
    res = ctx.store.apply_changeset(mapId, changes, who, body.comment)
    return _created(res, mapId, request)


def _changeset_json(c: ChangesetInfo, request: Request) -> dict[str, Any]:
    return {
        "id": str(c.id),
        "who": c.who,
        "at": c.at.isoformat(),
        "comment": c.comment,
        "created": c.n_create,
        "updated": c.n_update,
        "deleted": c.n_delete,
        "reverts": None if c.reverts is None else str(c.reverts),
        "links": [link(f"{base_url(request)}/collections/{c.map_id}/changesets/{c.id}", "self", JSON)],
    }


def _edit_json(e: EditInfo) -> dict[str, Any]:
    return {
        "id": str(e.id),
        "changeset": str(e.changeset_id),
        "feature_id": None if e.marking_id is None else str(e.marking_id),
        "op": e.op,
        "who": e.who,
        "at": e.at.isoformat(),
        "before": e.before,
        "after": e.after,
        "comment": e.comment,
    }


def _page_links(request: Request, offset: int, limit: int, returned: int, matched: int) -> list[dict]:
    url = request.url
    links = [link(str(url), "self", JSON)]
    if offset + returned < matched:
        links.append(link(str(url.include_query_params(offset=offset + limit, limit=limit)), "next", JSON))
    if offset > 0:
        links.append(link(str(url.include_query_params(offset=max(0, offset - limit), limit=limit)), "prev", JSON))
    return links


@router.get("/collections/{mapId}/changesets", summary="Changesets, newest first")
def list_changesets(
    request: Request,
    mapId: str = MapId,
    limit: int = Query(50, ge=1, le=1000),
    offset: int = Query(0, ge=0, le=10**12),
    ctx: Context = Depends(get_ctx),
) -> dict:
    rows, total = ctx.store.changesets(mapId, limit=limit, offset=offset)
    return {
        "changesets": [_changeset_json(c, request) for c in rows],
        "numberMatched": total,
        "numberReturned": len(rows),
        "links": _page_links(request, offset, limit, len(rows), total),
    }


@router.get("/collections/{mapId}/changesets/{changesetId}", summary="One changeset with its edits")
def get_changeset(
    request: Request,
    mapId: str = MapId,
    changesetId: str = PathParam(..., max_length=40),
    ctx: Context = Depends(get_ctx),
) -> dict:
    cid = parse_id(changesetId, "changesetId")
    rows, total = ctx.store.history(mapId, limit=10_000, changeset_id=cid)
    if not rows:
        from mapbuilder.store import UnknownChangesetError

        raise UnknownChangesetError(mapId, cid)
    info = ctx.store.get_changeset(mapId, cid)
    out = _changeset_json(info, request) if info else {"id": str(cid)}
    out["edits"] = [_edit_json(e) for e in rows]
    out["numberOfEdits"] = total
    return out


@router.get("/collections/{mapId}/history", summary="The edit log, newest first")
def history(
    request: Request,
    mapId: str = MapId,
    limit: int = Query(50, ge=1, le=1000),
    offset: int = Query(0, ge=0, le=10**12),
    changeset: str | None = Query(None, max_length=40, description="Only the edits of this changeset"),
    feature: str | None = Query(None, max_length=40, description="Only the edits of this feature"),
    ctx: Context = Depends(get_ctx),
) -> dict:
    cid = parse_id(changeset, "changeset") if changeset is not None else None
    fid = parse_id(feature, "feature") if feature is not None else None
    rows, total = ctx.store.history(mapId, limit=limit, offset=offset, changeset_id=cid, marking_id=fid)
    return {
        "edits": [_edit_json(e) for e in rows],
        "numberMatched": total,
        "numberReturned": len(rows),
        "links": _page_links(request, offset, limit, len(rows), total),
    }


class ReviewIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    accept_from: float | None = Field(None, ge=0, le=1, description="Accept the unreviewed detections scoring "
                                                                  "at least this")
    reject_below: float | None = Field(None, ge=0, le=1, description="Reject the unreviewed detections scoring "
                                                                   "below this")
    bbox: str | None = Field(None, max_length=200, description="Only inside minLon,minLat,maxLon,maxLat (WGS84)")
    comment: str = Field("", max_length=2000)
    dry_run: bool = Field(False, description="Count what it would do; write nothing")


@router.post(
    "/collections/{mapId}/review", summary="Accept and reject detections by their score, as one changeset",
    status_code=201,
    responses={200: {"description": "A dry run, or nothing matched: the counts, no changeset"},
               201: {"description": "The changeset that accepted and rejected them"}},
)  # fmt: skip
def review_by_score(
    body: ReviewIn, request: Request, mapId: str = MapId, ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    """What a team does before reviewing the doubtful detections one by one: the unreviewed
    detections scoring at least `accept_from` are accepted, those below `reject_below` rejected
    (within `bbox` when given), in one changeset that the history lists and a revert undoes.
    Detections without a score and markings a person decided on are left as they are. The map's
    summary (`GET .../summary`) shows how the unreviewed scores spread."""
    res = ctx.store.review_by_score(mapId, accept_from=body.accept_from, reject_below=body.reject_below,
                                    lonlat_box=bbox_param(body.bbox, 422), who=who, comment=body.comment, dry_run=body.dry_run)  # fmt: skip
    out: dict[str, Any] = {"accepted": res.accepted, "rejected": res.rejected, "revision": res.revision,
                           "changeset": None if res.changeset_id is None else str(res.changeset_id), "links": []}
    if res.changeset_id is None:
        return JSONResponse(out, status_code=200)
    url = f"{base_url(request)}/collections/{mapId}/changesets/{res.changeset_id}"
    out["links"] = [link(url, "self", JSON)]
    return JSONResponse(out, status_code=201, headers={"Location": url})


@router.get(
    "/collections/{mapId}/review/queue", summary="The unreviewed detections, lowest score first",
    responses={200: {"content": {GEOJSON: {}}}},
)  # fmt: skip
def review_queue(
    request: Request,
    mapId: str = MapId,
    bbox: str | None = Query(None, max_length=200, description="Only inside minLon,minLat,maxLon,maxLat (WGS84)"),
    limit: int | None = Query(None, ge=1, description="Page size (clamped to the server's maximum)"),
    after: str | None = Query(None, max_length=80, description="Where the page before ended: its `next` link "
                                                                "gives it (`score,id`; `none,id` past the scores)"),
    ctx: Context = Depends(get_ctx),
):
    """The queue a person steps through (the web editor's *Start review*): the map's unreviewed
    detections (within `bbox` when given), lowest score first, those without a score last, a page
    at a time. The `next` link goes on after the page's last detection, so that the detections
    decided meanwhile leave the queue without moving the rest. `numberMatched` counts the whole
    queue as it is now."""
    lim = min(limit if limit is not None else ctx.settings.items_default_limit, ctx.settings.items_max_limit)
    key = _queue_key(after)
    items, matched = ctx.store.review_queue(mapId, after=key, limit=lim, lonlat_box=bbox_param(bbox))
    links = [link(str(request.url), "self", GEOJSON)]
    if len(items) == lim:
        last = items[-1]
        token = f"{'none' if last.score is None else repr(float(last.score))},{last.id}"
        links.append(link(str(request.url.include_query_params(after=token, limit=lim)), "next", GEOJSON))
    body = {"type": "FeatureCollection", "features": [feature_of(m) for m in items], "numberMatched": matched,
            "numberReturned": len(items), "links": links}  # fmt: skip
    return JSONResponse(body, media_type=GEOJSON)


def _queue_key(after: str | None) -> tuple[float | None, int] | None:
    """A review queue's ``after`` (``score,id`` or ``none,id``) as (score, id)."""
    if after is None:
        return None
    score, _, mid = after.partition(",")
    try:
        key = None if score == "none" else float(score)
        ok = (key is None or math.isfinite(key)) and mid.isdigit() and 0 < int(mid) <= MAX_ID
    except ValueError:
        ok = False
    if not ok:
        raise Problem(400, f"after: {after[:80]!r} is not a score and an id (score,id) from a next link",
                      "bad-request")  # fmt: skip
    return key, int(mid)


@router.post("/collections/{mapId}/changesets/{changesetId}/revert", summary="Revert a changeset",
             status_code=201)  # fmt: skip
def revert_changeset(
    request: Request,
    mapId: str = MapId,
    changesetId: str = PathParam(..., max_length=40),
    body: RevertIn | None = Body(None),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    cid = parse_id(changesetId, "changesetId")
    res = ctx.store.revert_changeset(mapId, cid, who, body.comment if body else "")
    return _created(res, mapId, request)


_EDIT_FIELDS = (
    "x", "y", "length_m", "width_m", "bearing_deg", "weight", "score", "kind", "source", "status",
    "x0", "y0", "x1", "y1", "tile_key", "extra",
)  # fmt: skip


@router.post("/collections/{mapId}/history/{editId}/revert", summary="Revert one edit", status_code=201)
def revert_edit(
    request: Request,
    mapId: str = MapId,
    editId: str = PathParam(..., max_length=40),
    body: RevertIn | None = Body(None),
    ctx: Context = Depends(get_ctx),
    who: str = Depends(require_write),
):
    eid = parse_id(editId, "editId")
    e = ctx.store.get_edit(mapId, eid)
    if e is None:
        raise Problem(404, f"map {mapId!r} has no edit {eid}", "unknown-edit")
    op, before, after, mid = e.op, e.before, e.after, e.marking_id
    if op == "create":
        change = Change("delete", id=mid, version=after["version"])
    elif op == "delete":
        keep = {k: before[k] for k in _EDIT_FIELDS if k in before}
        change = Change("create", id=mid, marking=Marking(**keep, version=before["version"]))
    elif op == "update":
        change = Change("update", id=mid, version=after["version"],
                        fields={k: before[k] for k in _EDIT_FIELDS if k in before})  # fmt: skip
    else:
        raise StoreError(f"edit {eid} is an {op}; it cannot be reverted on its own")
    comment = (body.comment if body else "") or f"revert edit {eid}"
    res = ctx.store.apply_changeset(mapId, [change], who, comment)
    return _created(res, mapId, request)

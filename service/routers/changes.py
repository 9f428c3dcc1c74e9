"""A map's changes since a revision: how a copy kept elsewhere (a fleet's, a tool's) stays current."""

from __future__ import annotations

import re

from fastapi import APIRouter, Depends, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import JSONResponse

from ..deps import Context, get_ctx, require_read
from ..problems import Problem
from ._common import GEOJSON, JSON, MAX_ID, base_url, crs_uri, feature_of, link, statuses_param

router = APIRouter(tags=["Maps"], dependencies=[Depends(require_read)])

#: Changes per page unless the client asks for fewer or more (up to ``LANEMAP_ITEMS_MAX_LIMIT``).
DEFAULT_CHANGES_LIMIT = 1000


def _after(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"(\d{1,19}):(\d{1,19})", text.strip())
    if m is None or int(m[1]) > MAX_ID or int(m[2]) > MAX_ID:
        raise Problem(400, f"after: expected REVISION:ID as in a next link, got {text[:40]!r}", "invalid-parameter")
    return int(m[1]), int(m[2])


@router.get(
    "/collections/{mapId}/changes", summary="What changed in a map since a revision",
    description=(
        "The markings written and deleted after revision `since`, oldest first: a copy of the map "
        "(a fleet's, a tool's) that applies them, page by page, holds what the map holds, at the "
        "`revision` of the last page (the one without a `next` link); ask from there next time. "
        "`features` are the markings to hold now (their `revision` is the one that wrote them last), "
        "`removed` the ids to drop, `storageCrs` the metric CRS the map keeps its markings in (the "
        "features are WGS84 lon/lat; a copy that localizes projects them to it). With `status`, the copy holds only markings of those statuses, and a "
        "marking whose status left them is listed as removed. The first page (without `after`) says "
        "in `numberMatched` how many changes the pages hold in all. A copy starts from `since=0`. 409 "
        "(`stale-revision`) when `since` is from before the map was made anew under its id (a map "
        "created again goes on past the old one's last revision, see `changesSince`), from before the "
        "deletions it keeps (`lanemap maps prune-feed`), or one the map has not reached (a database "
        "restored from an older backup): the copy must be read whole again, from `since=0`."
    ),
    responses={200: {"content": {GEOJSON: {}}},
               409: {"description": "`since` is from before the map was made anew or before the deletions "
                                   "it keeps, or the map has not reached it: read the map whole"}},
)  # fmt: skip
def get_changes(
    request: Request,
    mapId: str = PathParam(..., description="The map's id", max_length=64),
    since: int = Query(..., ge=0, le=MAX_ID, description="The revision the copy is at (0: an empty copy)"),
    status: str | None = Query(None, description="Comma-separated statuses the copy keeps", max_length=100),
    limit: int | None = Query(None, ge=1, description="Changes per page (clamped to the server's maximum)"),
    after: str | None = Query(None, max_length=40, description="Where the page starts: a next link's REVISION:ID"),
    ctx: Context = Depends(get_ctx),
):
    lim = min(limit if limit is not None else DEFAULT_CHANGES_LIMIT, ctx.settings.items_max_limit)
    page = ctx.store.changes(mapId, since, statuses=statuses_param(status), after=_after(after), limit=lim)
    features = []
    for rev, m in page.changed:
        f = feature_of(m)
        f["properties"]["revision"] = rev
        features.append(f)
    url = request.url
    links = [link(str(url), "self", GEOJSON), link(f"{base_url(request)}/collections/{mapId}", "collection", JSON)]
    if page.more:
        cursor = f"{page.after[0]}:{page.after[1]}"
        links.append(link(str(url.include_query_params(after=cursor, limit=lim)), "next", GEOJSON))
    body = {
        "type": "FeatureCollection",
        "since": since,
        "revision": page.revision,
        "storageCrs": crs_uri(page.crs),
        "features": features,
        "removed": [{"id": str(i), "revision": rev} for rev, i in page.removed],
        "numberReturned": len(features) + len(page.removed),
        "links": links,
    }
    if after is None:
        # How many the pages hold in all (a marking written after this page's read may be counted
        # too): a client may read the map anew instead of a feed longer than the map it shows.
        body["numberMatched"] = ctx.store.count_changes(mapId, since)
    return JSONResponse(body, media_type=GEOJSON)

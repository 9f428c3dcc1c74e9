"""Scoring a map against true markings (``lanemap evaluate`` over HTTP)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends, Query
from fastapi import Path as PathParam
from fastapi.responses import JSONResponse

from mapbuilder.evaluate import EmptyMapError, evaluate_map

from ..deps import Context, get_ctx, require_read
from ..problems import Problem
from ._common import GEOJSON, JSON, feature_of, markings_of_body, statuses_param

router = APIRouter(tags=["Maps"], dependencies=[Depends(require_read)])


@router.post(
    "/collections/{mapId}/evaluate", summary="Score the map against true markings",
    description="The body is a GeoJSON FeatureCollection of true markings (Points in WGS84 with "
    "length_m and bearing_deg; a survey). The map's markings over the truth's extent are scored as "
    "`lanemap evaluate` does: precision, recall, centroid and cross-track RMSE, recall by kind, and "
    "(unless errors=false) the false and missed markings as a FeatureCollection whose features' "
    "`error` property is `false` or `missed`. Reads only.",
    openapi_extra={"requestBody": {"required": True, "content": {GEOJSON: {"schema": {"type": "object"}},
                                                                  JSON: {"schema": {"type": "object"}}}}},
)  # fmt: skip
def evaluate(
    mapId: str = PathParam(..., description="The map's id", max_length=64),
    body: Any = Body(..., media_type=GEOJSON),
    tolerance: float = Query(0.3, gt=0, le=10, description="Largest centroid (or axis) distance of a match, metres"),
    border: float = Query(0.0, ge=0, le=1000, description="Leave out markings this close to the truth's edge, metres"),
    status: str = Query("unreviewed,accepted", max_length=100, description="The map's markings to score"),
    errors: bool = Query(True, description="Include the false and missed markings"),
    ctx: Context = Depends(get_ctx),
):
    statuses = statuses_param(status)
    truth = markings_of_body(body)
    try:
        ev, _ = evaluate_map(ctx.store, mapId, truth, tolerance_m=tolerance, border_m=border,
                             statuses=statuses)  # fmt: skip
    except EmptyMapError as exc:
        raise Problem(409, str(exc), "empty-map") from None
    out: dict[str, Any] = {"map": mapId, "tolerance_m": tolerance, "border_m": border,
                           "statuses": statuses, **ev.to_dict()}  # fmt: skip
    if errors:
        out["errors"] = {"type": "FeatureCollection",
                         "features": [feature_of(m) for m in ev.error_markings()]}  # fmt: skip
    return JSONResponse(out)

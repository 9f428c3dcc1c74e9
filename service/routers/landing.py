"""Landing page and conformance declaration (OGC API Common / Features Part 1)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from ..deps import require_read
from ._common import JSON, base_url, link

router = APIRouter(tags=["Capabilities"], dependencies=[Depends(require_read)])

# Only what is implemented in full: jobs follow OGC API Processes status words, and
# tiles use the WebMercatorQuad grid, but neither API is offered as a whole.
CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-common-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-common-2/1.0/conf/collections",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/geojson",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/oas30",
    "http://www.opengis.net/spec/ogcapi-features-4/1.0/conf/create-replace-delete",
    "http://www.opengis.net/spec/ogcapi-features-4/1.0/conf/update",
    "http://www.opengis.net/spec/ogcapi-features-4/1.0/conf/optimistic-locking-etags",
    "http://www.opengis.net/spec/ogcapi-features-4/1.0/conf/features",
]


@router.get("/", summary="Landing page")
def landing(request: Request) -> dict:
    base = base_url(request)
    links = [
        link(f"{base}/", "self", JSON, "This document"),
        link(f"{base}/openapi.json", "service-desc", "application/vnd.oai.openapi+json;version=3.0",
             "The API definition"),
        link(f"{base}/docs", "service-doc", "text/html", "The API documentation"),
        link(f"{base}/conformance", "conformance", JSON, "Conformance classes implemented"),
        link(f"{base}/collections", "data", JSON, "The maps"),
        link(f"{base}/jobs", "http://www.opengis.net/def/rel/ogc/1.0/job-list", JSON, "Build jobs"),
        link(f"{base}/localize", "localize", JSON, "Localize a vehicle (POST) on the map where its GPS fix is"),
    ]  # fmt: skip
    if request.app.routes and any(getattr(r, "path", "") == "/editor" for r in request.app.routes):
        links.append(link(f"{base}/editor/", "alternate", "text/html", "The map editor"))
    return {
        "title": "lanemap",
        "description": "Lane-marking maps from aerial imagery, and vehicle localization against them",
        "links": links,
    }


@router.get("/conformance", summary="Conformance classes")
def conformance() -> dict:
    return {"conformsTo": CONFORMANCE}


"""Read queries the API needs beyond the store's: markings inside a WGS84 box.

A lon/lat box becomes a larger box in the storage CRS (its edges are curves
there); the store's grid keys narrow the search to that box and the stored
``lon``/``lat`` columns then keep exactly the markings inside the requested
one, so that ``numberMatched`` and paging agree with what is returned.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import fields

from sqlalchemy import and_, func, select

from mapbuilder.crs import from_wgs84
from mapbuilder.model import Marking
from mapbuilder.schema import GRID_CELL_M, markings
from mapbuilder.store import MapInfo, Store

_FIELDS = [f.name for f in fields(Marking)]


def _where(map_id: str, crs: str, lonlat: tuple[float, float, float, float], statuses: Sequence[str] | None):
    w, s, e, n = lonlat
    minx, miny, maxx, maxy = from_wgs84(crs).transform_bounds(w, s, e, n, densify_pts=21)
    if not all(math.isfinite(v) for v in (minx, miny, maxx, maxy)):
        return None
    c = markings.c
    clause = and_(
        c.map_id == map_id,
        c.gx.between(math.floor(minx / GRID_CELL_M), math.floor(maxx / GRID_CELL_M)),
        c.gy.between(math.floor(miny / GRID_CELL_M), math.floor(maxy / GRID_CELL_M)),
        c.x.between(minx, maxx),
        c.y.between(miny, maxy),
        c.lon.between(w, e),
        c.lat.between(s, n),
    )
    if statuses:
        clause = and_(clause, c.status.in_(list(statuses)))
    return clause


def clip_to_map(info: MapInfo, bbox: tuple[float, float, float, float]):
    """The part of ``bbox`` (lon/lat) over the map's extent, or None when they miss."""
    mb = info.bounds_wgs84()
    if mb is None or info.crs is None:
        return None
    w, s, e, n = max(bbox[0], mb[0]), max(bbox[1], mb[1]), min(bbox[2], mb[2]), min(bbox[3], mb[3])
    if w > e or s > n:
        return None
    return (w, s, e, n)


def markings_in_lonlat_box(
    store: Store, info: MapInfo, bbox: tuple[float, float, float, float],
    statuses: Sequence[str] | None = None, limit: int = 100, offset: int = 0,
) -> tuple[list[Marking], int]:  # fmt: skip
    """A page of the markings whose centroid is inside ``bbox`` (lon/lat, degrees), and their count."""
    clipped = clip_to_map(info, bbox)
    if clipped is None:
        return [], 0
    where = _where(info.id, info.crs, clipped, statuses)
    if where is None:
        return [], 0
    with store.engine.connect() as conn:
        total = conn.execute(select(func.count()).select_from(markings).where(where)).scalar_one()
        rows = conn.execute(
            select(markings).where(where).order_by(markings.c.id).limit(limit).offset(offset)
        ).all()
    out = []
    for r in rows:
        m = Marking(**{k: getattr(r, k) for k in _FIELDS})
        m.extra = dict(m.extra or {})
        out.append(m)
    return out, total

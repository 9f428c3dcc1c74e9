"""A map's localization index, built from its stored markings (API and CLI alike)."""

from __future__ import annotations

import functools

import numpy as np

from localizer import GeoFrame, MapIndex, Options
from mapbuilder.store import MarkingArrays, Store

#: Range of a request's ``min_probability``, the posterior an ``ok`` answer
#: needs: below 0.5 an ``ok`` answer could be likelier wrong than right.
MIN_PROBABILITY_RANGE = (0.5, 0.9999)


@functools.lru_cache(maxsize=64)
def localize_options(min_probability: float | None) -> Options | None:
    """Options of a request that sets its own ``ok`` threshold; None: the localizer's defaults.

    Cached: a fleet sends the same few thresholds, and building options validates every field.
    """
    return None if min_probability is None else Options(ambiguity_probability=min_probability)


def index_from_markings(arrays: MarkingArrays, crs: str, coverage: str = "hull", imaged=None) -> MapIndex:
    """The :class:`localizer.MapIndex` of a map's markings (``Store.marking_arrays``).

    The store keeps bearings clockwise from true north; the index wants grid
    bearings, so the meridian convergence at the map's centre is taken off.
    Kinds the store knows (an imported map's ``solid``, ``dash``, ...) tell
    the index which pieces belong to solid lines; for the others (detections)
    it infers that from their geometry. Detections (``source="detected"``)
    of unknown kind cut short or run long get slack along their axis
    (:func:`localizer.index.length_slack`); imported markings do not.
    ``coverage`` is how far the map speaks for the ground (the map's own, or
    ``LANEMAP_MAP_COVERAGE``, ``mapbuilder.store.MAP_COVERAGES``): ``hull`` and
    ``markings`` are the index's extent rules
    (:func:`localizer.index.map_extent`); ``imagery`` is the ground its builds
    imaged, ``imaged`` (:meth:`Store.imaged_footprint`), joined to the
    ``markings`` rule's.

    Raises
    ------
    localizer.LocalizationInputError
        On values the index cannot use (a bad CRS, non-positive weights).
    """
    extent = {"extent": "markings", "extent_area": imaged} if coverage == "imagery" else {"extent": coverage}
    if not len(arrays):
        return MapIndex.from_arrays(arrays.x, arrays.y, arrays.weight, crs, **extent)
    frame = GeoFrame(crs)
    lon, lat = frame.to_lonlat(float(np.mean(arrays.x)), float(np.mean(arrays.y)))
    return MapIndex.from_arrays(
        arrays.x, arrays.y, arrays.weight, crs,
        bearing_deg=np.asarray(arrays.bearing_deg) - frame.convergence_deg(lon, lat),
        length_m=arrays.length_m, kind=arrays.kind,
        measured=None if arrays.source is None else arrays.source == "detected", **extent,
    )


#: Decimal places of a coverage's WGS84 coordinates: about a centimetre.
COVERAGE_DECIMALS = 7


def coverage_feature(index: MapIndex, map_id: str, coverage: str, revision: int) -> dict:
    """The ground a map speaks for (its index's extent, drawn by ``coverage``) as a GeoJSON Feature in WGS84.

    Its geometry is null for a map without area (fewer than three markings and no imaged ground);
    the properties give the coverage, the map's revision, the area in square metres (in the map's
    CRS) and the margin the markings' ground was grown by, metres.
    """
    import json

    import shapely

    extent = index.extent
    geometry, area = None, 0.0
    if extent is not None:
        frame = index.frame
        lonlat = shapely.transform(extent.area, lambda xy: np.column_stack(frame.to_lonlat(xy[:, 0], xy[:, 1])))
        geometry = json.loads(shapely.to_geojson(shapely.set_precision(lonlat, 10.0 ** -COVERAGE_DECIMALS)))
        area = float(extent.area.area)
    return {"type": "Feature", "id": map_id, "geometry": geometry,
            "properties": {"coverage": coverage, "revision": revision, "area_m2": round(area, 1),
                           "margin_m": extent.margin_m if extent is not None else None}}


def load_index(store: Store, map_id: str, crs: str, coverage: str) -> MapIndex:
    """The index of a stored map's markings by ``coverage`` (:func:`index_from_markings`), read from ``store``."""
    imaged = store.imaged_footprint(map_id) if coverage == "imagery" else None
    return index_from_markings(store.marking_arrays(map_id), crs, coverage, imaged)

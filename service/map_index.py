"""A map's localization index, built from its stored markings (API and CLI alike)."""

from __future__ import annotations

import functools
import logging

import numpy as np

from localizer import GeoFrame, MapIndex, Options
from mapbuilder.store import MarkingArrays, StaleRevisionError, Store

log = logging.getLogger(__name__)

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
    bearings, so the meridian convergence is taken off (:func:`grid_bearings`).
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
        return MapIndex.from_arrays(arrays.x, arrays.y, arrays.weight, crs, **extent, key=arrays.id)
    frame = GeoFrame(crs)
    return MapIndex.from_arrays(
        arrays.x, arrays.y, arrays.weight, crs,
        bearing_deg=grid_bearings(frame, arrays.x, arrays.y, arrays.bearing_deg),
        length_m=arrays.length_m, kind=arrays.kind,
        measured=None if arrays.source is None else arrays.source == "detected", **extent, key=arrays.id,
    )


#: Markings' bearings are turned by the meridian convergence at the centre of
#: their square of this side, metres: 0.005 degrees from their own at most
#: in Karlsruhe (measured at 49 degrees of latitude; the gap grows with the
#: latitude's tangent, so reckoned 0.01 at 57 degrees and 0.04 at 80), and a
#: marking's grid bearing a function of its own place (an index updated with
#: an edit has the bearings of one built anew).
CONVERGENCE_SQUARE_M = 1000.0


def grid_bearings(frame: GeoFrame, x, y, bearing_deg) -> np.ndarray:
    """Bearings clockwise from true north at ``(x, y)`` (map CRS) as clockwise from grid north, degrees.

    The convergence grows with the distance from the projection's central
    meridian: across a city in a UTM zone it changes by about 0.1 degrees.
    """
    sx = np.floor(np.asarray(x, float) / CONVERGENCE_SQUARE_M).astype(np.int64)
    sy = np.floor(np.asarray(y, float) / CONVERGENCE_SQUARE_M).astype(np.int64)
    # one key per square: np.unique by rows takes a second for a city's markings
    _, first, which = np.unique(sx * (1 << 32) + sy, return_index=True, return_inverse=True)
    centre = (np.column_stack([sx[first], sy[first]]) + 0.5) * CONVERGENCE_SQUARE_M
    conv = np.asarray(frame.convergence_deg(*frame.to_lonlat(centre[:, 0], centre[:, 1])), float).reshape(-1)
    return np.asarray(bearing_deg, float) - conv[which.reshape(-1)]


#: The markings a localization index holds: those nobody rejected.
INDEXED_STATUSES = ("unreviewed", "accepted")
#: A map's index is updated with the markings changed since it was built
#: (:func:`updated_index`) while they number at most this share of its
#: markings, or :data:`UPDATE_MIN`; beyond, it is built anew.
UPDATE_SHARE = 0.1
UPDATE_MIN = 2000


def updated_index(store: Store, map_id: str, index: MapIndex, since: int, coverage: str,
                  imaged=None) -> tuple[MapIndex, int, int] | None:  # fmt: skip
    """The map's index ``index``, built at revision ``since``, updated with the markings
    written and removed since (``Store.changes``): ``(index, revision, changes)``, the same as
    :func:`load_index` at that revision (an edit of 200,000 markings in 0.08-0.10 s, against
    2.4-4.8 s for a build; of 1,000,000 in 0.7-1.1 s for a moved marking and 0.01 s for a
    weight or a review's decision, against 18-27 s, on a server's two busy cores). None where
    it must be built anew: an index without keys, more changes
    than :data:`UPDATE_SHARE` of it, a change feed that no longer reaches back to ``since``, or
    (``coverage`` ``imagery``) imaged ground that is not ``imaged`` any more.

    Raises
    ------
    mapbuilder.store.UnknownMapError
        The map was deleted.
    """
    if index.key is None or not len(index):
        return None  # kept by an older version, or an empty map's index, which has no columns to update
    if coverage == "imagery" and not _same_ground(index.extent_area, imaged):
        log.info("map %s: its imaged ground changed since revision %d; its index is built anew", map_id, since)
        return None
    cap = update_cap(len(index))
    if store.count_changes(map_id, since) > cap:  # before reading them: a review's 100,000 decisions
        return _too_many(map_id, cap, since)
    records, after = [], None
    while True:
        try:
            page = store.changes(map_id, since, statuses=INDEXED_STATUSES, after=after, limit=1000)
        except StaleRevisionError:
            log.info("map %s: its change feed no longer reaches back to revision %d; its index is built anew",
                     map_id, since)  # fmt: skip
            return None
        records += [(rev, m.id, m) for rev, m in page.changed] + [(rev, i, None) for rev, i in page.removed]
        if len(records) > cap:  # written since they were counted
            return _too_many(map_id, cap, since)
        if not page.more:
            break
        after = page.after
    last = {i: m for _, i, m in sorted(records, key=lambda r: (r[0], r[1]))}  # each marking as it is now
    written = [m for m in last.values() if m is not None]
    removed = np.array([i for i, m in last.items() if m is None], np.int64)
    cols = np.array([(m.x, m.y, m.weight, m.length_m, m.bearing_deg) for m in written], float).reshape(-1, 5)
    shaped = {} if index.inputs is None or index.inputs.u is None else {
        "bearing_deg": grid_bearings(index.frame, cols[:, 0], cols[:, 1], cols[:, 4]), "length_m": cols[:, 3]}
    updated = index.updated(removed, np.array([m.id for m in written], np.int64), cols[:, 0], cols[:, 1], cols[:, 2],
                            kind=[m.kind for m in written], measured=[m.source == "detected" for m in written],
                            **shaped)  # fmt: skip
    return updated, page.revision, len(last)


def update_cap(size: int) -> int:
    """The most markings changed since an index of ``size`` markings that :func:`updated_index`
    takes on (:data:`UPDATE_SHARE`, :data:`UPDATE_MIN`); more are built anew."""
    return max(UPDATE_MIN, int(UPDATE_SHARE * size))


def _too_many(map_id: str, cap: int, since: int) -> None:
    log.info("map %s: more than %d markings changed since revision %d; its index is built anew", map_id, cap, since)


def _same_ground(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(a.equals(b))


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
    return index_from_markings(store.marking_arrays(map_id, INDEXED_STATUSES), crs, coverage, imaged)

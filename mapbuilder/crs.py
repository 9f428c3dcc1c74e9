"""Coordinate reference systems: choosing a metric storage CRS, grid ↔ true bearings.

Every map is stored in a projected, metric CRS (by default the UTM zone of
the map's centre); the outside world speaks WGS84 lon/lat in GeoJSON order.
All transformers here use ``always_xy=True``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from pyproj import CRS, Proj, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

WGS84 = "EPSG:4326"


class CRSError(ValueError):
    """A CRS is unknown, or not suitable as a metric storage CRS."""


def utm_crs_for(lon: float, lat: float) -> str:
    """Return the WGS84 UTM zone holding a point, as ``"EPSG:326xx"``/``"EPSG:327xx"``.

    Parameters
    ----------
    lon, lat : float
        WGS84 longitude and latitude, degrees.
    """
    if not (-180.0 <= lon <= 180.0 and -80.0 <= lat <= 84.0):
        raise CRSError(f"no UTM zone for lon={lon}, lat={lat}")
    infos = query_utm_crs_info(
        datum_name="WGS 84",
        area_of_interest=AreaOfInterest(lon, lat, lon, lat),
    )
    if not infos:
        raise CRSError(f"no UTM zone for lon={lon}, lat={lat}")
    return f"{infos[0].auth_name}:{infos[0].code}"


@lru_cache(maxsize=64)
def metric_crs(crs: str) -> CRS:
    """Parse ``crs`` and check it is projected with metre units.

    Raises
    ------
    CRSError
        If the CRS cannot be parsed, is geographic, or its unit is not the metre.
    """
    try:
        parsed = CRS.from_user_input(crs)
    except Exception as exc:  # pyproj raises CRSError of its own with long text
        raise CRSError(f"unknown CRS {crs!r}") from exc
    if not parsed.is_projected:
        raise CRSError(f"CRS {crs!r} is not projected; a metric storage CRS is required")
    units = {axis.unit_name for axis in parsed.axis_info}
    if units != {"metre"}:
        raise CRSError(f"CRS {crs!r} has units {sorted(units)}, expected metre")
    return parsed


@lru_cache(maxsize=64)
def to_wgs84(crs: str) -> Transformer:
    """Transformer from ``crs`` to WGS84 lon/lat (``always_xy``)."""
    return Transformer.from_crs(crs, WGS84, always_xy=True)


@lru_cache(maxsize=64)
def from_wgs84(crs: str) -> Transformer:
    """Transformer from WGS84 lon/lat to ``crs`` (``always_xy``)."""
    return Transformer.from_crs(WGS84, crs, always_xy=True)


def meridian_convergence_deg(crs: str, lon, lat) -> np.ndarray:
    """Angle from true north to grid north at the given points, degrees.

    Positive where grid north lies clockwise (east) of true north, which in a
    UTM zone is east of the central meridian on the northern hemisphere
    (Karlsruhe, west of 9°E in UTM 32N: about -0.43°).
    A bearing measured clockwise from grid north converts to true north as
    ``true = grid + convergence``.
    """
    proj = Proj(metric_crs(crs))
    factors = proj.get_factors(np.asarray(lon, float), np.asarray(lat, float))
    # pyproj's sign matches ours; tests/test_crs.py pins it against geometry.
    return np.asarray(factors.meridian_convergence, float)

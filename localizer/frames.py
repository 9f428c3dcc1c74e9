"""Frame conventions: WGS84 ↔ map CRS, true heading ↔ grid yaw ↔ ENU yaw.

Conventions
-----------
* Map coordinates are ``(x, y) = (easting, northing)`` in a projected, metric CRS.
* Vehicle frame (ISO 8855): ``x`` forward, ``y`` left, metres.
* API heading: degrees clockwise from *true* north, in ``[0, 360)``.
* ENU yaw (REP-103): radians counter-clockwise from east, in ``(-pi, pi]``.
* Internally the numerics use the *grid* yaw: radians counter-clockwise from the
  map CRS's +x axis, so that ``map = R(yaw) @ vehicle + t``.

A projected CRS's grid north differs from true north by the meridian
convergence ``c`` (pyproj ``get_factors(...).meridian_convergence``, degrees):
``true_bearing = grid_bearing + c``. In UTM 32N at Karlsruhe ``c ≈ -0.43°``.
"""

from __future__ import annotations

import functools
import math
import threading

import numpy as np
from pyproj import CRS, Proj, Transformer

from .errors import LocalizationInputError

WGS84 = "EPSG:4326"


def wrap_angle(a):
    """Wrap radians to ``(-pi, pi]`` (scalar or array)."""
    w = np.mod(np.asarray(a, float) + math.pi, 2.0 * math.pi) - math.pi
    w = np.where(w == -math.pi, math.pi, w)
    return float(w) if np.ndim(w) == 0 else w


def wrap_deg360(h):
    """Wrap degrees to ``[0, 360)`` (scalar or array)."""
    w = np.mod(np.asarray(h, float), 360.0)
    w = np.where(w >= 360.0, 0.0, w)
    return float(w) if np.ndim(w) == 0 else w


def bearing_to_yaw(bearing_deg):
    """Bearing (degrees clockwise from north) to yaw (radians counter-clockwise from east).

    Works for any pair of matching axes: true bearing ↔ ENU yaw, grid bearing ↔ grid yaw.
    """
    return wrap_angle(math.pi / 2.0 - np.radians(bearing_deg))


def yaw_to_bearing(yaw_rad):
    """Yaw (radians counter-clockwise from east) to bearing (degrees clockwise from north)."""
    return wrap_deg360(90.0 - np.degrees(yaw_rad))


class GeoFrame:
    """Conversions between WGS84 and one projected metric CRS.

    Transformers are created per thread, so one instance can be shared by threads.

    Parameters
    ----------
    crs : str
        Anything pyproj understands (``"EPSG:25832"``...). Must be projected, in metres.

    Raises
    ------
    LocalizationInputError
        If the CRS is unknown, geographic, or not metric.
    """

    def __init__(self, crs: str):
        try:
            parsed = CRS.from_user_input(crs)
        except Exception as exc:  # pyproj's own CRSError carries a long PROJ message
            raise LocalizationInputError(f"crs: unknown CRS {crs!r}") from exc
        if not parsed.is_projected:
            raise LocalizationInputError(f"crs: {crs!r} is not a projected (metric) CRS")
        units = {axis.unit_name for axis in parsed.axis_info}
        if units != {"metre"}:
            raise LocalizationInputError(f"crs: {crs!r} has units {sorted(units)}, expected metre")
        self.crs = str(crs)
        self._parsed = parsed
        self._local = threading.local()

    def __reduce__(self):
        # The per-thread transformers are not picklable; a copy makes its own.
        return (GeoFrame, (self.crs,))

    def _tools(self):
        tools = getattr(self._local, "tools", None)
        if tools is None:
            tools = (
                Transformer.from_crs(WGS84, self._parsed, always_xy=True),
                Transformer.from_crs(self._parsed, WGS84, always_xy=True),
                Proj(self._parsed),
            )
            self._local.tools = tools
        return tools

    def to_xy(self, lon, lat):
        """WGS84 lon/lat (degrees) to map easting/northing (metres)."""
        x, y = self._tools()[0].transform(lon, lat)
        return x, y

    def to_lonlat(self, x, y):
        """Map easting/northing (metres) to WGS84 lon/lat (degrees)."""
        lon, lat = self._tools()[1].transform(x, y)
        return lon, lat

    def convergence_deg(self, lon, lat):
        """Meridian convergence at lon/lat, degrees: ``true_bearing = grid_bearing + c``."""
        if np.ndim(lon) and np.size(lon) == 0:  # PROJ refuses empty arrays
            return np.zeros(0)
        f = self._tools()[2].get_factors(lon, lat)
        c = np.asarray(f.meridian_convergence, float)
        return float(c) if c.ndim == 0 else c

    def heading_to_grid_yaw(self, heading_deg, lon, lat):
        """True heading (degrees clockwise from true north) to grid yaw (radians)."""
        return bearing_to_yaw(np.asarray(heading_deg, float) - self.convergence_deg(lon, lat))

    def grid_yaw_to_heading(self, yaw_rad, lon, lat):
        """Grid yaw (radians) to true heading (degrees clockwise from true north, [0, 360))."""
        return wrap_deg360(yaw_to_bearing(yaw_rad) + self.convergence_deg(lon, lat))


@functools.lru_cache(maxsize=64)
def shared_frame(crs: str) -> GeoFrame:
    """One :class:`GeoFrame` per CRS, shared: building one parses the CRS and takes about 10 ms,
    a hundred times a conversion.

    Raises
    ------
    LocalizationInputError
        As :class:`GeoFrame` (a refused CRS is not cached).
    """
    return GeoFrame(crs)

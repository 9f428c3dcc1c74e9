"""Heading and frame conventions of the localizer, pinned against geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Geod

from localizer import GeoFrame, LocalizationInputError, bearing_to_yaw, wrap_angle, yaw_to_bearing

GEOD = Geod(ellps="WGS84")


def grid_bearing_of_north(frame: GeoFrame, lon: float, lat: float) -> float:
    """Grid bearing (clockwise from grid north) of a short step due true north."""
    x0, y0 = frame.to_xy(lon, lat)
    x1, y1 = frame.to_xy(lon, lat + 0.001)
    return math.degrees(math.atan2(x1 - x0, y1 - y0))


@pytest.mark.parametrize(
    "crs, lon, lat",
    [("EPSG:25832", 8.40, 49.01), ("EPSG:32632", 6.1, 60.0), ("EPSG:32632", 11.5, 47.0),
     ("EPSG:32733", 14.0, -30.0)],
)
def test_convergence_sign_matches_geometry(crs, lon, lat):
    frame = GeoFrame(crs)
    conv = frame.convergence_deg(lon, lat)
    # Walking due (true) north has true bearing 0 = grid bearing + convergence.
    assert conv == pytest.approx(-grid_bearing_of_north(frame, lon, lat), abs=2e-3)


def test_karlsruhe_convergence_is_about_minus_0_43_deg():
    # The Lanelet2 example map lies around 8.435°E, 49.006°N.
    assert GeoFrame("EPSG:25832").convergence_deg(8.435, 49.006) == pytest.approx(-0.43, abs=0.01)


@pytest.mark.parametrize("crs, lon, lat", [("EPSG:25832", 8.40, 49.01), ("EPSG:32632", 6.1, 60.0)])
@pytest.mark.parametrize("grid_yaw", [0.0, 0.7, math.pi / 2, 2.5, -2.0])
def test_grid_yaw_to_true_heading_matches_geodesic_azimuth(crs, lon, lat, grid_yaw):
    frame = GeoFrame(crs)
    x, y = frame.to_xy(lon, lat)
    lon2, lat2 = frame.to_lonlat(x + 50 * math.cos(grid_yaw), y + 50 * math.sin(grid_yaw))
    azimuth, _, _ = GEOD.inv(lon, lat, lon2, lat2)
    heading = frame.grid_yaw_to_heading(grid_yaw, lon, lat)
    assert (heading - azimuth + 180) % 360 - 180 == pytest.approx(0.0, abs=0.01)
    back = frame.heading_to_grid_yaw(heading, lon, lat)
    assert wrap_angle(back - grid_yaw) == pytest.approx(0.0, abs=1e-9)


def test_bearing_yaw_conventions():
    assert bearing_to_yaw(0.0) == pytest.approx(math.pi / 2)  # north = +90° from east
    assert bearing_to_yaw(90.0) == pytest.approx(0.0)  # east
    assert bearing_to_yaw(180.0) == pytest.approx(-math.pi / 2)
    assert yaw_to_bearing(math.pi) == pytest.approx(270.0)  # west
    assert yaw_to_bearing(-1e-12) == pytest.approx(90.0)
    h = np.linspace(0, 359.5, 50)
    assert np.allclose(yaw_to_bearing(bearing_to_yaw(h)), h)
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi)


@pytest.mark.parametrize("crs", ["EPSG:4326", "not a crs", "EPSG:2263"])
def test_bad_crs_is_rejected(crs):
    # geographic, unparseable, US survey feet
    with pytest.raises(LocalizationInputError, match="crs"):
        GeoFrame(crs)


def test_frame_round_trip():
    frame = GeoFrame("EPSG:25832")
    lon, lat = frame.to_lonlat(*frame.to_xy(8.4, 49.0))
    assert (lon, lat) == pytest.approx((8.4, 49.0), abs=1e-9)

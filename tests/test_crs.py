"""CRS helpers: the sign of the meridian convergence is pinned against geometry."""

from __future__ import annotations

import math

import pytest

from mapbuilder.crs import CRSError, from_wgs84, meridian_convergence_deg, metric_crs, utm_crs_for


def _grid_bearing_of_true_north(crs: str, lon: float, lat: float) -> float:
    t = from_wgs84(crs)
    x0, y0 = t.transform(lon, lat)
    x1, y1 = t.transform(lon, lat + 1e-4)  # a step north along the meridian
    return math.degrees(math.atan2(x1 - x0, y1 - y0))


@pytest.mark.parametrize(
    "crs, lon, lat",
    [
        ("EPSG:25832", 8.43, 49.0),  # Karlsruhe, west of 9°E
        ("EPSG:25832", 11.5, 48.1),  # Munich, east of 9°E
        ("EPSG:32613", -104.8, 38.8),  # Colorado Springs
        ("EPSG:32760", 178.0, -40.0),  # southern hemisphere
    ],
)
def test_convergence_turns_grid_bearings_into_true_bearings(crs, lon, lat):
    conv = float(meridian_convergence_deg(crs, lon, lat))
    # True north has grid bearing g; its true bearing is 0 = g + convergence.
    assert _grid_bearing_of_true_north(crs, lon, lat) + conv == pytest.approx(0.0, abs=1e-3)


def test_karlsruhe_convergence_value():
    assert float(meridian_convergence_deg("EPSG:25832", 8.43, 49.0)) == pytest.approx(-0.43, abs=0.01)


def test_utm_zone_choice():
    assert utm_crs_for(8.43, 49.0) == "EPSG:32632"
    assert utm_crs_for(-104.8, 38.8) == "EPSG:32613"
    assert utm_crs_for(151.2, -33.9) == "EPSG:32756"
    with pytest.raises(CRSError):
        utm_crs_for(0.0, 89.0)


def test_metric_crs_rejects_geographic_and_foot_units():
    assert metric_crs("EPSG:25832").is_projected
    with pytest.raises(CRSError, match="not projected"):
        metric_crs("EPSG:4326")
    with pytest.raises(CRSError, match="expected metre"):
        metric_crs("EPSG:2263")  # NY Long Island, US survey feet
    with pytest.raises(CRSError, match="unknown CRS"):
        metric_crs("EPSG:999999")

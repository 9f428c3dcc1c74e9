"""Laying out the real Karlsruhe Lanelet2 map as markings."""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest

from mapbuilder.crs import meridian_convergence_deg, to_wgs84
from mapbuilder.lanelet2 import Lanelet2Error, layout_markings, read_lanelet2

from .conftest import KARLSRUHE_OSM


@pytest.fixture(scope="module")
def lmap():
    return read_lanelet2(KARLSRUHE_OSM, crs="EPSG:25832")


def test_reads_the_map_in_utm(lmap):
    types = collections.Counter(line.type for line in lmap.lines)
    assert types["stop_line"] == 28 and types["curbstone"] == 325
    xy = np.vstack([line.xy for line in lmap.lines])
    assert 456000 < xy[:, 0].min() < xy[:, 0].max() < 461500  # ~3.4 km wide
    assert 5427000 < xy[:, 1].min() < xy[:, 1].max() < 5429500
    assert len(lmap.centerlines) >= 300


def test_dashes_follow_the_pattern(lmap, karlsruhe_markings):
    dashes = [m for m in karlsruhe_markings if m.kind == "dash"]
    full = [m for m in dashes if abs(m.length_m - 3.0) < 1e-6]
    assert len(full) > 0.8 * len(dashes)
    dashed = [ln for ln in lmap.lines if ln.type in ("line_thin", "line_thick") and ln.subtype == "dashed"]
    expected = sum(math.floor(ln.length_m / 9.0) for ln in dashed)
    assert expected <= len(dashes) <= expected + len(dashed)
    # consecutive dashes on one line are 9 m apart (3 m dash + 6 m gap)
    line = max(dashed, key=lambda ln: ln.length_m)
    mine = [m for m in layout_markings(type(lmap)(lmap.crs, [line])) if abs(m.length_m - 3.0) < 1e-6]
    gaps = np.hypot(np.diff([m.x for m in mine]), np.diff([m.y for m in mine]))
    straight = gaps[gaps > 8.5]
    assert np.median(straight) == pytest.approx(9.0, abs=0.05)


def test_solid_pieces_and_stop_lines(karlsruhe_markings):
    kinds = collections.Counter(m.kind for m in karlsruhe_markings)
    assert kinds["stop_line"] == 28
    solid = [m for m in karlsruhe_markings if m.kind == "solid"]
    assert max(m.length_m for m in solid) <= 3.0 + 1e-6
    assert {m.width_m for m in karlsruhe_markings} <= {0.12, 0.25, 0.5}
    assert all(0 <= m.bearing_deg < 180 and m.weight > 0 for m in karlsruhe_markings)


def test_bearings_are_true_north(karlsruhe_markings):
    m = next(m for m in karlsruhe_markings if m.kind == "dash" and abs(m.length_m - 3.0) < 1e-6)
    grid = math.degrees(math.atan2(m.x1 - m.x0, m.y1 - m.y0)) % 180.0
    # Karlsruhe lies west of UTM 32N's central meridian: convergence about -0.43°.
    lon, lat = to_wgs84("EPSG:25832").transform(m.x, m.y)
    conv = float(meridian_convergence_deg("EPSG:25832", lon, lat))
    assert -0.47 < conv < -0.39
    assert (m.bearing_deg - grid + 90) % 180 - 90 == pytest.approx(conv, abs=1e-6)


def test_unreadable_file(tmp_path):
    bad = tmp_path / "bad.osm"
    bad.write_text("<osm><node id='1'")
    with pytest.raises(Lanelet2Error, match="cannot read Lanelet2 map"):
        read_lanelet2(bad)

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


def test_the_dash_pattern_runs_on_across_split_line_strings():
    from mapbuilder.lanelet2 import LaneletMap, Line, dashed_chains

    # One painted line split into three line strings (10.5 m, 7 m, 20 m; the
    # middle one drawn the other way round), and a fourth string turning off
    # at a right angle where the last ends.
    a = np.array([[0.0, 0.0], [10.5, 0.0]])
    b = np.array([[17.5, 0.0], [10.5, 0.0]])
    c = np.array([[17.5, 0.0], [37.5, 0.0]])
    d = np.array([[37.5, 0.0], [37.5, 12.0]])
    lines = [Line(i, "line_thin", "dashed", xy) for i, xy in enumerate((c, a, d, b))]
    chains = dashed_chains(lines)
    assert sorted(round(float(np.sum(np.hypot(*np.diff(xy, axis=0).T))), 6) for _, xy in chains) == [12.0, 37.5]
    dashes = sorted((m for m in layout_markings(LaneletMap("EPSG:25832", lines)) if m.y < 1e-9),
                    key=lambda m: m.x)
    # 0-3, 9-12, 18-21, 27-30, 36-37.5: every 9 m, never restarting at 10.5 or 17.5 m.
    assert [round(m.x0 if m.x0 < m.x1 else m.x1, 6) for m in dashes] == [0.0, 9.0, 18.0, 27.0, 36.0]
    assert [round(m.length_m, 6) for m in dashes] == [3.0, 3.0, 3.0, 3.0, 1.5]
    # Laid out string by string, the pattern would have restarted at 10.5 m:
    # a dash there, 1.5 m after the one at 9-10.5 m.
    assert not any(abs(m.x - 12.0) < 1e-6 for m in dashes)


def test_dashes_of_the_karlsruhe_map_do_not_touch_along_a_line(karlsruhe_markings):
    dashes = [m for m in karlsruhe_markings if m.kind == "dash"]
    ends = np.array([[m.x0, m.y0, m.x1, m.y1] for m in dashes])
    u = np.array([[math.sin(math.radians(m.bearing_deg)), math.cos(math.radians(m.bearing_deg))] for m in dashes])
    from scipy.spatial import cKDTree

    n = len(dashes)
    tree = cKDTree(np.r_[ends[:, :2], ends[:, 2:]])
    collinear_touching = [(i % n, j % n) for i, j in tree.query_pairs(1.0)
                          if i % n != j % n and abs(float(u[i % n] @ u[j % n])) > math.cos(math.radians(10.0))]
    # Laid out string by string there were 21 such pairs (of 388 dashes); what
    # is left are dashes of different lines meeting in junctions.
    assert len(collinear_touching) <= 6


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

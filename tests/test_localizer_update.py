"""An index updated with the markings that changed is the index built anew from the map as it is."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from localizer import LocalizationInputError, MapIndex
from localizer.index import EXTENT_SQUARE_M, _triangles_area, map_extent

from ._localizer_helpers import CRS, KarlsruheMarkings


def _map(kinds: bool):
    """The Karlsruhe markings and a copy of them 1.5 km east (squares of the extent far from
    any edit): columns as the service reads them, keys with gaps."""
    m = KarlsruheMarkings()
    n = len(m.xy)
    cols = {
        "x": np.concatenate([m.xy[:, 0], m.xy[:, 0] + 1500.0]),
        "y": np.concatenate([m.xy[:, 1], m.xy[:, 1]]),
        "weight": np.concatenate([m.weight, m.weight]).astype(float),
        "bearing_deg": np.concatenate([m.bearing_true, m.bearing_true]),
        "length_m": np.concatenate([m.length, m.length]),
        "kind": np.concatenate([m.kind, m.kind]) if kinds else np.full(2 * n, None, object),
        "measured": np.full(2 * n, not kinds),
    }
    cols["key"] = np.arange(2 * n, dtype=np.int64) * 3 + 10
    return cols


def _build(cols, extent):
    return MapIndex.from_arrays(cols["x"], cols["y"], cols["weight"], CRS, kind=cols["kind"],
                                bearing_deg=cols["bearing_deg"], length_m=cols["length_m"],
                                measured=cols["measured"], extent=extent, key=cols["key"])  # fmt: skip


def _edit(cols, rng, new_key):
    """Some markings removed, moved (solid pieces among them), reweighted, of another kind, and
    some added: the columns after, and the update (removed keys, written rows)."""
    n = len(cols["key"])
    pick = rng.permutation(n // 2)  # edits where the vehicle is: the Karlsruhe half
    removed, moved, weighted, kinded = pick[:30], pick[30:50], pick[50:70], pick[70:80]
    solid = np.flatnonzero(np.array([k == "solid" for k in cols["kind"]]) | (cols["length_m"] > 2.5))
    moved = np.union1d(moved, rng.choice(solid[solid < n // 2], 10, replace=False))
    moved = np.setdiff1d(moved, removed)
    after = {k: v.copy() for k, v in cols.items()}
    after["x"][moved] += rng.normal(0.0, 2.0, moved.size)
    after["y"][moved] += rng.normal(0.0, 2.0, moved.size)
    after["weight"][weighted] += 7.0
    after["kind"][kinded] = np.where(after["kind"][kinded] == "solid", "dash", None)
    added = rng.choice(n // 2, 25, replace=False)
    extra = {k: v[added].copy() for k, v in cols.items()}
    extra["x"] += rng.uniform(-40.0, 40.0, 25)
    extra["y"] += rng.uniform(-40.0, 40.0, 25)
    extra["key"] = np.arange(new_key, new_key + 25, dtype=np.int64)
    written = np.union1d(np.union1d(moved, weighted), kinded)
    written = np.setdiff1d(written, removed)
    rows = {k: np.concatenate([after[k][written], extra[k]]) for k in cols}
    keep = np.ones(n, bool)
    keep[removed] = False
    after = {k: np.concatenate([after[k][keep], extra[k]]) for k in cols}
    gone = np.concatenate([cols["key"][removed], [999_999_999]])  # a key the map never held
    return after, gone, rows


def _update(index, gone, rows):
    return index.updated(gone, rows["key"], rows["x"], rows["y"], rows["weight"], kind=rows["kind"],
                         bearing_deg=rows["bearing_deg"], length_m=rows["length_m"], measured=rows["measured"])


def _assert_same(a: MapIndex, b: MapIndex, probes: np.ndarray) -> None:
    np.testing.assert_array_equal(a.key, b.key)
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_array_equal(a.weight, b.weight)
    np.testing.assert_array_equal(a.axis, b.axis)
    np.testing.assert_array_equal(a.half_length, b.half_length)
    np.testing.assert_array_equal(a.expect_xy, b.expect_xy)
    np.testing.assert_array_equal(a.expect_owner, b.expect_owner)
    np.testing.assert_array_equal(a.expect_solid, b.expect_solid)
    np.testing.assert_array_equal(a.tree.query(probes)[1], b.tree.query(probes)[1])
    ea, eb = a.extent, b.extent
    np.testing.assert_array_equal(ea.squares, eb.squares)
    assert len(ea.pieces) == len(eb.pieces) and all(p.equals_exact(q, 0.0) for p, q in zip(ea.pieces, eb.pieces))
    np.testing.assert_array_equal(ea.beyond(probes[:, 0], probes[:, 1]), eb.beyond(probes[:, 0], probes[:, 1]))


@pytest.mark.parametrize("kinds", [True, False], ids=["imported", "detected"])
@pytest.mark.parametrize("extent", ["hull", "markings"])
def test_an_updated_index_is_the_index_built_anew(kinds, extent):
    """Two rounds of edits on the real Karlsruhe geometry: every array, the KD-tree's answers
    and the extent (square by square, and at 20,000 points) are those of an index built from
    the markings as they are. Detected markings (no kinds, measured) have their solid lines
    inferred and their lengths' slack set from their neighbours, both redone near the edits."""
    rng = np.random.default_rng(5)
    cols = _map(kinds)
    index = _build(cols, extent)
    _ = index.extent  # drawn: the update redraws it where markings moved
    lo, hi = cols["x"].min() - 50, cols["x"].max() + 50
    probes = np.column_stack([rng.uniform(lo, hi, 20_000), rng.uniform(cols["y"].min() - 50, cols["y"].max() + 50,
                                                                     20_000)])  # fmt: skip
    new_key = int(cols["key"].max()) + 1
    for _round in range(2):
        cols, gone, rows = _edit(cols, rng, new_key)
        new_key += 100
        updated = _update(index, gone, rows)
        anew = _build(cols, extent)
        _assert_same(updated, anew, probes)
        assert not updated.xy.flags.writeable and not updated.key.flags.writeable
        index = updated
    if extent == "markings":
        assert len(index.extent.squares) >= 4  # the far copy's squares were kept as they were
    if not kinds:
        assert (index.half_length > 0).any() and (index.inputs.line != ~np.asarray(
            [k is None for k in cols["kind"]])).any()  # fmt: skip


def test_an_update_that_moves_nothing_keeps_the_extent_and_one_not_drawn_stays_undrawn():
    cols = _map(True)
    index = _build(cols, "markings")
    drawn = index.extent
    rows = {k: v[:5].copy() for k, v in cols.items()}
    rows["weight"] = rows["weight"] + 1.0
    again = _update(index, [], rows)
    assert again.extent is drawn and again.weight[0] == cols["weight"][0] + 1.0
    fresh = _build(cols, "markings")
    later = _update(fresh, cols["key"][:3], {k: v[:0] for k, v in cols.items()})
    assert "extent" not in later.__dict__ and len(later) == len(cols["key"]) - 3
    removals = fresh.updated(cols["key"][:3].tolist(), [], [], [], [], kind=[], bearing_deg=[], length_m=[],
                             measured=[])  # plain lists, none written  # fmt: skip
    np.testing.assert_array_equal(removals.key, later.key)
    assert later.extent.squares.shape[0] >= 1


@pytest.mark.parametrize("kinds", [True, False], ids=["imported", "detected"])
def test_an_update_of_weights_alone_shares_all_but_the_weights(kinds):
    """A review's decisions and corrected weights leave the markings' places, kinds and lengths as
    they were: the updated index is still the one built anew, but it keeps the index's own
    arrays, KD-tree and extent, and an update that changes nothing keeps its weights too. A
    marking moved, lengthened, measured otherwise or made a piece of a solid line is no such
    update."""
    rng = np.random.default_rng(8)
    cols = _map(kinds)
    index = _build(cols, "markings")
    drawn = index.extent
    probes = np.column_stack([rng.uniform(cols["x"].min(), cols["x"].max(), 5_000),
                              rng.uniform(cols["y"].min(), cols["y"].max(), 5_000)])  # fmt: skip
    pick = np.sort(rng.choice(len(cols["key"]), 40, replace=False))
    rows = {k: v[pick].copy() for k, v in cols.items()}
    rows["weight"] = rows["weight"] * 2.0 + 1.0
    after = {k: v.copy() for k, v in cols.items()}
    after["weight"][pick] = rows["weight"]
    updated = _update(index, [999_999_999], rows)
    _assert_same(updated, _build(after, "markings"), probes)
    assert updated.tree is index.tree and updated.expect_xy is index.expect_xy and updated.extent is drawn
    assert index.weight[pick[0]] == cols["weight"][pick[0]]  # the index it was updated from is as it was
    unchanged = {k: v[pick].copy() for k, v in after.items()}
    same = _update(updated, [], unchanged)
    assert same.weight is updated.weight and same.tree is index.tree
    one = next(i for i in pick if after["kind"][i] != "solid" and after["length_m"][i] > 0.5)
    for column, value in (("measured", kinds), ("kind", "solid"), ("x", after["x"][one] + 0.3),
                          ("length_m", after["length_m"][one] + 1.0)):
        rows = {k: v[[one]].copy() for k, v in after.items()}
        rows[column] = np.array([value], after[column].dtype)
        other = {k: v.copy() for k, v in after.items()}
        other[column][one] = value
        changed = _update(updated, [], rows)
        assert changed.expect_xy is not index.expect_xy  # the whole update
        _assert_same(changed, _build(other, "markings"), probes)


def test_a_square_is_drawn_from_its_halo_alone():
    """Markings beyond a square's halo do not change its piece: the squares an edit does not reach
    keep what they had, and a map of separate parts is drawn part by part."""
    rng = np.random.default_rng(2)
    road = np.column_stack([np.arange(0.0, 900.0, 3.0), np.zeros(300)]) + [457_100.0, 5_428_500.0]
    road = np.concatenate([road, road + [0.0, 3.5]]) + rng.normal(0.0, 0.05, (600, 2))
    far = road + [0.0, 2.5 * EXTENT_SQUARE_M]
    alone, both = map_extent(road, "markings"), map_extent(np.concatenate([road, far]), "markings")
    pieces = {tuple(sq): p for sq, p in zip(both.squares.tolist(), both.pieces)}
    assert len(pieces) > len(alone.squares)
    assert all(pieces[tuple(sq)].equals_exact(p, 0.0) for sq, p in zip(alone.squares.tolist(), alone.pieces))
    assert not both.beyond(far[:, 0], far[:, 1]).any() and alone.beyond(far[:, 0], far[:, 1]).all()
    # markings on one line (surveyed dashes of one line) are their own ground, a metre around each
    dashes = np.column_stack([np.arange(0.0, 900.0, 3.0), np.zeros(300)]) + [457_100.0, 5_428_500.0]
    line = map_extent(dashes, "markings")
    assert not line.beyond(dashes[:, 0], dashes[:, 1] + 0.9).any()
    assert line.beyond(dashes[:, 0], dashes[:, 1] + 1.1).all()
    assert shapely.get_num_geometries(line.area) == 300


def test_the_area_of_triangles_drawn_from_their_outline_is_their_union(monkeypatch):
    """The short triangles of a triangulation, drawn from the edges of one triangle only: the
    union of the triangles as polygons, holes and parts touching at a corner included, on the
    Karlsruhe markings and on random points; degenerate (flat) triangles are joined as polygons."""
    from scipy.spatial import Delaunay

    from localizer import index

    joins, union_all = [], shapely.union_all
    monkeypatch.setattr(index.shapely, "union_all", lambda *a, **k: joins.append(1) or union_all(*a, **k))
    rng = np.random.default_rng(3)
    ka = KarlsruheMarkings().xy
    holes = 0
    for pts, link in ((ka, 30.0), (ka, 8.0), (rng.uniform(0.0, 100.0, (400, 2)), 9.0)):
        tri = Delaunay(pts)
        corners = pts[tri.simplices]
        short = (np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2) <= link).all(axis=1)
        drawn = _triangles_area(pts, tri.simplices[short])
        joined = union_all(shapely.polygons(corners[short]))
        assert drawn.is_valid and abs(drawn.area - joined.area) < 1e-6 * joined.area
        assert drawn.symmetric_difference(joined).area < 1e-6 * joined.area
        assert shapely.get_num_geometries(drawn) == shapely.get_num_geometries(joined)
        holes += shapely.get_num_interior_rings(shapely.get_parts(drawn)).sum()
        assert shapely.get_num_interior_rings(shapely.get_parts(joined)).sum() == \
            shapely.get_num_interior_rings(shapely.get_parts(drawn)).sum()  # fmt: skip
    assert holes > 0  # the case is exercised
    assert not joins  # drawn from the outlines, not joined as polygons
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [2.0, 2.0], [2.0, 1.0], [1.0, 2.0]])
    pinched = _triangles_area(square, np.array([[0, 1, 2], [0, 2, 3], [2, 5, 4], [2, 4, 6]]))
    assert pinched.area == pytest.approx(2.0) and shapely.get_num_geometries(pinched) == 2
    flat = _triangles_area(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [1.0, 1.0]]),
                           np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3]]))  # fmt: skip
    assert flat.area == pytest.approx(1.0) and joins


def test_updates_are_refused_where_they_cannot_be_right():
    cols = _map(True)
    plain = MapIndex.from_arrays(cols["x"], cols["y"])
    with pytest.raises(LocalizationInputError, match="without keys"):
        plain.updated([], [1], [0.0], [0.0])
    with pytest.raises(LocalizationInputError, match="ascending"):
        MapIndex.from_arrays(cols["x"][:3], cols["y"][:3], key=[3, 2, 5])
    index = _build(cols, "hull")
    rows = {k: np.concatenate([v[:2], v[:1]]) for k, v in cols.items()}
    with pytest.raises(LocalizationInputError, match="unique"):
        _update(index, [], rows)
    with pytest.raises(LocalizationInputError, match="if and only if"):
        index.updated([], cols["key"][:1], cols["x"][:1], cols["y"][:1])
    with pytest.raises(LocalizationInputError, match="NaN"):
        index.updated([], cols["key"][:1], [np.nan], cols["y"][:1], bearing_deg=[0.0], length_m=[1.0])

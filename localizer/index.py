"""A map's spatial index, built once and shared by requests (and threads)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import shapely
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from .errors import LocalizationInputError
from .frames import GeoFrame


def _column(name: str, values, n: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise LocalizationInputError(f"{name}: not an array of numbers") from exc
    if n is not None and arr.size != n:
        raise LocalizationInputError(f"{name}: {arr.size} values, expected {n}")
    if not np.all(np.isfinite(arr)):
        raise LocalizationInputError(f"{name}: contains NaN or infinite values")
    return arr


def _continuous_pieces(xy: np.ndarray, u: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Interior pieces of continuous lines: both ends meet another marking's end.

    Ends must lie within 0.6 m with directions within 20°. A dash that merely
    continues a solid line touches it at one end only and stays point-like.
    """
    n = len(xy)
    if n < 2:
        return np.zeros(n, bool)
    ends = np.concatenate([xy + 0.5 * length[:, None] * u, xy - 0.5 * length[:, None] * u])
    owner = np.concatenate([np.arange(n), np.arange(n)])
    touched = np.zeros(2 * n, bool)
    pairs = cKDTree(ends).query_pairs(0.6, output_type="ndarray")
    i, j = owner[pairs[:, 0]], owner[pairs[:, 1]]
    meet = (i != j) & (np.abs(np.einsum("kd,kd->k", u[i], u[j])) > math.cos(math.radians(20.0)))
    touched[pairs[meet].ravel()] = True
    return touched[:n] & touched[n:]


#: A detection of unknown kind is compared with the detections around it: those
#: of unknown kind in the same ``TYPICAL_CELL_M`` square of the map grid (fewer
#: than ``TYPICAL_MIN`` there: all of the map's). Longer ones than
#: ``MAX_DASH_LENGTH_M`` (stop lines, uncut lines) are not compared.
TYPICAL_CELL_M = 40.0
TYPICAL_MIN = 6
MAX_DASH_LENGTH_M = 8.0
#: A detection whose length departs from the typical one by more than this
#: share of it (plus 0.1 m) gets slack along its axis.
LENGTH_TOLERANCE = 0.15


def length_slack(xy: np.ndarray, length: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """Slack along the axis of detections cut short or run long, metres (0 for the others).

    A dash that a tree's crown or a car hides in part, or that a shadow
    breaks, is detected short; one that touches another marking, long. Its
    centroid then lies anywhere within ``|length - typical| / 2`` of the
    painted dash's along the axis, where ``typical`` is the median length of
    the detections around it (:data:`TYPICAL_CELL_M`): a vehicle's camera
    sees the whole dash, so where along that stretch it matches is unknown.
    On the map built from the Karlsruhe renders 23 of 264 dash detections were
    0.25-1.5 m off (fragments under trees and cars, dashes run into crossing
    ones or stop lines); the slack raised success from near starts on that
    map from 82.8 to 85.5 % (``benchmarks/localize_detected.py``, seeds 3 and
    7). Only measured markings get it: on exact geometry it costs information.

    Parameters
    ----------
    xy : (M, 2) ndarray
        Centroids, metres.
    length : (M,) ndarray
        Lengths along the major axis, metres.
    candidate : (M,) bool ndarray
        Detections that may be dashes (unknown kind, not pieces of lines, with
        a length, at most :data:`MAX_DASH_LENGTH_M`); only these are compared
        and changed.

    Returns
    -------
    (M,) ndarray
        ``|length - typical|`` where it exceeds ``LENGTH_TOLERANCE * typical
        + 0.1``, else 0.
    """
    slack = np.zeros(len(xy))
    idx = np.flatnonzero(candidate)
    if idx.size < TYPICAL_MIN + 1:
        return slack
    lens = length[idx]
    # The median length per grid cell: sorted by cell, then by length, by one flat key each:
    # np.lexsort held the interpreter for a second at 1,000,000 markings.
    cell_xy = np.floor(xy[idx] / TYPICAL_CELL_M).astype(np.int64)
    _, cell = np.unique(_cell_keys(cell_xy), return_inverse=True)
    cell = cell.reshape(-1)
    order = np.argsort(cell * (float(lens.max()) + 1.0) + lens, kind="stable")
    count = np.bincount(cell)
    first = np.cumsum(count) - count
    med = 0.5 * (lens[order][first + (count - 1) // 2] + lens[order][first + count // 2])
    typical = np.where(count >= TYPICAL_MIN, med, float(np.median(lens)))[cell]
    off = np.abs(lens - typical)
    slack[idx] = np.where(off > LENGTH_TOLERANCE * typical + 0.1, off, 0.0)
    return slack


#: Spacing of the expected observations along a solid line, metres.
SOLID_SAMPLE_M = 3.0


def _marking_tree(xy: np.ndarray) -> cKDTree:
    """The KD-tree over a map's markings ``xy`` (M, 2), metres.

    Cells split at their middle, not at the median: built in 0.08 s for
    1,000,000 markings of a street grid instead of 0.24 s, and answering the
    localizer's nearest-neighbour and radius queries as fast (2026-12-07).
    A marking that comes, goes or moves rebuilds it (:meth:`MapIndex.updated`).
    """
    return cKDTree(xy if len(xy) else np.zeros((0, 2)), balanced_tree=False, compact_nodes=False)


def expected_points(xy: np.ndarray, axis: np.ndarray, half: np.ndarray):
    """Points where a camera should report a centroid: ``(points, owner, on_line)``.

    Point-like markings are their centroid; a line-like marking of length
    ``L`` gives ``max(1, round(L / SOLID_SAMPLE_M))`` evenly spaced points.
    """
    point = half == 0
    line = np.flatnonzero(~point)
    n = np.maximum(1, np.round(2 * half[line] / SOLID_SAMPLE_M).astype(np.intp))
    own = np.repeat(line, n)
    k = np.arange(own.size) - np.repeat(np.cumsum(n) - n, n)  # index of the point on its marking
    a = (k + 0.5) / np.repeat(n, n) * 2 * half[own] - half[own]
    pts = np.concatenate([xy[point], xy[own] + a[:, None] * axis[own]]).reshape(-1, 2)
    owner = np.concatenate([np.flatnonzero(point), own]).astype(np.intp)
    solid = np.concatenate([np.zeros(int(point.sum()), bool), np.ones(own.size, bool)])
    return pts, owner, solid


@dataclass(frozen=True, eq=False)
class MapIndex:
    """Marking centroids of one map with a KD-tree over them.

    Build it with :meth:`from_arrays`. It is immutable: share one instance
    between requests and threads (KD-tree queries are read-only, and the
    coordinate transformers of :class:`GeoFrame` are per thread).

    Attributes
    ----------
    xy : (M, 2) ndarray
        Marking centroids in the map CRS, metres.
    weight : (M,) ndarray
        Marking weights (pixel counts); informative only.
    axis : (M, 2) ndarray
        Unit direction of line-like markings (solid-line pieces), zero otherwise.
    half_length : (M,) ndarray
        Half length of line-like markings, metres; 0 for point-like markings.
        For a detection cut short or run long, half its slack along its axis
        (:func:`length_slack`).
    tree : scipy.spatial.cKDTree
        Over ``xy``.
    frame : GeoFrame
        WGS84 ↔ map CRS conversions.
    expect_xy : (E, 2) ndarray
        Where a camera is expected to report a centroid: point-like markings,
        and points every :data:`SOLID_SAMPLE_M` along line-like ones (a camera
        cuts a solid line into clusters of a few metres). Used for negative
        evidence (what a pose predicts in view but nobody saw); precomputed
        once per map.
    expect_owner : (E,) ndarray
        Marking index of each expected point.
    expect_solid : (E,) ndarray of bool
        The expected point lies on a line-like marking.
    extent_rule : str
        How the map's extent (:attr:`extent`, beyond which it says nothing)
        is drawn from its markings: ``"hull"`` or ``"markings"``
        (:func:`map_extent`).
    extent_area : shapely geometry or None
        Ground known from elsewhere to hold every marking painted on it (the
        footprint of the imagery the map was built from), map CRS; the extent
        is the union of it and the rule's.
    key : (M,) int64 ndarray or None
        The caller's identifiers of the markings (a store's ids), ascending;
        an index with keys can be updated with the markings that changed
        (:meth:`updated`) instead of being built anew.
    """

    xy: np.ndarray
    weight: np.ndarray
    axis: np.ndarray
    half_length: np.ndarray
    tree: cKDTree
    frame: GeoFrame
    expect_xy: np.ndarray | None = None
    expect_owner: np.ndarray | None = None
    expect_solid: np.ndarray | None = None
    extent_rule: str = "hull"
    extent_area: shapely.Geometry | None = None
    key: np.ndarray | None = None
    inputs: "_Inputs | None" = field(default=None, repr=False)

    def __setstate__(self, state: dict) -> None:
        # A copy (pickle: an index kept in a file) is as read-only as the index it copies.
        self.__dict__.update(state)
        for name in ("xy", "weight", "axis", "half_length", "expect_xy", "expect_owner", "expect_solid", "key"):
            arr = state.get(name)
            if isinstance(arr, np.ndarray):
                arr.setflags(write=False)

    @property
    def crs(self) -> str:
        return self.frame.crs

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def max_half_length(self) -> float:
        return float(self.half_length.max()) if len(self) else 0.0

    @classmethod
    def from_arrays(
        cls,
        x,
        y,
        weight=None,
        crs: str = "EPSG:25832",
        *,
        kind=None,
        bearing_deg=None,
        length_m=None,
        measured=None,
        extent: str = "hull",
        extent_area: shapely.Geometry | None = None,
        key=None,
    ) -> "MapIndex":
        """Build the index of a map.

        Parameters
        ----------
        x, y : array_like, shape (M,)
            Marking centroids in ``crs`` (easting, northing), metres.
        weight : array_like, shape (M,), optional
            Pixel counts γ of the markings (default 1).
        crs : str
            The map's projected, metric CRS.
        bearing_deg, length_m : array_like, shape (M,), optional
            Direction of each marking's major axis (degrees clockwise from north)
            and its length (metres). With them, pieces of continuous (solid) lines
            become segments: a camera clusters a solid line at its own phase, so
            only the distance across the line is informative. The paper's method
            always uses centroids.
        kind : array_like of str or None, shape (M,), optional
            What each marking is, where known (an imported map knows; a
            detection does not): ``"solid"`` marks the pieces of solid lines,
            any other kind (``"dash"``, ``"stop_line"``, ...) a point-like
            marking (compared without case and surrounding blanks). A piece of
            unknown kind (None or blank, or no ``kind`` at all) is taken as
            part of a continuous line when both its ends meet the ends of
            other markings of about the same direction (within 0.6 m, 20°). That leaves the two end pieces of every line
            point-like, as a dash continuing a line would be (a camera's
            cluster anywhere along such a piece then pulls the pose along the
            line), so give the kinds where they are known. A point-like
            marking of unknown kind whose length departs from that of the
            detections around it (a dash cut short by a tree, or run into
            another marking) becomes a segment as long as the difference
            (:func:`length_slack`): its painted dash's centroid lies somewhere
            along it. Only markings marked ``measured`` get such slack.
        measured : array_like of bool, shape (M,), optional
            Markings whose geometry was measured from imagery (detections),
            which may be cut short or run long; default none (exact geometry,
            e.g. a surveyed map without kinds).
        extent : {"hull", "markings"}
            How far the map speaks for the ground (:func:`map_extent`):
            ``"hull"`` for a map that holds every marking painted within its
            markings' convex hull, ``"markings"`` for a map whose world goes
            on past it inside that hull (a route, separate parts of a city).
            The default method's check at a map's edge
            (``Options.edge_share``) reads it.
        extent_area : shapely geometry, optional
            Ground, in ``crs``, known to hold every marking painted on it
            whether or not the markings show it: the footprint of the imagery
            a map was built from. The extent is its union with the rule's
            (with ``"markings"``: every marking placed beyond the imagery by
            hand or by an import adds its own ground).
        key : array_like of int, shape (M,), optional
            The markings' identifiers (a store's ids), strictly ascending: an
            index with keys can be updated with the markings that change
            (:meth:`updated`).

        Raises
        ------
        LocalizationInputError
            On NaN/inf, mismatched lengths, non-positive weights, keys not
            strictly ascending or a bad CRS.
        """
        _check_extent_rule(extent)  # here, though the extent is drawn later, on first use
        if extent_area is not None and not isinstance(extent_area, shapely.Geometry):
            raise LocalizationInputError("extent_area: expected a shapely geometry")
        frame = GeoFrame(crs)
        rows = _Rows.parse(x, y, weight, kind, bearing_deg, length_m, measured, key)
        line = rows.line
        if rows.u is not None and not rows.known.all():
            line = np.where(rows.known, line, _continuous_pieces(rows.xy, rows.u, rows.length) & (rows.length > 0.5))
        return cls._assemble(frame, rows, line, extent, extent_area)

    @classmethod
    def _assemble(cls, frame: GeoFrame, rows: "_Rows", line: np.ndarray, extent: str,
                  extent_area: shapely.Geometry | None, tree: cKDTree | None = None) -> "MapIndex":  # fmt: skip
        """The index of ``rows`` whose pieces of solid lines are ``line``."""
        xy, n = rows.xy, len(rows.xy)
        axis = np.zeros_like(xy)
        half = np.zeros(n)
        if rows.u is not None:
            axis[line] = rows.u[line]
            half[line] = 0.5 * rows.length[line]
            if rows.measured.any() and not rows.known.all():
                candidate = rows.measured & ~rows.known & ~line & (rows.length > 0) & (rows.length <= MAX_DASH_LENGTH_M)
                slack = length_slack(xy, rows.length, candidate)
                loose = slack > 0
                axis[loose] = rows.u[loose]
                half[loose] = 0.5 * slack[loose]
        exy, owner, esolid = expected_points(xy, axis, half)
        inputs = None
        if rows.key is not None:
            inputs = _Inputs(u=rows.u, length=rows.length, known=rows.known, line=line, measured=rows.measured)
        for arr in (xy, rows.weight, axis, half, exy, owner, esolid, rows.key, *(inputs.arrays() if inputs else ())):
            if arr is not None:
                arr.setflags(write=False)
        if tree is None:
            tree = _marking_tree(xy)
        return cls(xy=xy, weight=rows.weight, axis=axis, half_length=half, tree=tree, frame=frame,
                   expect_xy=exy, expect_owner=owner, expect_solid=esolid, extent_rule=extent,
                   extent_area=extent_area, key=rows.key, inputs=inputs)  # fmt: skip

    def updated(self, removed, key, x, y, weight=None, *, kind=None, bearing_deg=None, length_m=None,
                measured=None) -> "MapIndex":  # fmt: skip
        """This index with some markings written anew and some removed: what
        :meth:`from_arrays` builds from the markings as they are now, for a
        fraction of its cost when few changed.

        Needs an index built with ``key``. The markings' pieces of continuous
        lines are inferred again only near the markings that changed, and the
        extent, if drawn, redrawn only near the ones that moved
        (:meth:`MapExtent.updated`); the rest is rebuilt whole, in vectorized
        passes (the expected points, the lengths' slack, whose typical lengths
        are the map's, and the KD-tree if a marking came, went or moved). For
        1,000,000 markings by ``"markings"``: 0.5-0.7 s for a moved marking,
        against 18-25 s for a build (2026-12-07, two cores). Where only
        weights changed, or nothing the index holds (a review's decisions),
        everything but the weights is this index's own (0.01 s a server's
        update, with reading the change feed).

        Parameters
        ----------
        removed : array_like of int
            Keys of markings no longer in the map; keys the index does not
            hold are ignored (a marking added and removed since it was built).
        key : array_like of int, shape (K,)
            Keys of the markings written since (added or changed), each once.
        x, y, weight, kind, bearing_deg, length_m, measured
            Their values, as :meth:`from_arrays` takes them; ``bearing_deg``
            and ``length_m`` must be given if and only if this index was built
            with them.

        Raises
        ------
        LocalizationInputError
            On an index built without keys, values :meth:`from_arrays` rejects,
            or keys given twice.
        """
        old = self.inputs
        if old is None or self.key is None:
            raise LocalizationInputError("this index was built without keys: build it anew")
        rows = _Rows.parse(x, y, weight, kind, bearing_deg, length_m, measured, key, sorted_keys=False)
        if (rows.u is None) != (old.u is None):
            raise LocalizationInputError("bearing_deg, length_m: give them if and only if the index was built with them")
        removed = np.asarray(removed, np.int64).reshape(-1)
        same = self._reweighted(rows, removed)
        if same is not None:
            return same
        gone_keys = np.concatenate([removed, rows.key])
        gone = np.isin(self.key, gone_keys)
        keep = ~gone
        merged_key = np.concatenate([self.key[keep], rows.key])
        order = np.argsort(merged_key, kind="stable")

        def merge(a, b):
            return None if a is None else np.concatenate([a[keep], b])[order]

        now = _Rows(xy=merge(self.xy, rows.xy), weight=merge(self.weight, rows.weight), u=merge(old.u, rows.u),
                    length=merge(old.length, rows.length), known=merge(old.known, rows.known),
                    line=merge(old.line, rows.line), measured=merge(old.measured, rows.measured),
                    key=merged_key[order])  # fmt: skip
        if now.xy.shape == self.xy.shape and np.array_equal(now.xy, self.xy):
            tree = self.tree  # no marking moved, came or went (weights, kinds)
        else:
            tree = _marking_tree(now.xy)
        line = now.line  # merged: a new array
        changed_xy = np.concatenate([self.xy[gone], rows.xy])
        if now.u is not None and len(changed_xy) and not now.known.all():
            reach = 0.6 + float(max(now.length.max(initial=0.0), old.length[gone].max(initial=0.0)))
            near = _ball(tree, changed_xy, reach)  # whose ends may meet a changed marking's
            around = _ball(tree, changed_xy, 2.0 * reach)  # the ends those may meet
            inferred = _continuous_pieces(now.xy[around], now.u[around], now.length[around])
            redo = np.isin(around, near) & ~now.known[around]
            line[around[redo]] = inferred[redo] & (now.length[around[redo]] > 0.5)
        index = self._assemble(self.frame, now, line, self.extent_rule, self.extent_area, tree)
        drawn = self.__dict__.get("extent", False)
        if drawn is not False:  # drawn already: redrawn where markings moved
            was, was_xy = self.key[gone], self.xy[gone]  # ascending
            at = _positions(was, rows.key)
            same = at >= 0
            same[same] = (was_xy[at[same]] == rows.xy[same]).all(axis=1)
            stayed = np.zeros(len(was), bool)
            stayed[at[same]] = True
            moved = np.concatenate([was_xy[~stayed], rows.xy[~same]])
            index.__dict__["extent"] = (map_extent(now.xy, self.extent_rule, area=self.extent_area) if drawn is None
                                        else drawn.updated(now.xy, moved))  # fmt: skip
        return index

    def _reweighted(self, rows: "_Rows", removed: np.ndarray) -> "MapIndex | None":
        """:meth:`updated` where no marking came or went and the written ones differ from the
        index's in their weights at most (a review's decisions, a weight corrected): the arrays
        but the weights, the KD-tree and the extent are this index's own. None otherwise."""
        held = _positions(self.key, removed)
        at = _positions(self.key, rows.key)
        if (held >= 0).any() or (at < 0).any():
            return None
        old = self.inputs
        known = rows.known
        if not (np.array_equal(self.xy[at], rows.xy) and np.array_equal(old.known[at], known)
                and np.array_equal(old.measured[at], rows.measured)
                and np.array_equal(old.line[at][known], rows.line[known])):  # unknown kinds: inferred as before
            return None
        if old.u is not None and not (np.array_equal(old.u[at], rows.u)
                                      and np.array_equal(old.length[at], rows.length)):
            return None
        if np.array_equal(self.weight[at], rows.weight):
            weight = self.weight
        else:
            weight = self.weight.copy()
            weight[at] = rows.weight
            weight.setflags(write=False)
        index = replace(self, weight=weight)
        for name in ("extent", "expect_groups"):  # drawn already: the same
            if name in self.__dict__:
                index.__dict__[name] = self.__dict__[name]
        return index

    @cached_property
    def extent(self) -> "MapExtent | None":
        """Where the map speaks for the ground (:func:`map_extent` by :attr:`extent_rule`); None
        for a map without area.

        Built on first use (a race builds it twice, harmlessly): it is the
        costliest part of a large map's index, and only the default method's
        check at a map's edge (``Options.edge_share``) reads it.
        """
        return map_extent(self.xy, self.extent_rule, area=self.extent_area)

    @cached_property
    def expect_groups(self) -> tuple[np.ndarray, np.ndarray]:
        """Expected points grouped by marking: ``(order, start)``.

        The expected points of marking ``i`` are ``order[start[i]:start[i + 1]]``;
        a request gathers those of its neighbourhood without touching the whole
        map. Built on first use (a race builds it twice, harmlessly).
        """
        owner = np.zeros(0, np.intp) if self.expect_owner is None else self.expect_owner
        order = np.argsort(owner, kind="stable")
        start = np.searchsorted(owner[order], np.arange(len(self) + 1))
        return order, start

    def expect_of(self, markings: np.ndarray) -> np.ndarray:
        """Indices (ascending) of the expected points of ``markings``."""
        order, start = self.expect_groups
        lo, hi = start[markings], start[markings + 1]
        cnt = hi - lo
        total = int(cnt.sum())
        if total == 0:
            return np.zeros(0, np.intp)
        pos = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)
        return np.sort(order[pos])

    def near(self, center, radius: float) -> np.ndarray:
        """Indices of markings within ``radius`` metres of ``center`` (x, y)."""
        if len(self) == 0:
            return np.zeros(0, dtype=np.intp)
        idx = self.tree.query_ball_point(np.asarray(center, float), radius)
        return np.sort(np.asarray(idx, dtype=np.intp))

    def distance_to_nearest(self, point) -> float:
        """Distance from ``point`` (x, y) to the nearest marking, metres (inf when empty)."""
        if len(self) == 0:
            return math.inf
        d, _ = self.tree.query(np.asarray(point, float))
        return float(d)


def _ball(tree: cKDTree, centres: np.ndarray, radius: float) -> np.ndarray:
    """Indices (ascending, once each) of the points of ``tree`` within ``radius`` of any of ``centres``."""
    hits = tree.query_ball_point(centres, radius)
    return np.unique(np.concatenate([np.asarray(h, np.intp) for h in hits] + [np.zeros(0, np.intp)]))


@dataclass(frozen=True, eq=False)
class _Inputs:
    """What an index with keys keeps of its markings beyond its own arrays, to be updated
    (:meth:`MapIndex.updated`): directions and lengths (None if not given), which markings'
    kinds were given, which are pieces of solid lines (given or inferred), which were measured."""

    u: np.ndarray | None
    length: np.ndarray | None
    known: np.ndarray
    line: np.ndarray
    measured: np.ndarray

    def arrays(self) -> tuple:
        return self.u, self.length, self.known, self.line, self.measured

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        for arr in self.arrays():
            if arr is not None:
                arr.setflags(write=False)


@dataclass
class _Rows:
    """Markings as :meth:`MapIndex.from_arrays` takes them, checked: ``line`` holds the pieces of
    solid lines by kind (those of unknown kind are inferred from their neighbours)."""

    xy: np.ndarray
    weight: np.ndarray
    u: np.ndarray | None
    length: np.ndarray | None
    known: np.ndarray
    line: np.ndarray
    measured: np.ndarray
    key: np.ndarray | None

    @classmethod
    def parse(cls, x, y, weight, kind, bearing_deg, length_m, measured, key, sorted_keys: bool = True) -> "_Rows":
        xs = _column("x", x)
        n = xs.size
        ys = _column("y", y, n)
        w = np.ones_like(xs) if weight is None else _column("weight", weight, n)
        if np.any(w <= 0):
            raise LocalizationInputError("weight: map marking weights must be positive")
        keys = None
        if key is not None:
            try:
                keys = np.asarray(key)  # [] is float64 to numpy
                keys = keys.astype(np.int64, casting="safe" if keys.size else "unsafe").reshape(-1)
            except (TypeError, ValueError) as exc:
                raise LocalizationInputError("key: not an array of integers") from exc
            if keys.size != n:
                raise LocalizationInputError(f"key: {keys.size} values, expected {n}")
            # ascending keys are unique; np.unique took 0.8 s for a city's
            if np.any(np.diff(keys) <= 0) if sorted_keys else np.unique(keys).size != n:
                raise LocalizationInputError("key: keys must be unique" + (", ascending" if sorted_keys else ""))
        known = np.zeros(n, bool)
        line = np.zeros(n, bool)
        u = length = None
        if bearing_deg is not None and length_m is not None:
            b = np.radians(_column("bearing_deg", bearing_deg, n))
            length = _column("length_m", length_m, n)
            u = np.column_stack([np.sin(b), np.cos(b)])
            if kind is not None:
                kinds = np.asarray(kind, dtype=object).reshape(-1)
                if kinds.size != n:
                    raise LocalizationInputError(f"kind: {kinds.size} values, expected {n}")
                # Kinds come from people too (the editor): "Solid " is solid.
                names = ["" if k is None else str(k).strip().lower() for k in kinds]
                known = np.array([name != "" for name in names], bool).reshape(-1)
                line = np.array([name == "solid" for name in names], bool).reshape(-1) & (length > 0.5)
        meas = np.zeros(n, bool)
        if measured is not None and u is not None:
            meas = np.asarray(measured, dtype=bool).reshape(-1)
            if meas.size != n:
                raise LocalizationInputError(f"measured: {meas.size} values, expected {n}")
        return cls(xy=np.column_stack([xs, ys]), weight=w, u=u, length=length, known=known, line=line,
                   measured=meas, key=keys)  # fmt: skip


#: Delaunay triangles between markings whose sides are all at most this long
#: make up a map's extent, metres: a road's width and the gaps of its dashes
#: and junctions, but not the unmapped stretch between two parts of a map.
EXTENT_LINK_M = 30.0
#: How a map's extent is drawn when its markings alone say (:func:`map_extent`).
EXTENT_RULES = ("hull", "markings")
#: How far a point must lie outside the triangles to be beyond the map,
#: metres: a marking at the edge is still seen with the range noise of a far
#: observation.
EXTENT_MARGIN_M = 1.0
#: The side of the squares of the map grid whose ground the ``"markings"``
#: rule draws one at a time, metres (:func:`map_extent`). An edit redraws
#: the squares within two link lengths of it. For a street grid of 1,000,000
#: markings: the whole map in 10 s (22 s by squares of 1 km, 36 s as one
#: triangulation, 2026-12-07), a moved marking's squares in 0.1 s (0.9 s by 1 km).
EXTENT_SQUARE_M = 500.0
#: A square's triangles come from the Delaunay triangulation of the markings
#: within this many link lengths of it.
EXTENT_HALO_LINKS = 2.0


def _check_extent_rule(rule: str) -> None:
    if rule not in EXTENT_RULES:
        raise LocalizationInputError(f"extent: {rule!r} is not one of {', '.join(EXTENT_RULES)}")


_NO_SQUARES = np.zeros((0, 2), np.int64)


@dataclass(frozen=True, eq=False)
class MapExtent:
    """The ground a map speaks for: beyond it, an unmapped marking may be painted.

    Attributes
    ----------
    pieces : (P,) ndarray of shapely geometries
        The ground, in pieces that may overlap (map CRS, metres), prepared
        for point queries: by ``"markings"`` one piece per square of the map
        grid (:data:`EXTENT_SQUARE_M`), by ``"hull"`` the hull; each grown by
        ``margin_m``.
    squares : (P, 2) int64 ndarray
        The grid square of each piece (``floor(xy / EXTENT_SQUARE_M)``); by
        ``"hull"``, none.
    rule : str
        How it was drawn: ``"hull"`` or ``"markings"`` (:func:`map_extent`).
    link_m, margin_m : float
        The other parameters it was built with.
    given : shapely geometry or None
        Ground known from elsewhere to be part of it (:func:`map_extent`'s ``area``).
    """

    pieces: np.ndarray
    squares: np.ndarray
    rule: str
    link_m: float
    margin_m: float
    given: shapely.Geometry | None = None

    def __post_init__(self) -> None:
        self._index()

    def _index(self) -> None:
        geoms = self.pieces if self.given is None else np.append(self.pieces, self.given)
        shapely.prepare(geoms)
        object.__setattr__(self, "_geoms", geoms)
        object.__setattr__(self, "_tree", shapely.STRtree(geoms))

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("_geoms", "_tree")}

    def __setstate__(self, state: dict) -> None:
        # A pickled geometry comes back unprepared, and the tree is not pickled.
        self.__dict__.update(state)
        self._index()

    @cached_property
    def area(self) -> shapely.Geometry:
        """The extent as one geometry (map CRS; for display: queries use :meth:`beyond`)."""
        if len(self._geoms) == 1:
            return self._geoms[0]
        return shapely.union_all(self._geoms)

    def beyond(self, x, y) -> np.ndarray:
        """Whether the points ``(x, y)`` (map CRS, metres) lie more than ``margin_m`` outside."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        points = shapely.points(x.ravel(), y.ravel())
        near, piece = self._tree.query(points)  # bounding boxes: then the prepared pieces
        inside = np.zeros(points.size, bool)
        inside[near[shapely.intersects(self._geoms[piece], points[near])]] = True
        return ~inside.reshape(x.shape)

    def updated(self, xy: np.ndarray, moved: np.ndarray) -> "MapExtent | None":
        """The extent of the markings at ``xy``, drawn by the same rule, where the markings
        at ``moved`` (their places before and after) are all that changed since this one.

        The same as :func:`map_extent` of ``xy``, but by ``"markings"`` only the
        squares whose triangles may have changed are drawn again.
        """
        xy = np.asarray(xy, float).reshape(-1, 2)
        moved = np.asarray(moved, float).reshape(-1, 2)
        if not len(moved):
            return self
        pts = _rule_points(xy, self.rule, self.link_m, self.given)
        if self.rule != "markings" or len(pts) < 3 or not len(self.squares):
            return map_extent(xy, self.rule, self.link_m, self.margin_m, area=self.given)
        side, halo = EXTENT_SQUARE_M, EXTENT_HALO_LINKS * self.link_m
        redo = np.unique(_halo_pairs(moved, side, halo)[0], axis=0)
        if len(redo) <= 64:  # only the markings near those squares: their own order kept
            near = np.zeros(len(pts), bool)
            for lo in redo * side - halo - 1.0:
                near |= ((pts >= lo) & (pts < lo + side + 2.0 * halo + 2.0)).all(axis=1)
            pts = pts[near]
        keep = ~_rows_in(self.squares, redo)
        squares, pieces = _square_pieces(pts, self.link_m, self.margin_m, only=redo)
        squares = np.concatenate([self.squares[keep], squares])
        pieces = np.concatenate([self.pieces[keep], pieces])
        order = np.lexsort((squares[:, 1], squares[:, 0]))
        return MapExtent(pieces=pieces[order], squares=squares[order], rule=self.rule, link_m=self.link_m,
                         margin_m=self.margin_m, given=self.given)  # fmt: skip


def _positions(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Where each of ``keys`` is in ``sorted_keys`` (ascending), or -1 where it is not."""
    if not len(sorted_keys):
        return np.full(len(keys), -1, np.intp)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return np.where(sorted_keys[at] == keys, at, -1)


def _rows_in(rows: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Whether each row of ``rows`` (K, 2) int64 is a row of ``table``."""
    if not len(rows) or not len(table):
        return np.zeros(len(rows), bool)
    return np.isin(_cell_keys(rows), _cell_keys(table))


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 per grid cell ``cells`` (K, 2) int64: a flat key sorts and compares as fast as
    an integer (``np.unique`` by rows held the interpreter for a second at 1,000,000 markings)."""
    return cells[:, 0] * (1 << 32) + cells[:, 1]


def _halo_pairs(xy: np.ndarray, side: float, halo: float) -> tuple[np.ndarray, np.ndarray]:
    """Each point with each grid square whose box grown by ``halo`` (< ``side``) holds it:
    ``(squares (K, 2) int64, points (K,))``, sorted by square, then point."""
    lo = np.floor((xy - halo) / side).astype(np.int64)
    hi = np.floor((xy + halo) / side).astype(np.int64)
    squares, points = [], []
    for step in ((0, 0), (1, 0), (0, 1), (1, 1)):
        sq = lo + step
        ok = np.flatnonzero((sq <= hi).all(axis=1))
        squares.append(sq[ok])
        points.append(ok)
    squares, points = np.concatenate(squares), np.concatenate(points)
    order = np.lexsort((points, squares[:, 1], squares[:, 0]))
    return squares[order], points[order]


def _square_piece(pts: np.ndarray, square: np.ndarray, side: float, link_m: float,
                  margin_m: float) -> shapely.Geometry | None:  # fmt: skip
    """The ground of one grid square by ``"markings"``: the short triangles whose centroid lies
    in it, and the markings in it that are in no short triangle, all grown by ``margin_m``.

    ``pts`` are the markings within the square's halo, in the map's order:
    the triangulation, a function of them alone, is the same whether the
    whole map or one square is drawn.
    """
    home = (np.floor(pts / side) == square).all(axis=1)
    short = np.zeros(0, bool)
    corners = np.zeros((0, 3, 2))
    if len(pts) >= 3:
        try:
            tri = Delaunay(pts - square * side)
        except QhullError:  # all on one line
            tri = None
        if tri is not None:
            corners = pts[tri.simplices]  # (T, 3, 2)
            short = (np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2) <= link_m).all(axis=1)
    parts = [np.zeros(0, object)]
    kept = short & (np.floor(corners.mean(axis=1) / side) == square).all(axis=1)
    if kept.any():
        area = _triangles_area(pts, tri.simplices[kept])
        parts.append(shapely.buffer(shapely.get_parts(area), margin_m, quad_segs=4))
    lone = home.copy()
    if short.any():
        lone[np.unique(tri.simplices[short])] = False
    if lone.any():
        parts.append(shapely.buffer(shapely.points(pts[lone]), margin_m, quad_segs=4))
    parts = np.concatenate(parts)
    return shapely.disjoint_subset_union_all(parts) if len(parts) else None


def _square_pieces(pts: np.ndarray, link_m: float, margin_m: float,
                   only: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The ``"markings"`` pieces of the squares near ``pts`` (or of the squares ``only``):
    ``(squares (P, 2), pieces (P,))``, sorted by square."""
    side, halo = EXTENT_SQUARE_M, EXTENT_HALO_LINKS * link_m
    squares, member = _halo_pairs(pts, side, halo)
    if only is not None:
        keep = _rows_in(squares, only)
        squares, member = squares[keep], member[keep]
    breaks = np.flatnonzero((np.diff(squares, axis=0) != 0).any(axis=1)) + 1
    out_sq, out = [], []
    for group in np.split(np.arange(len(squares)), breaks):
        if not len(group):
            continue
        piece = _square_piece(pts[member[group]], squares[group[0]], side, link_m, margin_m)
        if piece is not None:
            out_sq.append(squares[group[0]])
            out.append(piece)
    pieces = np.empty(len(out), object)
    pieces[:] = out
    return np.array(out_sq, np.int64).reshape(-1, 2), pieces


def _triangles_area(pts: np.ndarray, simplices: np.ndarray) -> shapely.Geometry:
    """The union of the triangles ``pts[simplices]`` (T, 3) of one triangulation.

    Drawn from the outline alone: the edges of one triangle only cut the
    plane into faces (:func:`shapely.polygonize`), each all inside or all
    outside, and the side of its outline edge that the triangle holding it
    lies on says which. Joining the triangles as polygons instead, whose
    creation took half of the time, drew the extent of a 1,000,000-marking
    street grid in 14.5 s instead of 10.0 s (2026-12-07). The triangles' own
    area checks the result; where it differs (degenerate triangles) they
    are joined as polygons.
    """
    a, b, c = (pts[simplices[:, k]] for k in range(3))
    doubled = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    ccw = simplices.copy()
    ccw[doubled < 0, 1:] = simplices[doubled < 0, :0:-1]  # every triangle to the left of its edges
    edges = np.concatenate([ccw[:, [0, 1]], ccw[:, [1, 2]], ccw[:, [2, 0]]])
    n = np.int64(len(pts))
    ends = np.sort(edges, axis=1)
    _, first, count = np.unique(ends[:, 0].astype(np.int64) * n + ends[:, 1], return_index=True, return_counts=True)
    outline = edges[first[count == 1]]  # its triangle on its left
    faces = shapely.get_parts(shapely.polygonize(shapely.linestrings(
        np.stack([pts[outline[:, 0]], pts[outline[:, 1]]], axis=1))))  # fmt: skip
    rings = shapely.get_exterior_ring(faces)
    start = shapely.get_coordinates(shapely.get_point(rings, 0))
    then = shapely.get_coordinates(shapely.get_point(rings, 1))
    corner = np.unique(outline)
    vertex = dict(zip(map(tuple, pts[corner].tolist()), corner.tolist()))
    forward = set(map(tuple, outline.tolist()))
    inside = np.array([((vertex[p], vertex[q]) in forward) == left for p, q, left in
                       zip(map(tuple, start.tolist()), map(tuple, then.tolist()), shapely.is_ccw(rings))], bool)
    area = shapely.multipolygons(faces[inside])
    if abs(area.area - 0.5 * np.abs(doubled).sum()) <= 1e-9 * max(1.0, area.area):
        return area
    return shapely.union_all(shapely.polygons(pts[simplices]))


def _rule_points(xy: np.ndarray, rule: str, link_m: float, given: shapely.Geometry | None) -> np.ndarray:
    """The markings the rule's ground is drawn from: with ``given`` ground and ``"markings"``,
    those within ``link_m`` of ground outside it."""
    if given is not None and rule == "markings" and len(xy):
        inner = given.buffer(-link_m)
        if not inner.is_empty:
            return xy[~shapely.contains_xy(inner, xy[:, 0], xy[:, 1])]
    return xy


def map_extent(xy: np.ndarray, rule: str = "hull", link_m: float = EXTENT_LINK_M,
               margin_m: float = EXTENT_MARGIN_M, area: shapely.Geometry | None = None) -> MapExtent | None:  # fmt: skip
    """The extent of a map whose markings are at ``xy`` (map CRS, metres), by ``rule``.

    ``"hull"``: the markings' convex hull, for a map that holds every marking
    painted within it (an area surveyed whole). ``"markings"``: the union of
    the Delaunay triangles between markings whose sides are all at most
    ``link_m`` long, and of the markings themselves, for a map whose world
    goes on past it in places its hull covers: the streets of a route, parts
    of a city, a survey with a stretch of road left out. It ends where the
    markings do, and open ground between them wider than ``link_m`` (a city
    block between mapped streets) lies outside too. Either is grown by
    ``margin_m`` (with mitred corners, so that a point is beyond a hull when it
    lies more than ``margin_m`` beyond one of its sides).

    By ``"markings"`` the ground is drawn a square of the map grid at a time
    (:data:`EXTENT_SQUARE_M`): a square holds the short triangles whose
    centroid lies in it, from the triangulation of the markings within
    ``EXTENT_HALO_LINKS * link_m`` of it, and its markings in none of them.
    Where markings lie in general position these are the triangles of the
    whole map's triangulation; an edit redraws only the squares near it
    (:meth:`MapExtent.updated`), and a map of separate parts is triangulated
    part by part (qhull slows down with distant points).

    ``area`` (map CRS) is ground known from elsewhere to hold every marking
    painted on it, such as the footprint of the imagery the map was built
    from: the extent is its union with the rule's. It is not grown: past
    the imagery's border nothing is known, and a marking painted just past
    it, unmapped, must count as beyond the map (the markings near the border
    have their margin from the rule's extent). With ``"markings"``, only
    the markings within ``link_m`` of ground outside ``area`` are triangulated
    (a triangle with sides of at most ``link_m`` that reaches beyond ``area``
    has all its corners there), so a map built wholly from imagery costs
    little more than its footprint.

    Returns None for fewer than three markings, or, by ``"hull"``, markings on
    one line (no area), unless ``area`` is given and not empty.

    Raises
    ------
    LocalizationInputError
        On an unknown ``rule``.
    """
    _check_extent_rule(rule)
    xy = np.asarray(xy, float).reshape(-1, 2)
    given = None if area is None or area.is_empty else shapely.make_valid(area)
    pts = _rule_points(xy, rule, link_m, given)
    squares, pieces = _NO_SQUARES, np.zeros(0, object)
    if len(pts) >= 3 and rule == "markings":
        squares, pieces = _square_pieces(pts, link_m, margin_m)
    elif len(pts) >= 3:
        try:
            hull = ConvexHull(pts - pts.mean(axis=0))
        except QhullError:
            hull = None
        if hull is not None:
            pieces = np.array([shapely.Polygon(pts[hull.vertices]).buffer(margin_m, join_style="mitre",
                                                                         mitre_limit=1e6)], object)  # fmt: skip
    if not len(pieces) and given is None:
        return None
    return MapExtent(pieces=pieces, squares=squares, rule=rule, link_m=float(link_m), margin_m=float(margin_m),
                     given=given)  # fmt: skip

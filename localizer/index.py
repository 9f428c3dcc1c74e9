"""A map's spatial index, built once and shared by requests (and threads)."""

from __future__ import annotations

import math
from dataclasses import dataclass
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
    if n < 3:
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
    # The median length per grid cell: sorted by cell, then by length.
    cell_xy = np.floor(xy[idx] / TYPICAL_CELL_M).astype(np.int64)
    _, cell = np.unique(cell_xy, axis=0, return_inverse=True)
    cell = cell.reshape(-1)
    order = np.lexsort((lens, cell))
    count = np.bincount(cell)
    first = np.cumsum(count) - count
    med = 0.5 * (lens[order][first + (count - 1) // 2] + lens[order][first + count // 2])
    typical = np.where(count >= TYPICAL_MIN, med, float(np.median(lens)))[cell]
    off = np.abs(lens - typical)
    slack[idx] = np.where(off > LENGTH_TOLERANCE * typical + 0.1, off, 0.0)
    return slack


#: Spacing of the expected observations along a solid line, metres.
SOLID_SAMPLE_M = 3.0


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

    def __setstate__(self, state: dict) -> None:
        # A copy (pickle: an index kept in a file) is as read-only as the index it copies.
        self.__dict__.update(state)
        for name in ("xy", "weight", "axis", "half_length", "expect_xy", "expect_owner", "expect_solid"):
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

        Raises
        ------
        LocalizationInputError
            On NaN/inf, mismatched lengths, non-positive weights or a bad CRS.
        """
        _check_extent_rule(extent)  # here, though the extent is drawn later, on first use
        if extent_area is not None and not isinstance(extent_area, shapely.Geometry):
            raise LocalizationInputError("extent_area: expected a shapely geometry")
        frame = GeoFrame(crs)
        xs = _column("x", x)
        ys = _column("y", y, xs.size)
        w = np.ones_like(xs) if weight is None else _column("weight", weight, xs.size)
        if np.any(w <= 0):
            raise LocalizationInputError("weight: map marking weights must be positive")
        xy = np.column_stack([xs, ys])
        axis = np.zeros_like(xy)
        half = np.zeros(xs.size)
        if bearing_deg is not None and length_m is not None:
            b = np.radians(_column("bearing_deg", bearing_deg, xs.size))
            length = _column("length_m", length_m, xs.size)
            u = np.column_stack([np.sin(b), np.cos(b)])
            known = np.zeros(xs.size, bool)
            solid = np.zeros(xs.size, bool)
            if kind is not None:
                kinds = np.asarray(kind, dtype=object).reshape(-1)
                if kinds.size != xs.size:
                    raise LocalizationInputError(f"kind: {kinds.size} values, expected {xs.size}")
                # Kinds come from people too (the editor): "Solid " is solid.
                names = ["" if k is None else str(k).strip().lower() for k in kinds]
                known = np.array([n != "" for n in names], bool)
                solid = np.array([n == "solid" for n in names], bool)
            if not known.all():
                solid = np.where(known, solid, _continuous_pieces(xy, u, length))
            solid &= length > 0.5
            axis[solid] = u[solid]
            half[solid] = 0.5 * length[solid]
            if measured is not None and not known.all():
                meas = np.asarray(measured, dtype=bool).reshape(-1)
                if meas.size != xs.size:
                    raise LocalizationInputError(f"measured: {meas.size} values, expected {xs.size}")
                slack = length_slack(xy, length, meas & ~known & ~solid & (length > 0) & (length <= MAX_DASH_LENGTH_M))
                loose = slack > 0
                axis[loose] = u[loose]
                half[loose] = 0.5 * slack[loose]
        exy, owner, esolid = expected_points(xy, axis, half)
        for arr in (xy, w, axis, half, exy, owner, esolid):
            arr.setflags(write=False)
        tree = cKDTree(xy) if xs.size else cKDTree(np.zeros((0, 2)))
        return cls(xy=xy, weight=w, axis=axis, half_length=half, tree=tree, frame=frame,
                   expect_xy=exy, expect_owner=owner, expect_solid=esolid, extent_rule=extent,
                   extent_area=extent_area)

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


def _check_extent_rule(rule: str) -> None:
    if rule not in EXTENT_RULES:
        raise LocalizationInputError(f"extent: {rule!r} is not one of {', '.join(EXTENT_RULES)}")


@dataclass(frozen=True)
class MapExtent:
    """The ground a map speaks for: beyond it, an unmapped marking may be painted.

    Attributes
    ----------
    area : shapely.Polygon or shapely.MultiPolygon
        The extent grown by ``margin_m`` (map CRS, metres), prepared for
        point queries.
    rule : str
        How it was drawn: ``"hull"`` or ``"markings"`` (:func:`map_extent`).
    link_m, margin_m : float
        The other parameters it was built with.
    """

    area: shapely.Geometry
    rule: str
    link_m: float
    margin_m: float

    def __setstate__(self, state: dict) -> None:
        # A pickled geometry comes back unprepared.
        self.__dict__.update(state)
        shapely.prepare(self.area)

    def beyond(self, x, y) -> np.ndarray:
        """Whether the points ``(x, y)`` (map CRS, metres) lie more than ``margin_m`` outside."""
        return ~shapely.intersects_xy(self.area, np.asarray(x, float), np.asarray(y, float))


def _rule_area(xy: np.ndarray, rule: str, link_m: float, margin_m: float) -> shapely.Geometry | None:
    """The area of ``rule`` over the markings at ``xy``, grown by ``margin_m`` (None: no area)."""
    if len(xy) < 3:
        return None
    centre = xy.mean(axis=0)
    try:
        if rule == "hull":
            hull = ConvexHull(xy - centre)
        else:
            tri = Delaunay(xy - centre)
    except QhullError:
        return None
    if rule == "hull":
        return shapely.Polygon(xy[hull.vertices]).buffer(margin_m, join_style="mitre", mitre_limit=1e6)
    corners = xy[tri.simplices]  # (T, 3, 2)
    short = (np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2) <= link_m).all(axis=1)
    # Grown a part at a time and joined where they meet: a MultiPolygon's own buffer
    # took 31 s for the 30,000 parts of 1,000,000 markings, a MultiPoint's 15 s for
    # 27,000 markings in no kept triangle (a lone stop line, sparse detections).
    parts = [np.zeros(0, object)]
    if short.any():
        parts.append(shapely.buffer(shapely.get_parts(_triangles_union(corners[short])), margin_m, quad_segs=4))
    lone = np.ones(len(xy), bool)
    lone[np.unique(tri.simplices[short])] = False
    if lone.any():
        parts.append(shapely.buffer(shapely.points(xy[lone]), margin_m, quad_segs=4))
    return shapely.disjoint_subset_union_all(np.concatenate(parts))


#: The side of the squares whose triangles :func:`_triangles_union` joins at a time, metres.
EXTENT_TILE_M = 500.0


def _triangles_union(corners: np.ndarray) -> shapely.Geometry:
    """The union of the triangles ``corners`` (T, 3, 2), none overlapping another.

    Joined a square of :data:`EXTENT_TILE_M` at a time (by a triangle's first
    corner), then the squares' unions, which share only edges: the same
    union, without the polygons of every triangle at once (the build's peak
    for 1,000,000 markings fell from 1.8 GB to 0.6-0.7 GB).
    """
    cell = np.floor(corners[:, 0, :] / EXTENT_TILE_M).astype(np.int64)
    order = np.lexsort((cell[:, 1], cell[:, 0]))
    corners, cell = corners[order], cell[order]
    breaks = np.flatnonzero((np.diff(cell, axis=0) != 0).any(axis=1)) + 1
    return shapely.coverage_union_all([shapely.coverage_union_all(shapely.polygons(square))
                                       for square in np.split(corners, breaks)])  # fmt: skip


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

    Returns None for fewer than three markings or markings on one line (no
    area), unless ``area`` is given and not empty.

    Raises
    ------
    LocalizationInputError
        On an unknown ``rule``.
    """
    _check_extent_rule(rule)
    xy = np.asarray(xy, float).reshape(-1, 2)
    given = None if area is None or area.is_empty else shapely.make_valid(area)
    if given is not None and rule == "markings" and len(xy):
        inner = given.buffer(-link_m)
        if not inner.is_empty:
            xy = xy[~shapely.contains_xy(inner, xy[:, 0], xy[:, 1])]
    area = _rule_area(xy, rule, link_m, margin_m)
    if given is not None:
        area = given if area is None else shapely.union(area, given)
    if area is None:
        return None
    shapely.prepare(area)
    return MapExtent(area=area, rule=rule, link_m=float(link_m), margin_m=float(margin_m))

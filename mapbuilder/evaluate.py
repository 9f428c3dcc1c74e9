"""How well a map's markings agree with a true set: precision, recall, centroid errors.

The rules (the same for ``lanemap evaluate`` and ``benchmarks/build_quality.py``):

* a detection matches a *discrete* true marking (a dash, a stop line, a
  stall line) when their centroids are within ``tolerance_m`` (one to one,
  by a minimum-cost assignment);
* a *line* (a solid line, or any marking longer than the builder keeps
  whole) is cut into pieces at places that mean nothing, so a detection is
  correct when its centroid lies within ``tolerance_m`` of a true piece's
  axis, and a true piece is found when a detection's axis passes within
  ``tolerance_m`` of its centroid;
* precision = correct detections / detections; recall = true markings found
  / true markings counted (at least ``min_visible`` of it visible, where the
  truth says so, and its centroid ``border_m`` inside the area);
* the centroid error is measured on matched discrete markings, the
  cross-track error on detections that lie on lines.

:func:`evaluate_markings` works in one metric CRS (metres);
:func:`evaluate_map` takes the truth in WGS84 and scores a stored map with it.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .cluster import ClusterParams
from .crs import from_wgs84, meridian_convergence_deg, to_wgs84
from .geojson import PROGRESS_STEP
from .model import Marking
from .store import Store

#: Markings longer than this are lines for scoring, metres: the builder cuts
#: longer ones into pieces.
LINE_LENGTH_M = ClusterParams.whole_max_length_m


@dataclass
class Evaluation:
    """The agreement of detected markings with true ones (see the module docstring).

    Attributes
    ----------
    detected, truth : list of Marking
        The detections inside the area, and every true marking given.
    detection_ok : (D,) bool ndarray
        Whether each detection lies on a true marking.
    found : (T,) bool ndarray
        Whether each true marking was found.
    counted : (T,) bool ndarray
        Whether each true marking counts towards recall.
    is_line : (T,) bool ndarray
        Whether each true marking is scored as a piece of a line.
    centroid_errors_m : (K,) ndarray
        Centroid distances of the matched, counted discrete markings, metres.
    centroid_error_kinds : list of str or None
        Their true kinds.
    cross_track_m : (L,) ndarray
        Distances of the detections on lines to the nearest true axis, metres.
    """

    detected: list[Marking]
    truth: list[Marking]
    detection_ok: np.ndarray
    found: np.ndarray
    counted: np.ndarray
    is_line: np.ndarray
    centroid_errors_m: np.ndarray
    centroid_error_kinds: list[str | None] = field(default_factory=list)
    cross_track_m: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n_detected(self) -> int:
        return len(self.detected)

    @property
    def n_correct(self) -> int:
        return int(self.detection_ok.sum())

    @property
    def n_true(self) -> int:
        return int(self.counted.sum())

    @property
    def n_found(self) -> int:
        return int((self.found & self.counted).sum())

    @property
    def precision(self) -> float:
        return self.n_correct / self.n_detected if self.n_detected else math.nan

    @property
    def recall(self) -> float:
        return self.n_found / self.n_true if self.n_true else math.nan

    @property
    def centroid_rmse_m(self) -> float:
        e = self.centroid_errors_m
        return float(np.sqrt(np.mean(e**2))) if e.size else math.nan

    @property
    def cross_track_rmse_m(self) -> float:
        e = self.cross_track_m
        return float(np.sqrt(np.mean(e**2))) if e.size else math.nan

    @property
    def false_detections(self) -> list[Marking]:
        return [m for m, ok in zip(self.detected, self.detection_ok) if not ok]

    @property
    def missed(self) -> list[Marking]:
        return [t for t, f, c in zip(self.truth, self.found, self.counted) if c and not f]

    def error_markings(self) -> list[Marking]:
        """The false detections and the missed true markings, copies with
        ``extra["error"]`` set to ``"false"`` or ``"missed"`` (a GeoJSON property once
        written)."""
        out = []
        for kind, items in (("false", self.false_detections), ("missed", self.missed)):
            for m in items:
                flagged = copy.copy(m)
                flagged.extra = {**(m.extra or {}), "error": kind}
                out.append(flagged)
        return out

    def recall_by_kind(self) -> dict[str, dict[str, int]]:
        """``{kind: {"true": n, "found": k}}`` over the counted true markings."""
        out: dict[str, dict[str, int]] = {}
        for t, f, c in zip(self.truth, self.found, self.counted):
            if c:
                d = out.setdefault(str(t.kind), {"true": 0, "found": 0})
                d["true"] += 1
                d["found"] += int(f)
        return dict(sorted(out.items()))

    def to_dict(self) -> dict:
        """The figures as plain JSON values (NaN as None)."""

        def num(v: float, digits: int) -> float | None:
            return None if not math.isfinite(v) else round(v, digits)

        return {
            "precision": num(self.precision, 4),
            "recall": num(self.recall, 4),
            "detections": self.n_detected,
            "correct_detections": self.n_correct,
            "true_markings": self.n_true,
            "found": self.n_found,
            "centroid_rmse_m": num(self.centroid_rmse_m, 4),
            "centroid_matches": int(self.centroid_errors_m.size),
            "cross_track_rmse_m": num(self.cross_track_rmse_m, 4),
            "on_lines": int(self.cross_track_m.size),
            "recall_by_kind": self.recall_by_kind(),
        }


def _assign(a: np.ndarray, b: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matches of points ``a`` (N, 2) to points ``b`` (M, 2) within ``tolerance_m``:
    as many as can be made, then the smallest sum of distances among those.

    Only pairs within the tolerance are ever compared (a k-d tree finds them), and each group
    of points linked by such pairs is assigned on its own, so a city's markings need no
    N x M matrix. Returns the indices into ``a`` (ascending), into ``b``, and the distances.
    """
    pairs = cKDTree(a).sparse_distance_matrix(cKDTree(b), tolerance_m, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    i, j, d = pairs["i"], pairs["j"], pairs["v"]
    n = len(a)
    graph = coo_matrix((np.ones(i.size), (i, n + j)), shape=(n + len(b), n + len(b)))
    _, label = connected_components(graph, directed=False)
    rows, cols, dists = [], [], []
    order = np.argsort(label[i], kind="stable")
    i, j, d = i[order], j[order], d[order]
    starts = np.flatnonzero(np.r_[True, label[i][1:] != label[i][:-1]])
    for lo, hi in zip(starts, np.r_[starts[1:], i.size]):
        ui, ri = np.unique(i[lo:hi], return_inverse=True)
        uj, rj = np.unique(j[lo:hi], return_inverse=True)
        # pairs beyond the tolerance cost more than any set of pairs within it
        cost = np.full((ui.size, uj.size), 1e6)
        cost[ri, rj] = d[lo:hi]
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] <= tolerance_m
        rows.append(ui[r[ok]])
        cols.append(uj[c[ok]])
        dists.append(cost[r[ok], c[ok]])
    rows, cols, dists = np.concatenate(rows), np.concatenate(cols), np.concatenate(dists)
    order = np.argsort(rows, kind="stable")
    return rows[order], cols[order], dists[order]


def _nearest_segment(points: np.ndarray, segments: np.ndarray, tolerance_m: float) -> np.ndarray:
    """Distance of each point (N, 2) to the nearest of ``segments`` (S, 4), metres; ``inf`` where
    none lies within ``tolerance_m``. Only segments whose middle is near enough to matter are
    measured."""
    out = np.full(len(points), np.inf)
    if not len(points) or not len(segments):
        return out
    mid = 0.5 * (segments[:, :2] + segments[:, 2:])
    half = 0.5 * np.hypot(*(segments[:, 2:] - segments[:, :2]).T)
    reach = tolerance_m + float(half.max()) + 1e-9
    near = cKDTree(points).sparse_distance_matrix(cKDTree(mid), reach, output_type="ndarray")
    if near.size == 0:
        return out
    i, j = near["i"], near["j"]
    keep = near["v"] <= tolerance_m + half[j] + 1e-9
    i, j = i[keep], j[keep]
    seg = segments[j]
    x0, y0, x1, y1 = seg.T
    dxs, dys = x1 - x0, y1 - y0
    l2 = np.maximum(dxs * dxs + dys * dys, 1e-12)
    px, py = points[i, 0], points[i, 1]
    t = np.clip(((px - x0) * dxs + (py - y0) * dys) / l2, 0, 1)
    dist = np.hypot(px - (x0 + t * dxs), py - (y0 + t * dys))
    np.minimum.at(out, i, dist)
    return out


def _axes(items: Sequence[Marking], grid_bearing_deg: np.ndarray | None) -> np.ndarray:
    """``x0, y0, x1, y1`` of each marking: its own ends, or else its centroid ± half its
    length along its bearing (``grid_bearing_deg``: clockwise from grid north)."""
    seg = np.array([[m.x0, m.y0, m.x1, m.y1] for m in items], float).reshape(-1, 4)
    missing = ~np.isfinite(seg).all(axis=1)
    if missing.any():
        bearing = (np.array([m.bearing_deg for m in items], float) if grid_bearing_deg is None
                   else np.asarray(grid_bearing_deg, float))  # fmt: skip
        b = np.radians(bearing[missing])
        half = 0.5 * np.array([m.length_m for m in items], float)[missing]
        x = np.array([m.x for m in items], float)[missing]
        y = np.array([m.y for m in items], float)[missing]
        ux, uy = np.sin(b) * half, np.cos(b) * half
        seg[missing] = np.column_stack([x - ux, y - uy, x + ux, y + uy])
    return seg


def is_line(m: Marking, line_length_m: float = LINE_LENGTH_M) -> bool:
    """Whether a true marking is scored as a piece of a line."""
    extra = m.extra or {}
    if "continuous" in extra:
        return bool(extra["continuous"]) or m.length_m > line_length_m
    return m.kind == "solid" or m.length_m > line_length_m


def evaluate_markings(
    detected: Sequence[Marking],
    truth: Sequence[Marking],
    bounds: tuple[float, float, float, float],
    *,
    tolerance_m: float = 0.3,
    border_m: float = 2.0,
    min_visible: float = 0.9,
    line_length_m: float = LINE_LENGTH_M,
    detected_grid_bearing_deg: np.ndarray | None = None,
    truth_grid_bearing_deg: np.ndarray | None = None,
) -> Evaluation:
    """Score detected markings against true ones inside ``bounds``.

    Parameters
    ----------
    detected, truth : sequence of Marking
        Markings with ``x``, ``y`` in one metric CRS; a marking without end
        points (``x0`` ...) is taken as its centroid ± half its length along
        its bearing.
    bounds : (xmin, ymin, xmax, ymax)
        The area the truth covers, metres; detections outside it, less
        ``border_m``, are left out.
    tolerance_m : float
        Largest centroid (or axis) distance of a match, metres.
    border_m : float
        Markings this close to the edge of ``bounds`` are not scored, metres
        (where imagery ends, markings are cut).
    min_visible : float
        A true marking counts towards recall when at least this share of it
        is visible (its ``extra["visible"]``; 1 when not given).
    line_length_m : float
        True markings longer than this are scored as pieces of lines, metres.
    detected_grid_bearing_deg, truth_grid_bearing_deg : (N,) ndarray, optional
        The markings' bearings clockwise from grid north, degrees, where they
        differ from ``bearing_deg`` (true north): used for markings without
        end points.

    Returns
    -------
    Evaluation
    """
    if not tolerance_m > 0:
        raise ValueError(f"tolerance_m must be positive, got {tolerance_m}")
    xmin, ymin, xmax, ymax = bounds

    def inside(x, y):
        return (x > xmin + border_m) & (x < xmax - border_m) & (y > ymin + border_m) & (y < ymax - border_m)

    dx = np.array([m.x for m in detected], float)
    dy = np.array([m.y for m in detected], float)
    keep = inside(dx, dy) if len(detected) else np.zeros(0, bool)
    det = [m for m, k in zip(detected, keep) if k]
    dx, dy = dx[keep], dy[keep]
    dgb = None if detected_grid_bearing_deg is None else np.asarray(detected_grid_bearing_deg)[keep]
    dseg = _axes(det, dgb)
    truth = list(truth)
    tx = np.array([m.x for m in truth], float)
    ty = np.array([m.y for m in truth], float)
    line = np.array([is_line(m, line_length_m) for m in truth], bool)
    vis = np.array([float((m.extra or {}).get("visible", 1.0)) for m in truth])
    counted = inside(tx, ty) & (vis >= min_visible) if truth else np.zeros(0, bool)
    det_ok = np.zeros(len(det), bool)
    found = np.zeros(len(truth), bool)
    errors: list[float] = []
    error_kinds: list[str | None] = []
    cross: list[float] = []
    disc = np.flatnonzero(~line)
    if len(det) and len(disc):
        r, c, dist = _assign(np.column_stack([dx, dy]), np.column_stack([tx[disc], ty[disc]]), tolerance_m)
        det_ok[r] = True
        found[disc[c]] = True
        cnt = counted[disc[c]]
        errors = list(dist[cnt])
        error_kinds = [truth[i].kind for i in disc[c][cnt]]
    lines = np.flatnonzero(line)
    if len(det) and len(lines):
        tseg = _axes([truth[i] for i in lines],
                     None if truth_grid_bearing_deg is None else np.asarray(truth_grid_bearing_deg)[lines])
        dist = _nearest_segment(np.column_stack([dx, dy]), tseg, tolerance_m)
        on_line = (~det_ok) & (dist <= tolerance_m)
        det_ok |= on_line
        cross = list(dist[on_line])
        found[lines] = _nearest_segment(np.column_stack([tx[lines], ty[lines]]), dseg, tolerance_m) <= tolerance_m
    return Evaluation(
        detected=det, truth=truth, detection_ok=det_ok, found=found, counted=counted, is_line=line,
        centroid_errors_m=np.array(errors, float), centroid_error_kinds=error_kinds,
        cross_track_m=np.array(cross, float),
    )


class EmptyMapError(ValueError):
    """The map has nothing stored yet, so no CRS to score it in."""


def evaluate_map(
    store: Store,
    map_id: str,
    truth: Sequence[Marking],
    *,
    tolerance_m: float = 0.3,
    border_m: float = 0.0,
    statuses: Sequence[str] | None = ("unreviewed", "accepted"),
    min_visible: float = 0.9,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Evaluation, tuple[float, float, float, float]]:
    """Score a stored map against true markings given in WGS84 (``lon``, ``lat``,
    ``bearing_deg`` clockwise from true north), over the truth's extent.

    The truth is taken as complete over the box around its markings (their
    lengths and the tolerance included); the map's markings with one of
    ``statuses`` inside it are scored. Returns the :class:`Evaluation`, whose
    markings are in the map's CRS, and that box in the map's CRS.
    ``progress``, optional, is called with the map's markings read so far and
    their number, every :data:`PROGRESS_STEP` and at the end.

    Raises
    ------
    ValueError
        Without true markings (or with one lacking a finite lon/lat).
    EmptyMapError
        When the map has no CRS yet (nothing stored).
    """
    if not truth:
        raise ValueError("no true markings to score against")
    info = store.get_map(map_id)
    if info.crs is None:
        raise EmptyMapError(f"map {map_id} is empty and has no CRS yet")
    crs = info.crs
    truth = [copy.copy(m) for m in truth]
    lon = np.array([m.lon for m in truth], float)
    lat = np.array([m.lat for m in truth], float)
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        raise ValueError("every true marking needs a finite lon/lat")
    x, y = from_wgs84(crs).transform(lon, lat)
    for m, a, b in zip(truth, x, y):
        m.x, m.y = float(a), float(b)
        m.x0 = m.y0 = m.x1 = m.y1 = None  # ends given in another CRS are rebuilt from the axis
    truth_grid = np.array([m.bearing_deg for m in truth], float) - meridian_convergence_deg(crs, lon, lat)
    reach = 0.5 * max(m.length_m for m in truth) + tolerance_m
    bounds = (float(x.min()) - reach, float(y.min()) - reach, float(x.max()) + reach, float(y.max()) + reach)
    box = to_wgs84(crs).transform_bounds(*bounds, densify_pts=21)
    total = store.count_markings(map_id, statuses, box) if progress is not None else 0
    detected = []
    for m in store.iter_markings(map_id, statuses=statuses, lonlat_box=box):
        detected.append(m)
        if progress is not None and len(detected) % PROGRESS_STEP == 0:
            progress(len(detected), total)
    if progress is not None:
        progress(len(detected), max(total, len(detected)))
    det_grid = None
    if detected:
        dlon = np.array([m.lon for m in detected], float)
        dlat = np.array([m.lat for m in detected], float)
        det_grid = np.array([m.bearing_deg for m in detected], float) - meridian_convergence_deg(crs, dlon, dlat)
    ev = evaluate_markings(detected, truth, bounds, tolerance_m=tolerance_m, border_m=border_m,
                           min_visible=min_visible, detected_grid_bearing_deg=det_grid,
                           truth_grid_bearing_deg=truth_grid)  # fmt: skip
    return ev, bounds

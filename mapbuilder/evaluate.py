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

Everything is in one metric CRS (metres).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .model import Marking

#: Markings longer than this are lines for scoring, metres (the builder's
#: ``ClusterParams.whole_max_length_m``: it cuts longer ones into pieces).
LINE_LENGTH_M = 8.0


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


def segment_distances(px: np.ndarray, py: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distances of points to line segments.

    Parameters
    ----------
    px, py : (P,) ndarray
        Point coordinates, metres.
    segments : (S, 4) ndarray
        ``x0, y0, x1, y1`` of each segment, metres.

    Returns
    -------
    (P, S) ndarray
        Distances, metres.
    """
    x0, y0, x1, y1 = (segments[:, i][None] for i in range(4))
    dx, dy = x1 - x0, y1 - y0
    l2 = np.maximum(dx * dx + dy * dy, 1e-12)
    t = np.clip(((px[:, None] - x0) * dx + (py[:, None] - y0) * dy) / l2, 0, 1)
    return np.hypot(px[:, None] - (x0 + t * dx), py[:, None] - (y0 + t * dy))


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
        d = np.hypot(dx[:, None] - tx[disc][None], dy[:, None] - ty[disc][None])
        cost = np.where(d <= tolerance_m, d, 1e6)
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] <= tolerance_m
        det_ok[r[ok]] = True
        found[disc[c[ok]]] = True
        cnt = counted[disc[c[ok]]]
        errors = list(d[r[ok], c[ok]][cnt])
        error_kinds = [truth[i].kind for i in disc[c[ok]][cnt]]
    lines = np.flatnonzero(line)
    if len(det) and len(lines):
        tseg = _axes([truth[i] for i in lines],
                     None if truth_grid_bearing_deg is None else np.asarray(truth_grid_bearing_deg)[lines])
        dist = segment_distances(dx, dy, tseg).min(axis=1)
        on_line = (~det_ok) & (dist <= tolerance_m)
        det_ok |= on_line
        cross = list(dist[on_line])
        found[lines] = segment_distances(tx[lines], ty[lines], dseg).min(axis=1) <= tolerance_m
    return Evaluation(
        detected=det, truth=truth, detection_ok=det_ok, found=found, counted=counted, is_line=line,
        centroid_errors_m=np.array(errors, float), centroid_error_kinds=error_kinds,
        cross_track_m=np.array(cross, float),
    )

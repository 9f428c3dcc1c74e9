"""Cluster marking pixels into markings and measure them.

A probability image from the classifier becomes markings in three steps:

1. :func:`label_pixels` thresholds it and groups the marking pixels into
   clusters (connected components, optionally joining pixels closer than a
   link distance, the Euclidean clustering of Pink 2008);
   :func:`split_junctions` cuts clusters where strokes of different
   directions meet (a stall line and the line it ends on).
2. :func:`split_long` cuts clusters longer than a piece length into pieces, so
   that the centroid of a long solid line is local. The cuts lie on a grid
   anchored in world coordinates along the cluster's (quantised) direction,
   so two tiles that see the same stretch of line cut it at the same places.
3. :func:`measure_clusters` measures each cluster from the second moments of
   its pixels: centroid, major-axis bearing, length, width, end points, pixel
   count and mean probability; :func:`filter_clusters` drops shapes no lane
   marking has.

:func:`detect_markings` runs the three steps.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields

import numpy as np
from affine import Affine
from scipy import ndimage as ndi

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClusterParams:
    """Parameters of clustering, splitting and filtering.

    Attributes
    ----------
    threshold : float
        Probability above which a pixel is a marking pixel.
    threshold_low : float or None
        Hysteresis: pixels above this are marking pixels when connected to one
        above ``threshold``; None disables it.
    link_m : float
        Marking pixels closer than this (metres) join one cluster even when not
        8-connected; 0 keeps plain 8-connectivity.
    max_length_m : float
        Length of the pieces long clusters are cut into, metres.
    split_factor : float
        Only clusters longer than ``split_factor * max_length_m`` are cut, so a
        marking measured a little longer than a piece (a 3 m dash) stays whole.
    min_width_m, max_width_m : float
        Accepted range of marking widths, metres.
    min_length_m : float
        Shortest accepted marking (or piece), metres.
    min_area_m2 : float
        Smallest accepted painted area, square metres.
    direction_step_deg : float
        Quantisation of the cutting direction of long clusters, degrees.
    whole_width_m : float or None
        Clusters at least this wide (area / length) and at most
        ``whole_max_length_m`` long are not cut: stop lines (0.5 m wide, up to
        7 m across a carriageway) are one marking, and a piece of one has its
        centroid metres off the line's. None cuts every long cluster.
    whole_max_length_m : float
        Longest cluster ``whole_width_m`` keeps whole, metres.
    join_gap_m : float
        Collinear clusters whose facing ends are at most this far apart along
        their axis are joined (a marking broken by wear or a shadow); 0
        disables it. On validation renders with the default model, 0.6 m
        raised the recall of dashes and stop lines from 0.47 to 0.70 and
        precision from 0.74 to 0.78.
    join_angle_deg : float
        Largest difference of direction of clusters to join, degrees.
    join_offset_m : float
        Largest sideways offset of a facing end from the other cluster's axis, metres.
    junction_angle_deg : float or None
        Clusters that are not one straight stripe are cut where lines whose
        directions differ by more than this meet (:func:`split_junctions`:
        stall lines on the line or kerb they end at, a stop line and the lane
        line beside it); None keeps them whole.
    verify : bool
        Check every cluster that passes the shape filter with the cluster
        verifier (by default the CNN on :func:`cluster_crops`; the earlier
        one on :func:`context_features`), when the image window and a
        verifier are given to :func:`detect_markings`. Off here, so that a
        bare ``ClusterParams()`` keeps its pixel threshold's meaning; on in
        ``lanemap build`` and the API's build jobs, which pair it with
        :func:`mapbuilder.build.default_threshold` and
        :func:`mapbuilder.build.default_threshold_low`. On held-out renders
        the CNN at pixel threshold :data:`CNN_PIXEL_THRESHOLD` (hysteresis
        :data:`CNN_PIXEL_THRESHOLD_LOW`) reaches precision 0.971 at recall
        0.950, against 0.61 / 0.92 for a build without it at 0.5 (kerbs, lot
        borders, car outlines), and on the real USGS crop it keeps all four
        stall lines with no other detection (14 without), at about 1.6 times
        the tile CPU of a build without it (2048 px tiles).
    verify_threshold : float
        Verifier probability a cluster needs to be kept. 0.6 for the shipped
        CNN, chosen on the validation scenes (``benchmarks/build_quality.py
        --seed 5000``): 0.5 / 0.6 / 0.7 / 0.8 gave precision 0.952 / 0.957 /
        0.958 / 0.963 at recall 0.911 / 0.911 / 0.908 / 0.903.
    verify_continuation : bool
        Keep a cluster the verifier rejects when it continues one it accepts
        (:func:`continues_accepted`: pieces of one line).
    verify_continuation_min : float
        Verifier probability a rejected cluster needs to be taken back as a
        continuation: a piece the verifier doubts is taken back, one it
        rejects outright is not; at or above ``verify_threshold`` nothing is
        taken back. Without it (0), one accepted piece of a kerb
        or a lot border took back the whole border, piece by piece. Chosen on
        the validation scenes (``benchmarks/build_quality.py --verify --seed
        5000``, ``--seed 6000 --n 9``, ``--seed 7000 --n 9``): 0 / 0.05 /
        0.1 / 0.15 / 0.2 / 0.3 gave a mean F1 of 0.9471 / 0.9493 / 0.9500 /
        0.9503 / 0.9505 / 0.9490, flat from 0.1 to 0.2; at 0.15 precision
        rose by 0.002 / 0.013 / 0.011 and recall fell by 0.001 / 0.001 /
        0.004 (``--seed 8000 --n 12``: +0.024 and −0.007).
    verify_halves_m : float
        A cluster at least this long (metres) that the CNN verifier rejects is
        checked again with crops centred on each of its halves, and kept when
        it accepts one: the crop (3.2 m) sees little beyond the ends of a long
        cluster, and a gap or a car beside one end (stall lines between parked
        cars) can sink the whole. Like continuation, it keeps paint the
        verifier doubts in part; kerbs and car outlines are rejected along
        their whole length. Wide clusters are checked again too: blurred
        stall lines measure 0.3–0.4 m wide and stay whole up to 8 m like stop
        lines, and since junctions are cut (``junction_angle_deg``) a wide
        cluster is seldom a marking merged with something beside it. 0
        disables it.
    extend_junctions : bool
        A marking that ends on another one running across it (a stop line on
        the lane line, a stall line on the lot border) has its end moved to
        the other's axis (:func:`extend_to_junctions`): the pixels they share
        belong to one cluster only, so the end of the other was measured at
        the edge of the line it meets, up to 0.6 m short of where it is
        painted.
    """

    threshold: float = 0.5
    threshold_low: float | None = None
    link_m: float = 0.0
    max_length_m: float = 3.0
    split_factor: float = 1.2
    min_width_m: float = 0.08
    max_width_m: float = 0.6
    min_length_m: float = 0.3
    min_area_m2: float = 0.04
    direction_step_deg: float = 2.0
    whole_width_m: float | None = 0.3
    whole_max_length_m: float = 8.0
    join_gap_m: float = 0.6
    join_angle_deg: float = 12.0
    join_offset_m: float = 0.12
    junction_angle_deg: float | None = 30.0
    verify: bool = False
    verify_threshold: float = 0.6
    verify_continuation: bool = True
    verify_continuation_min: float = 0.15
    verify_halves_m: float = 2.0
    extend_junctions: bool = True

    def __post_init__(self):
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold must be in (0, 1), got {self.threshold}")
        if self.max_length_m <= 0:
            raise ValueError(f"max_length_m must be positive, got {self.max_length_m}")
        if self.split_factor < 1.0:
            raise ValueError(f"split_factor must be >= 1, got {self.split_factor}")
        if not 0 <= self.min_width_m < self.max_width_m:
            raise ValueError(
                f"need 0 <= min_width_m < max_width_m, got {self.min_width_m}, {self.max_width_m}"
            )
        if self.link_m < 0:
            raise ValueError(f"link_m must be >= 0, got {self.link_m}")
        if self.join_gap_m < 0:
            raise ValueError(f"join_gap_m must be >= 0, got {self.join_gap_m}")
        if self.threshold_low is not None and not 0.0 < self.threshold_low < self.threshold:
            raise ValueError(f"threshold_low must be in (0, threshold = {self.threshold}), "
                             f"got {self.threshold_low}")
        if not 0.0 < self.verify_threshold < 1.0:
            raise ValueError(f"verify_threshold must be in (0, 1), got {self.verify_threshold}")
        if not 0.0 <= self.verify_continuation_min < 1.0:
            raise ValueError(f"verify_continuation_min must be in [0, 1), "
                             f"got {self.verify_continuation_min}")
        if self.junction_angle_deg is not None and not 0.0 < self.junction_angle_deg <= 90.0:
            raise ValueError(f"junction_angle_deg must be in (0, 90] or None, "
                             f"got {self.junction_angle_deg}")


@dataclass
class Clusters:
    """Measured clusters, one entry per cluster (all arrays of equal length).

    Attributes
    ----------
    x, y : ndarray of float64
        Centroid in the CRS of the transform, metres: the middle of the
        pixels' extent along the major axis, their mean across it.
    col, row : ndarray of float64
        Centroid in pixel coordinates of the array (pixel (0, 0) spans [0, 1)).
    weight : ndarray of int64
        Pixel count (the weight γ).
    length_m, width_m : ndarray of float64
        Extent along the major axis, and area / length, metres.
    bearing_deg : ndarray of float64
        Major axis, degrees clockwise from grid north, in [0, 180).
    x0, y0, x1, y1 : ndarray of float64
        End points of the major axis; (x1 - x0, y1 - y0) points along ``bearing_deg``.
    score : ndarray of float64
        Mean probability of the cluster's pixels.
    spread_m : ndarray of float64
        Width the pixels' spread across the major axis implies (sqrt(12) times
        its standard deviation), metres: about ``width_m`` for a straight
        stripe, more for a bent, forked or ring-shaped cluster.
    piece : ndarray of bool
        The cluster was cut from a longer one (:func:`split_long`): a piece of
        a continuous line, whose centroid marks where the cut fell, not a
        place on the line a camera would single out.
    """

    x: np.ndarray
    y: np.ndarray
    col: np.ndarray
    row: np.ndarray
    weight: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    bearing_deg: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    x1: np.ndarray
    y1: np.ndarray
    score: np.ndarray
    spread_m: np.ndarray
    piece: np.ndarray | None = None

    def __post_init__(self):
        if self.piece is None:  # clusters measured without cutting: no piece
            self.piece = np.zeros(len(self.x), bool)

    def __len__(self) -> int:
        return len(self.x)

    def take(self, index) -> "Clusters":
        """The clusters selected by a boolean mask or index array."""
        out = Clusters(**{f.name: getattr(self, f.name)[index] for f in fields(self)})
        if hasattr(self, "share"):
            out.share = self.share[index]
        return out

    @classmethod
    def empty(cls) -> "Clusters":
        z = np.zeros(0)
        return cls(**{f.name: z.copy() for f in fields(cls) if f.name != "piece"})


def label_pixels(
    prob: np.ndarray,
    valid: np.ndarray | None = None,
    threshold: float = 0.5,
    link_px: int = 0,
    threshold_low: float | None = None,
) -> tuple[np.ndarray, int]:
    """Group marking pixels into clusters.

    Parameters
    ----------
    prob : (H, W) float
        Probability of "marking" per pixel.
    valid : (H, W) bool, optional
        Pixels that may be marking pixels.
    threshold : float
        Pixels with ``prob > threshold`` are marking pixels.
    link_px : int
        Marking pixels up to this many pixels apart (Chebyshev) join one
        cluster; 0 or 1 mean 8-connectivity.
    threshold_low : float, optional
        Hysteresis: pixels above this join a cluster that holds at least one
        pixel above ``threshold`` (faint parts of a marking stay attached,
        faint noise on its own does not).

    Returns
    -------
    labels : (H, W) int32
        0 for background, 1..n for clusters.
    n : int
        Number of clusters.
    """
    mask = prob > threshold
    if valid is not None:
        mask &= valid
    structure = np.ones((3, 3), bool)
    if threshold_low is not None and threshold_low < threshold:
        weak = prob > threshold_low
        if valid is not None:
            weak &= valid
        labels, n = ndi.label(weak, structure=structure)
        strong = np.zeros(n + 1, bool)
        strong[labels[mask]] = True
        strong[0] = False
        if link_px <= 1:
            # the weak components holding a strong pixel are the clusters
            lut = np.cumsum(strong, dtype=np.int32)
            lut[~strong] = 0
            return lut[labels], int(strong.sum())
        mask = strong[labels]
    if link_px <= 1:
        labels, n = ndi.label(mask, structure=structure)
        return labels.astype(np.int32, copy=False), int(n)
    # Dilating by half the link distance merges clusters whose gap is at most link_px.
    grown = ndi.binary_dilation(mask, structure=np.ones((link_px, link_px), bool))
    labels, n = ndi.label(grown, structure=structure)
    labels[~mask] = 0
    # Relabel densely: a dilated component may hold no original pixel only if empty.
    used = np.unique(labels[mask])
    lut = np.zeros(n + 1, np.int32)
    lut[used] = np.arange(1, used.size + 1, dtype=np.int32)
    return lut[labels], int(used.size)


def _pixel_world(transform: Affine, rows: np.ndarray, cols: np.ndarray):
    c = cols + 0.5
    r = rows + 0.5
    x = transform.a * c + transform.b * r + transform.c
    y = transform.d * c + transform.e * r + transform.f
    return x, y


def _world_pixel(transform: Affine, x: np.ndarray, y: np.ndarray):
    """CRS coordinates to (col, row) pixel coordinates of the array (pixel (0, 0) spans [0, 1))."""
    inv = ~transform
    return inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f


def _resolution(transform: Affine) -> float:
    return math.sqrt(abs(transform.a * transform.e - transform.b * transform.d))


def _moments(lab: np.ndarray, x: np.ndarray, y: np.ndarray, k: int):
    n = np.bincount(lab, minlength=k).astype(float)
    d = np.maximum(n, 1.0)  # unused labels have no pixels
    mx = np.bincount(lab, x, k) / d
    my = np.bincount(lab, y, k) / d
    dx = x - mx[lab]
    dy = y - my[lab]
    cxx = np.bincount(lab, dx * dx, k) / d
    cyy = np.bincount(lab, dy * dy, k) / d
    cxy = np.bincount(lab, dx * dy, k) / d
    # Major axis as a unit vector (ux, uy) in x-east / y-north coordinates.
    theta = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    ux, uy = np.cos(theta), np.sin(theta)
    # Orient along a bearing in [0, 180): pointing east, or due north.
    flip = (ux < -1e-12) | ((np.abs(ux) <= 1e-12) & (uy < 0))
    ux[flip] *= -1
    uy[flip] *= -1
    return n, mx, my, dx, dy, ux, uy


def _minor_var(lab, dx, dy, ux, uy, n, k):
    """Variance of the pixels across each cluster's major axis."""
    across = dy * ux[lab] - dx * uy[lab]
    return np.bincount(lab, across * across, k) / np.maximum(n, 1.0)


def _extent(lab, s, k):
    smin = np.full(k, np.inf)
    smax = np.full(k, -np.inf)
    np.minimum.at(smin, lab, s)
    np.maximum.at(smax, lab, s)
    return smin, smax


def _measure(rows, cols, lab, score, transform: Affine, cut: np.ndarray | None = None) -> Clusters:
    """Measure clusters given as pixel lists (rows, cols, label, probability).

    ``cut`` (per pixel, optional) marks the pixels of clusters that were cut
    from longer ones; their clusters get ``piece`` set.
    """
    if rows.size == 0:
        return Clusters.empty()
    k = int(lab.max()) + 1
    x, y = _pixel_world(transform, rows, cols)
    n, mx, my, dx, dy, ux, uy = _moments(lab, x, y, k)
    smin, smax = _extent(lab, dx * ux[lab] + dy * uy[lab], k)
    d = np.maximum(n, 1)
    mean_score = np.bincount(lab, score.astype(float), k) / d
    var_minor = _minor_var(lab, dx, dy, ux, uy, n, k)

    keep = n > 0
    keep[0] = False
    res = _resolution(transform)
    n, mx, my, ux, uy = n[keep], mx[keep], my[keep], ux[keep], uy[keep]
    smin, smax = smin[keep] - 0.5 * res, smax[keep] + 0.5 * res
    length = smax - smin
    x = mx + ux * (0.5 * (smin + smax))
    y = my + uy * (0.5 * (smin + smax))
    col, row = _world_pixel(transform, x, y)
    return Clusters(
        x=x,
        y=y,
        col=col,
        row=row,
        weight=n.astype(np.int64),
        length_m=length,
        width_m=n * res * res / length,
        bearing_deg=np.degrees(np.arctan2(ux, uy)) % 180.0,
        x0=mx + ux * smin,
        y0=my + uy * smin,
        x1=mx + ux * smax,
        y1=my + uy * smax,
        score=mean_score[keep],
        spread_m=np.sqrt(12.0 * var_minor[keep] + res * res),
        piece=None if cut is None else (np.bincount(lab, np.asarray(cut, bool), k) > 0)[keep],
    )


def measure_clusters(
    labels: np.ndarray,
    prob: np.ndarray,
    transform: Affine,
    n_labels: int | None = None,
) -> Clusters:
    """Measure every cluster of a label image.

    Parameters
    ----------
    labels : (H, W) int
        0 for background, 1..n for clusters (as from :func:`label_pixels`).
    prob : (H, W) float
        Probability image, for the mean score.
    transform : Affine
        Pixel (col, row) to CRS metres of the array's (0, 0) corner.
    n_labels : int, optional
        Unused; kept for symmetry with :func:`label_pixels`.

    Returns
    -------
    Clusters
        One entry per non-empty label, in label order.

    Notes
    -----
    The centroid is the middle of the pixels' extent along the major axis and
    their mean across it (a worn marking with holes, or more pixels on its rim
    at one end, keeps its centre where its ends put it; the pixel mean moved
    dashes by 8 cm RMS along their axis on held-out renders, the middle by 4 cm);
    the bearing is that of the major axis of their second moments; length is the extent of the pixels
    along that axis plus one pixel, width is area / length (robust to ragged
    edges); the end points are the ends of that extent on the axis.
    """
    rows, cols = np.nonzero(labels)
    lab = labels[rows, cols].astype(np.int64)
    return _measure(rows, cols, lab, prob[rows, cols], transform)


class _PixelIndex:
    """Find the 8-neighbours of sparse pixels among them."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray):
        self.width = int(cols.max()) + 3
        self.key = (rows.astype(np.int64) + 1) * self.width + (cols.astype(np.int64) + 1)
        self.order = np.argsort(self.key)
        self.skey = self.key[self.order]

    def neighbour(self, which: np.ndarray | slice, dr: int, dc: int) -> tuple[np.ndarray, np.ndarray]:
        """Index of the pixel at offset (dr, dc) from each pixel ``which``, and whether it exists."""
        nkey = self.key[which] + dr * self.width + dc
        pos = np.minimum(np.searchsorted(self.skey, nkey), self.skey.size - 1)
        return self.order[pos], self.skey[pos] == nkey


def _circular_diff(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    d = np.abs(a - b)
    return np.minimum(d, n - d)


def _components(rows: np.ndarray, cols: np.ndarray, lab: np.ndarray,
                direction: np.ndarray | None = None, n_directions: int = 0,
                direction_tol: int = 0) -> np.ndarray:
    """8-connected parts of equal label among sparse pixels, as labels 0..m-1.

    With ``direction`` (a bin 0..n_directions-1 per pixel, circular), two
    neighbours are connected only when their bins differ by at most
    ``direction_tol``.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = rows.size
    index = _PixelIndex(rows, cols)
    src, dst = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        j, found = index.neighbour(slice(None), dr, dc)
        hit = found & (lab[j] == lab)
        if direction is not None:
            hit &= _circular_diff(direction[j], direction, n_directions) <= direction_tol
        src.append(np.flatnonzero(hit))
        dst.append(j[hit])
    src, dst = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(n, n))
    _, parts = connected_components(graph, directed=False)
    return parts


def _direction_bins(rows: np.ndarray, cols: np.ndarray, mask: np.ndarray, reach_px: int,
                    n_directions: int, max_across_px: float,
                    ratio: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Direction of the longest straight run of ``mask`` through each pixel.

    For each of ``n_directions`` directions over 180 degrees, counts the
    consecutive mask pixels from each given pixel both ways, up to
    ``reach_px`` each way; the direction with the longest run (smoothed over
    neighbouring directions, so that ties between them take the middle) is
    returned as a bin 0..n_directions-1, with a flag: True where that run is
    at least ``ratio`` times the run across it (plus one) and the run across
    is at most ``max_across_px``, and the stroke runs on beyond ``reach_px``
    in total (not so in a blob's corner): the pixel clearly lies on one
    stroke no wider than a marking. Not so in wide blobs (a car roof), in
    the corners of wide strokes and where two long strokes cross. Rounded
    sample positions follow a thin line only roughly, so the caller passes
    the marking mask dilated by one pixel, with a margin of ``reach_px``
    around every pixel.
    """
    runs = np.zeros((n_directions, rows.size), np.float32)
    for t in range(n_directions):
        a = math.pi * t / n_directions
        sr, sc = -math.sin(a), math.cos(a)
        for sign in (1.0, -1.0):
            alive = np.ones(rows.size, bool)
            for step in range(1, reach_px + 1):
                rr = np.rint(rows + sign * step * sr).astype(np.intp)
                cc = np.rint(cols + sign * step * sc).astype(np.intp)
                alive &= mask[rr, cc]
                runs[t] += alive
    smooth = 2.0 * runs + np.roll(runs, 1, axis=0) + np.roll(runs, -1, axis=0)
    best = np.argmax(smooth, axis=0)
    i = np.arange(rows.size)
    across = runs[(best + n_directions // 2) % n_directions, i]
    along = runs[best, i]
    clear = (along >= ratio * (across + 1.0)) & (across <= max_across_px) & (along > reach_px)
    return best, clear


def _adopt_neighbours(rows: np.ndarray, cols: np.ndarray, lab: np.ndarray, bins: np.ndarray,
                      n_directions: int, part: np.ndarray, assigned: np.ndarray,
                      passes: int) -> np.ndarray:
    """Give unassigned pixels the ``part`` of an assigned 8-neighbour of equal ``lab``.

    In each pass every unassigned pixel next to an assigned one takes the part
    of the neighbour nearest to it in direction bin (the first in a fixed
    neighbour order on ties), so the result depends on the pixels' layout
    only. Modifies ``part`` in place; returns which pixels have a part now.
    """
    index = _PixelIndex(rows, cols)
    assigned = assigned.copy()
    for _ in range(passes):
        todo = np.flatnonzero(~assigned)
        if todo.size == 0:
            break
        best = np.full(todo.size, n_directions + 1)
        new = np.full(todo.size, -1, part.dtype)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr == 0 and dc == 0:
                    continue
                j, found = index.neighbour(todo, dr, dc)
                ok = found & assigned[j] & (lab[j] == lab[todo])
                diff = _circular_diff(bins[j], bins[todo], n_directions)
                better = ok & (diff < best)
                best[better] = diff[better]
                new[better] = part[j[better]]
        got = new >= 0
        if not got.any():
            break
        part[todo[got]] = new[got]
        assigned[todo[got]] = True
    return assigned


def split_junctions(
    rows: np.ndarray,
    cols: np.ndarray,
    lab: np.ndarray,
    resolution_m: float,
    angle_deg: float = 30.0,
    min_spread_m: float = 0.7,
    reach_m: float = 0.8,
    n_directions: int = 16,
    max_width_m: float = 0.6,
    max_area_m2: float = 200.0,
) -> np.ndarray:
    """Cut clusters where lines of different directions meet.

    A stall line ends on the painted or kerb line it meets, a stop line on
    the lane line beside it: the pixel classifier joins them into one
    cluster whose centroid lies on neither, and the verifier judges the
    combined shape. Every pixel of a cluster that is not a straight stripe
    (its pixels spread across its major axis by more than ``min_spread_m``,
    which no single marking is) takes the direction of the longest straight
    run of marking pixels through it (:func:`_direction_bins`, within
    ``reach_m``), and the cluster is re-split into 8-connected parts whose
    neighbouring pixels differ in direction by less than ``angle_deg``.
    A gently curved line changes direction little from pixel to pixel and
    stays whole; at a junction the pixels take the direction of the line
    that runs through. A cut is kept only where it leaves two long thin
    strokes or more. Directions come from the cluster's pixels within
    ``reach_m`` of a pixel, so two tiles that both hold a cluster cut it alike.

    Parameters
    ----------
    rows, cols, lab : ndarray
        Marking pixels (array indices) and their cluster labels (> 0).
    resolution_m : float
        Metres per pixel.
    max_width_m : float
        Widest stroke, metres: wider blobs (a car roof) are not cut into strips.
    max_area_m2 : float
        Clusters with more pixels than this area are left alone: no group of
        markings that touch covers that much (a lot's border with fifty stall
        lines, about 60 m²), and the cost grows with the pixel count.

    Returns
    -------
    ndarray
        New labels for the pixels, 1..m.
    """
    lab = lab.astype(np.int64, copy=True)
    if lab.size == 0:
        return lab
    k = int(lab.max()) + 1
    x = cols + 0.5
    y = rows + 0.5
    n, _, _, dx, dy, ux, uy = _moments(lab, x, y, k)
    spread = np.sqrt(12.0 * _minor_var(lab, dx, dy, ux, uy, n, k)) * resolution_m
    branched = (spread > min_spread_m) & (n * resolution_m ** 2 <= max_area_m2)
    branched[0] = False
    if not branched.any():
        return lab
    sel = np.flatnonzero(branched[lab])
    r, c = rows[sel], cols[sel]
    # the selected clusters' pixels, dilated by one pixel, in their bounding
    # box with room for every sample position
    reach_px = max(2, int(round(reach_m / resolution_m)))
    pad = reach_px + 2
    r0, c0 = int(r.min()) - pad, int(c.min()) - pad
    mask = np.zeros((int(r.max()) - r0 + pad + 1, int(c.max()) - c0 + pad + 1), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            mask[r - r0 + dr, c - c0 + dc] = True
    bins, clear = _direction_bins(r - r0, c - c0, mask, reach_px, n_directions,
                                  max_width_m / resolution_m + 1.0)
    tol = int(angle_deg / (180.0 / n_directions))
    # Strokes are grown from the pixels whose direction is clear; pixels
    # whose direction is not (a chain of them could bridge two strokes at
    # any angle) then join the stroke of a neighbour, nearest in direction first.
    ls = lab[sel]
    part = _components(r, c, np.where(clear, ls, -1 - np.arange(ls.size)), bins,
                       n_directions, tol)
    # pixels farther from any clear pixel than half a marking's width are no
    # part of a stroke through it
    passes = int(math.ceil(0.5 * max_width_m / resolution_m)) + 1
    done = _adopt_neighbours(r, c, ls, bins, n_directions, part, clear, passes=passes)
    if not done.all():
        # pixels no clear stroke reached (a blob without one) stay together
        left = np.flatnonzero(~done)
        part[left] = part.max() + 1 + _components(r[left], c[left], ls[left])
    # A cut stands only where it leaves two strokes or more (a car roof's
    # corners look like strokes too, but it yields no two long thin parts).
    m = int(part.max()) + 1
    pn, _, _, pdx, pdy, pux, puy = _moments(part, c + 0.5, r + 0.5, m)
    smin, smax = _extent(part, pdx * pux[part] + pdy * puy[part], m)
    plen = (smax - smin + 1.0) * resolution_m
    pwidth = pn * resolution_m ** 2 / plen
    stroke = (plen >= 1.0) & (plen >= 3.0 * pwidth)
    ids, at = np.unique(part, return_index=True)
    strokes = np.bincount(ls[at], stroke[ids], k)  # each part lies in one cluster
    cut = strokes[ls] >= 2
    lab[sel[cut]] = k + part[cut]
    _, dense = np.unique(lab, return_inverse=True)
    return dense.reshape(-1) + 1


def _split_sparse(
    rows: np.ndarray,
    cols: np.ndarray,
    lab: np.ndarray,
    transform: Affine,
    max_length_m: float,
    split_factor: float,
    direction_step_deg: float,
    rounds: int = 4,
    whole_width_m: float | None = None,
    whole_max_length_m: float = 8.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Labels after cutting long clusters, and which pixels were cut; see :func:`split_long`."""
    lab = lab.astype(np.int64, copy=True)
    cut = np.zeros(lab.size, bool)
    if lab.size == 0:
        return lab, cut
    limit = split_factor * max_length_m
    step = math.radians(direction_step_deg)
    x, y = _pixel_world(transform, rows, cols)
    for _ in range(rounds):
        k = int(lab.max()) + 1
        n, mx, my, dx, dy, ux, uy = _moments(lab, x, y, k)
        smin, smax = _extent(lab, dx * ux[lab] + dy * uy[lab], k)
        extent = smax - smin
        long_ = extent > limit
        if whole_width_m is not None:
            res = _resolution(transform)
            width = n * res * res / np.maximum(extent + res, res)
            long_ &= ~((width >= whole_width_m) & (extent + res <= whole_max_length_m))
        long_[0] = False
        if not long_.any():
            break
        sel = np.flatnonzero(long_[lab])
        cut[sel] = True
        ls = lab[sel]
        theta = np.round(np.arctan2(uy, ux) / step) * step
        qx, qy = np.cos(theta), np.sin(theta)
        piece = np.floor((x[sel] * qx[ls] + y[sel] * qy[ls]) / max_length_m).astype(np.int64)
        piece -= piece.min()
        _, dense = np.unique(ls * (int(piece.max()) + 1) + piece, return_inverse=True)
        new = dense.reshape(-1) + 1
        # A cut can leave two parts of a curved line in one bin: give each part its own label.
        lab[sel] = k + _components(rows[sel], cols[sel], new)
    # Dense labels 1..m.
    _, dense = np.unique(lab, return_inverse=True)
    return dense.reshape(-1) + 1, cut


def split_long(
    labels: np.ndarray,
    transform: Affine,
    max_length_m: float = 3.0,
    split_factor: float = 1.2,
    direction_step_deg: float = 2.0,
    rounds: int = 4,
) -> tuple[np.ndarray, int]:
    """Cut clusters longer than ``split_factor * max_length_m`` into pieces.

    Each long cluster is cut perpendicular to its major axis (quantised to
    ``direction_step_deg``) at multiples of ``max_length_m`` measured from
    the CRS origin, so the cuts do not depend on which part of the line a
    tile sees. Curved clusters whose pieces are still too long are cut again
    along the pieces' own axes, up to ``rounds`` times.

    Returns
    -------
    labels : (H, W) int32
        New label image, 1..n.
    n : int
    """
    rows, cols = np.nonzero(labels)
    out = np.zeros(labels.shape, np.int32)
    if rows.size == 0:
        return out, 0
    lab, _ = _split_sparse(rows, cols, labels[rows, cols], transform, max_length_m, split_factor,
                           direction_step_deg, rounds)
    out[rows, cols] = lab
    return out, int(lab.max())


def _label_ids(lab: np.ndarray) -> np.ndarray:
    n = np.bincount(lab)
    ids = np.flatnonzero(n)
    return ids[ids > 0]


def join_collinear(
    rows: np.ndarray,
    cols: np.ndarray,
    lab: np.ndarray,
    transform: Affine,
    gap_m: float = 0.6,
    angle_deg: float = 12.0,
    offset_m: float = 0.12,
) -> np.ndarray:
    """Join clusters that continue each other: a marking broken by wear or shadow.

    Two elongated clusters are joined when their directions differ by at most
    ``angle_deg``, their facing ends are at most ``gap_m`` apart along the
    axis, and each facing end lies within ``offset_m`` of the other's axis
    (so parallel double lines stay apart).

    Parameters
    ----------
    rows, cols, lab : ndarray
        Marking pixels and their cluster labels (> 0).
    transform : Affine
        Pixel to CRS metres.

    Returns
    -------
    ndarray
        New labels for the pixels.
    """
    if lab.size == 0 or gap_m <= 0:
        return lab
    c = _measure(rows, cols, lab, np.zeros(lab.size), transform)
    ids = _label_ids(lab)
    elongated = c.length_m >= 2.5 * c.width_m
    idx = np.flatnonzero(elongated)
    if idx.size < 2:
        return lab
    ends, i, j, a, b = _aligned_end_pairs(c, idx, gap_m + offset_m, angle_deg)
    if len(i) == 0:
        return lab
    # Each end must face the other cluster: it is the end nearer to it.
    m = len(idx)
    pa, pb = ends[i], ends[j]
    far_a = ends[np.where(i < m, i + m, i - m)]
    far_b = ends[np.where(j < m, j + m, j - m)]
    gap = np.hypot(*(pa - pb).T)
    facing = (np.hypot(*(far_a - pb).T) >= gap) & (np.hypot(*(far_b - pa).T) >= gap)
    ua = pa - far_a
    ua /= np.maximum(np.hypot(*ua.T), 1e-9)[:, None]
    ub = pb - far_b
    ub /= np.maximum(np.hypot(*ub.T), 1e-9)[:, None]
    d = pb - pa
    along = d[:, 0] * ua[:, 0] + d[:, 1] * ua[:, 1]
    side_a = np.abs(d[:, 1] * ua[:, 0] - d[:, 0] * ua[:, 1])
    side_b = np.abs(d[:, 1] * ub[:, 0] - d[:, 0] * ub[:, 1])
    join = facing & (along >= -offset_m) & (along <= gap_m) & (side_a <= offset_m) \
        & (side_b <= offset_m)
    if not join.any():
        return lab
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(c)
    graph = coo_matrix((np.ones(int(join.sum()), np.int8), (a[join], b[join])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    # every cluster takes the label of the first cluster of its group
    first = np.full(comp.max() + 1, n, np.int64)
    np.minimum.at(first, comp, np.arange(n))
    roots = first[comp]
    lut = np.zeros(int(lab.max()) + 1, np.int64)
    lut[ids] = ids[roots]
    return lut[lab]


#: Names of the per-cluster context features of :func:`context_features`, in order.
CONTEXT_FEATURES: tuple[str, ...] = (
    "score",
    "width",
    "log_length",
    "spread_ratio",
    "brightness",
    "saturation",
    "contrast_near",
    "contrast_near_min",
    "side_difference_near",
    "contrast_far",
    "side_difference_far",
    "side_saturation_near",
    "side_saturation_difference",
    "side_saturation_far",
    "side_texture",
    "axis_brightness_spread",
)

#: Version of the context features; stored in verifier files and checked on load.
CONTEXT_VERSION = "1"

#: Distances of the side samples beyond a cluster's half width, metres. The
#: near one stays on the road surface between an edge line and its kerb
#: (0.25 m apart); the far one reaches past a kerb onto the sidewalk or grass.
SIDE_NEAR_M = 0.12
SIDE_FAR_M = 0.4
#: Samples along each cluster.
N_ALONG = 9


def context_features(
    clusters: Clusters,
    rgb: np.ndarray,
    valid: np.ndarray | None,
    transform: Affine,
) -> np.ndarray:
    """Shape and road-surface context of each cluster, for the cluster verifier.

    Paint is a thin, straight stripe on road surface that is darker than the
    paint and alike on both sides. A kerb has road on one side and sidewalk,
    grass or soil on the other; the outline of a car roof or windscreen is
    bent and lies on car paint. Each cluster is sampled along its axis
    (:data:`N_ALONG` points over its middle 80 %) and on both sides at
    :data:`SIDE_NEAR_M` and :data:`SIDE_FAR_M` beyond its half width;
    medians along the cluster make the side values robust to a car or a
    shadow over part of one side.

    Parameters
    ----------
    clusters : Clusters
        Measured clusters, in the CRS of ``transform``.
    rgb : (H, W, 3) uint8
        The image window the clusters were found in.
    valid : (H, W) bool or None
        False at nodata pixels (samples there are ignored).
    transform : Affine
        Pixel (col, row) of the window to CRS metres.

    Returns
    -------
    (N, F) float32
        Features named by :data:`CONTEXT_FEATURES`. Brightness is the channel
        mean (0–1), saturation max − min channel (0–1); lengths in metres.
    """
    n = len(clusters)
    nf = len(CONTEXT_FEATURES)
    if n == 0:
        return np.zeros((0, nf), np.float32)
    h, w = rgb.shape[:2]
    ok = np.ones((h, w), bool) if valid is None else np.asarray(valid, bool)
    inv = ~transform
    ux = (clusters.x1 - clusters.x0) / np.maximum(clusters.length_m, 1e-9)
    uy = (clusters.y1 - clusters.y0) / np.maximum(clusters.length_m, 1e-9)
    nx, ny = -uy, ux
    t = (np.arange(N_ALONG) + 0.5) / N_ALONG * 0.8 + 0.1  # middle 80 %
    px = clusters.x0[:, None] + (clusters.x1 - clusters.x0)[:, None] * t[None]
    py = clusters.y0[:, None] + (clusters.y1 - clusters.y0)[:, None] * t[None]

    def at(off: np.ndarray):
        x = px + nx[:, None] * off[:, None]
        y = py + ny[:, None] * off[:, None]
        col = inv.a * x + inv.b * y + inv.c
        row = inv.d * x + inv.e * y + inv.f
        return row.ravel(), col.ravel()

    lum_img = None
    sat_img = None

    def lum_sat(rows, cols):
        nonlocal lum_img, sat_img
        r = np.clip(np.floor(rows).astype(np.intp), 0, h - 1)
        c = np.clip(np.floor(cols).astype(np.intp), 0, w - 1)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        v = rgb[r, c].astype(np.float32)
        lum = v.mean(axis=1) / 255.0
        sat = (v.max(axis=1) - v.min(axis=1)) / 255.0
        bad = ~inside | ~ok[r, c]
        lum[bad] = np.nan
        sat[bad] = np.nan
        return lum.reshape(n, N_ALONG), sat.reshape(n, N_ALONG)

    half = clusters.width_m / 2
    axis_l, axis_s = lum_sat(*at(np.zeros(n)))
    sides = {}
    for name, d in (("near", SIDE_NEAR_M), ("far", SIDE_FAR_M)):
        for sgn in (1, -1):
            sides[name, sgn] = lum_sat(*at(sgn * (half + d)))

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN medians of masked samples
        med = {k: (np.nanmedian(v[0], axis=1), np.nanmedian(v[1], axis=1))
               for k, v in sides.items()}
        lin = np.nanmedian(axis_l, axis=1)
        sin_ = np.nanmedian(axis_s, axis=1)
        tex = np.fmax(np.nanstd(sides["near", 1][0], axis=1),
                      np.nanstd(sides["near", -1][0], axis=1))
        q = np.nanpercentile(axis_l, [20, 80], axis=1)
    a_l, a_s = med["near", 1]
    b_l, b_s = med["near", -1]
    fa_l, fa_s = med["far", 1]
    fb_l, fb_s = med["far", -1]
    f = np.empty((n, nf), np.float32)
    f[:, 0] = clusters.score
    f[:, 1] = clusters.width_m
    f[:, 2] = np.log(np.maximum(clusters.length_m, 1e-3))
    f[:, 3] = clusters.spread_m / np.maximum(clusters.width_m, 1e-3)
    f[:, 4] = lin
    f[:, 5] = sin_
    f[:, 6] = lin - np.fmax(a_l, b_l)
    f[:, 7] = lin - np.fmin(a_l, b_l)
    f[:, 8] = np.abs(a_l - b_l)
    f[:, 9] = lin - np.fmax(fa_l, fb_l)
    f[:, 10] = np.abs(fa_l - fb_l)
    f[:, 11] = np.fmax(a_s, b_s)
    f[:, 12] = np.abs(a_s - b_s)
    f[:, 13] = np.fmax(fa_s, fb_s)
    f[:, 14] = tex
    f[:, 15] = q[1] - q[0]
    # a side wholly outside the image or in nodata: no evidence either way
    return np.nan_to_num(f, nan=0.0)


#: Oriented crops of :func:`cluster_crops`: samples across and along each
#: cluster, and their spacing in metres (resolution-independent).
CROP_ACROSS = 16
CROP_ALONG = 32
CROP_STEP_M = 0.1
#: Image channels of a crop: luminance and saturation relative to the
#: crop's median, the pixel probability, and valid data.
CROP_CHANNELS: tuple[str, ...] = ("luminance", "saturation", "probability", "valid")
#: Per-cluster scalars given to the crop classifier beside the crop.
CROP_SCALARS: tuple[str, ...] = (
    "score", "width", "log_length", "spread_ratio", "resolution", "median_luminance",
    "median_saturation",
)
#: Pixel threshold of builds whose clusters the CNN verifier checks: lower
#: than the default, since the verifier removes what the lower threshold lets in.
CNN_PIXEL_THRESHOLD = 0.2
#: Hysteresis threshold of those builds: pixels above it join a cluster that
#: has pixels above :data:`CNN_PIXEL_THRESHOLD`, so a line keeps its faint
#: stretches (beside a car, in a shadow) and its ends. Chosen on the
#: validation scenes (``benchmarks/build_quality.py --verify --seed 5000``
#: and ``--seed 6000 --n 9``): 0.1 / 0.05 / 0.03 gave precision 0.964 /
#: 0.974 / 0.981 and 0.951 / 0.955 / 0.952, recall 0.934 / 0.943 / 0.955 and
#: 0.890 / 0.897 / 0.905, against 0.957 / 0.915 and 0.951 / 0.853 without;
#: 0.03 moved the second set's centroid RMSE from 4.4 to 6.0 cm, 0.05 to 5.1.
CNN_PIXEL_THRESHOLD_LOW = 0.05
#: Version of the crop definition; stored in CNN verifier files and checked on load.
CROP_VERSION = "1"


def _sum_and_range(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sum (uint16) and max − min (uint8) of the first three channels of ``px`` (..., C) uint8."""
    r, g, b = px[..., 0], px[..., 1], px[..., 2]
    total = r.astype(np.uint16)
    total += g
    total += b
    spread = np.maximum(np.maximum(r, g), b)
    spread -= np.minimum(np.minimum(r, g), b)
    return total, spread


def cluster_crops(
    clusters: Clusters,
    rgb: np.ndarray,
    valid: np.ndarray | None,
    transform: Affine,
    prob: np.ndarray,
    rotate_deg: np.ndarray | None = None,
    shift_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Oriented image crops around each cluster, for the CNN cluster verifier.

    Each crop is centred on the cluster's centroid, its rows run across the
    cluster and its columns along its major axis: :data:`CROP_ACROSS` x
    :data:`CROP_ALONG` samples :data:`CROP_STEP_M` apart (1.6 m x 3.2 m),
    bilinear, whatever the image's resolution. A kerb shows sidewalk or grass
    on one side, a car outline car paint and a bend; paint on road shows road
    on both sides and goes straight on.

    ``rotate_deg`` (N,) and ``shift_m`` (N, 2: along, across) turn and move
    each crop off the cluster's axis: training uses them so that the verifier
    tolerates the axis of a cluster that holds a little clutter.

    Returns
    -------
    crops : (N, C, CROP_ACROSS, CROP_ALONG) float32
        Channels :data:`CROP_CHANNELS`: luminance and saturation (channel mean
        and max − min, 0–255) minus their medians over the crop's valid samples,
        divided by 64; the probability; 1 at valid samples (0 outside the
        image and at nodata, where the other channels are 0).
    scalars : (N, S) float32
        :data:`CROP_SCALARS`: mean probability, width / 0.3 m, log length (m),
        spread / width, resolution / 0.1 m, and the medians (0–1).
    """
    n = len(clusters)
    nc, na, nx_ = len(CROP_CHANNELS), CROP_ACROSS, CROP_ALONG
    if n == 0:
        return (np.zeros((0, nc, na, nx_), np.float32),
                np.zeros((0, len(CROP_SCALARS)), np.float32))
    h, w = rgb.shape[:2]
    ux = (clusters.x1 - clusters.x0) / np.maximum(clusters.length_m, 1e-9)
    uy = (clusters.y1 - clusters.y0) / np.maximum(clusters.length_m, 1e-9)
    cx, cy = clusters.x, clusters.y
    if rotate_deg is not None:
        t = np.radians(np.asarray(rotate_deg, float))
        ux, uy = ux * np.cos(t) - uy * np.sin(t), ux * np.sin(t) + uy * np.cos(t)
    if shift_m is not None:
        sh = np.asarray(shift_m, float)
        cx = cx + sh[:, 0] * ux - sh[:, 1] * uy
        cy = cy + sh[:, 0] * uy + sh[:, 1] * ux
    inv = ~transform
    # pixel coordinates (col, row) of the centre and of one step along / across
    cc = inv.a * cx + inv.b * cy + inv.c - 0.5
    cr = inv.d * cx + inv.e * cy + inv.f - 0.5
    s = CROP_STEP_M
    a_c, a_r = (inv.a * ux + inv.b * uy) * s, (inv.d * ux + inv.e * uy) * s
    v_c, v_r = (inv.a * -uy + inv.b * ux) * s, (inv.d * -uy + inv.e * ux) * s
    jv = (np.arange(na, dtype=np.float64) - (na - 1) / 2)[None, :, None]
    ju = (np.arange(nx_, dtype=np.float64) - (nx_ - 1) / 2)[None, None, :]
    col = cc[:, None, None] + ju * a_c[:, None, None] + jv * v_c[:, None, None]
    row = cr[:, None, None] + ju * a_r[:, None, None] + jv * v_r[:, None, None]
    inside = (col > -0.5) & (col < w - 0.5) & (row > -0.5) & (row < h - 0.5)
    col = np.clip(col, 0, w - 1)
    row = np.clip(row, 0, h - 1)
    c0 = np.minimum(col.astype(np.intp), w - 2 if w > 1 else 0)
    r0 = np.minimum(row.astype(np.intp), h - 2 if h > 1 else 0)
    fc = (col - c0).astype(np.float32)
    fr = (row - r0).astype(np.float32)
    dc = 1 if w > 1 else 0
    dr = w if h > 1 else 0
    k00 = r0 * w + c0
    corners = (k00, k00 + dc, k00 + dr, k00 + dr + dc)
    wts = ((1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc)
    pflat = np.asarray(prob, np.float32).ravel()
    lum = np.zeros(col.shape, np.float32)
    sat = np.zeros(col.shape, np.float32)
    pr = np.zeros(col.shape, np.float32)
    if 2 * 4 * col.size < h * w:
        # A few clusters (a second look at some): the channel sum and max - min
        # at their corner pixels only, not over the window's millions of pixels.
        for k, wt in zip(corners, wts):
            lum_k, sat_k = _sum_and_range(rgb[k // w, k % w])
            lum += wt * lum_k
            sat += wt * sat_k
            pr += wt * pflat[k]
    else:
        # A tile's worth of clusters: channel sum and max - min of the window
        # once, then four gathers per sample.
        lum_w, sat_w = _sum_and_range(rgb)
        lum_w, sat_w = lum_w.ravel(), sat_w.ravel()
        for k, wt in zip(corners, wts):
            lum += wt * lum_w[k]
            sat += wt * sat_w[k]
            pr += wt * pflat[k]
    lum *= np.float32(1 / 3)
    ok = inside
    if valid is not None and not np.all(valid):
        vflat = np.asarray(valid, bool).ravel()
        ok = ok & vflat[corners[0]] & vflat[corners[1]] & vflat[corners[2]] & vflat[corners[3]]
    okf = ok.astype(np.float32)
    import warnings

    # Medians over each crop's valid samples; nanmedian (a sort) only for the
    # crops that reach past the image or into nodata, np.median (a partition)
    # for the rest.
    lum2, sat2, ok2 = lum.reshape(n, -1), sat.reshape(n, -1), ok.reshape(n, -1)
    full = ok2.all(axis=1)
    ml = np.empty(n, np.float64)
    ms = np.empty(n, np.float64)
    ml[full] = np.median(lum2[full], axis=1)
    ms[full] = np.median(sat2[full], axis=1)
    if not full.all():
        part = ~full
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a crop wholly in nodata
            ml[part] = np.nanmedian(np.where(ok2[part], lum2[part], np.nan), axis=1)
            ms[part] = np.nanmedian(np.where(ok2[part], sat2[part], np.nan), axis=1)
    ml = np.nan_to_num(ml, nan=0.0).astype(np.float32)
    ms = np.nan_to_num(ms, nan=0.0).astype(np.float32)
    crops = np.empty((n, nc, na, nx_), np.float32)
    crops[:, 0] = (lum - ml[:, None, None]) * np.float32(1 / 64) * okf
    crops[:, 1] = (sat - ms[:, None, None]) * np.float32(1 / 64) * okf
    crops[:, 2] = pr * okf
    crops[:, 3] = okf
    res = _resolution(transform)
    sc = np.empty((n, len(CROP_SCALARS)), np.float32)
    sc[:, 0] = clusters.score
    sc[:, 1] = clusters.width_m / 0.3
    sc[:, 2] = np.log(np.maximum(clusters.length_m, 1e-3))
    sc[:, 3] = clusters.spread_m / np.maximum(clusters.width_m, 1e-3)
    sc[:, 4] = res / 0.1
    sc[:, 5] = ml / 255.0
    sc[:, 6] = ms / 255.0
    return crops, sc


def halves_accepted(clusters: Clusters, rejected: np.ndarray, verifier, rgb: np.ndarray,
                    valid: np.ndarray | None, transform: Affine, prob: np.ndarray,
                    min_length_m: float = 2.0, threshold: float = 0.5,
                    max_width_m: float | None = None) -> np.ndarray:
    """Rejected long clusters the verifier accepts on one of their halves.

    Crops centred a quarter of the length before and after the centroid (on
    the cluster's axis) are scored for each rejected cluster at least
    ``min_length_m`` long; see :attr:`ClusterParams.verify_halves_m`. Only
    CNN verifiers (``verifier.kind == "crops"``) are asked; others accept nothing.

    Returns
    -------
    (N,) bool
        True where a half is accepted (above ``threshold``).
    """
    out = np.zeros(len(clusters), bool)
    if getattr(verifier, "kind", None) != "crops":
        return out
    cand = np.asarray(rejected, bool) & (clusters.length_m >= min_length_m)
    if max_width_m is not None:
        cand &= clusters.width_m < max_width_m
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return out
    sub = clusters.take(idx)
    best = np.zeros(idx.size, np.float32)
    for sign in (-1.0, 1.0):
        shift = np.column_stack([sign * sub.length_m / 4, np.zeros(idx.size)])
        crops, scalars = cluster_crops(sub, rgb, valid, transform, prob, shift_m=shift)
        best = np.maximum(best, verifier.predict_crops(crops, scalars))
    out[idx] = best > threshold
    log.debug("%d of %d rejected long clusters accepted on a half", int(out.sum()), idx.size)
    return out


def continues_accepted(clusters: Clusters, keep: np.ndarray, gap_m: float = 0.6,
                       angle_deg: float = 10.0, offset_m: float = 0.1,
                       rounds: int = 3, prob: np.ndarray | None = None,
                       min_prob: float = 0.0) -> np.ndarray:
    """Keep rejected clusters that continue an accepted one: pieces of one line.

    A solid line is cut into pieces that the verifier judges one by one; a
    piece it doubts, between or beside pieces it accepts, is paint too. A
    rejected cluster is taken back when one of its ends lies within ``gap_m``
    of an end of an accepted cluster of the same direction (within
    ``angle_deg``), and each lies within ``offset_m`` of the other's axis
    there. Repeated ``rounds`` times, so a line is taken back piece by piece.
    With ``prob``, the verifier's probability of each cluster, only clusters
    with at least ``min_prob`` are taken back: the verifier doubts the pieces
    of a line it accepts elsewhere, but rejects the pieces of a kerb or lot
    border outright, even where it accepts one of them.

    Returns
    -------
    (N,) bool
        ``keep`` with the clusters taken back.
    """
    keep = np.asarray(keep, bool).copy()
    n = len(clusters)
    if n < 2 or keep.all() or not keep.any():
        return keep
    ends, i, j, a, b = _aligned_end_pairs(clusters, np.arange(n), gap_m, angle_deg)
    if len(i) == 0:
        return keep
    length = np.maximum(clusters.length_m, 1e-9)
    ux = (clusters.x1 - clusters.x0) / length
    uy = (clusters.y1 - clusters.y0) / length

    def side(k, p):
        """Distance of points p from the axis of clusters k."""
        dx, dy = p[:, 0] - clusters.x[k], p[:, 1] - clusters.y[k]
        return np.abs(dx * uy[k] - dy * ux[k])

    ok = (side(a, ends[j]) <= offset_m) & (side(b, ends[i]) <= offset_m)
    a, b = a[ok], b[ok]
    if len(a) == 0:
        return keep
    a, b = np.concatenate([a, b]), np.concatenate([b, a])
    eligible = np.ones(n, bool) if prob is None else np.asarray(prob) >= min_prob
    for _ in range(rounds):
        back = np.zeros(n, bool)
        back[a[keep[b] & ~keep[a] & eligible[a]]] = True
        if not back.any():
            break
        keep |= back
    return keep


def _aligned_end_pairs(c: Clusters, idx: np.ndarray, radius_m: float, angle_deg: float):
    """End points of different clusters among ``idx`` within ``radius_m`` whose axes agree.

    Returns ``(ends, i, j, a, b)``: the ``(2 len(idx), 2)`` end points (first
    ends, then second ends), the indices of each pair's two end points into
    them and the two clusters (indices into ``c``), for pairs whose bearings
    differ by at most ``angle_deg``.
    """
    from scipy.spatial import cKDTree

    ends = np.concatenate([np.column_stack([c.x0[idx], c.y0[idx]]),
                           np.column_stack([c.x1[idx], c.y1[idx]])])  # fmt: skip
    owner = np.concatenate([idx, idx])
    pairs = cKDTree(ends).query_pairs(radius_m, output_type="ndarray").reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    a, b = owner[i], owner[j]
    diff = np.abs(c.bearing_deg[a] - c.bearing_deg[b]) % 180.0
    ok = (a != b) & (np.minimum(diff, 180.0 - diff) <= angle_deg)
    return ends, i[ok], j[ok], a[ok], b[ok]


def extend_to_junctions(clusters: Clusters, transform: Affine, angle_deg: float = 30.0,
                        gap_m: float | None = None, min_line_m: float = 1.0) -> Clusters:
    """Move the ends of markings that end on another marking to that marking's axis.

    Where a stroke meets a line running across it (a T junction), the pixels
    they share go to one cluster only (:func:`split_junctions`, or a separate
    cluster from the start), so the stroke's end is measured at the near edge
    of the line it meets. An end qualifies when the stroke's axis, prolonged
    outwards, reaches the other cluster's axis within that cluster's half
    width (measured along the stroke) plus ``gap_m``, at a point inside the
    other's extent (or in the gap the stroke leaves in it), and the two
    directions differ by at least ``angle_deg``.
    The end moves to the crossing point; the centroid (the middle of the
    extent) and the length follow. Width and pixel count are unchanged.

    Parameters
    ----------
    clusters : Clusters
        Measured markings of one window.
    transform : Affine
        Pixel (col, row) to CRS metres, for the centroid's pixel coordinates.
    angle_deg : float
        Smallest difference of direction of a junction, degrees.
    gap_m : float, optional
        Largest gap between the end and the other's edge, metres; default two pixels.
    min_line_m : float
        The other cluster must be at least this long, and twice the width of
        the one that ends on it, metres (not a sliver left at a corner).
    """
    from scipy.spatial import cKDTree

    n = len(clusters)
    if n < 2:
        return clusters
    if not 0.0 < angle_deg <= 90.0:
        raise ValueError(f"angle_deg must be in (0, 90], got {angle_deg}")
    res = _resolution(transform)
    gap = 2.0 * res if gap_m is None else gap_m
    c = clusters
    length = np.maximum(c.length_m, 1e-9)
    ux, uy = (c.x1 - c.x0) / length, (c.y1 - c.y0) / length
    ends = np.concatenate([np.column_stack([c.x0, c.y0]), np.column_stack([c.x1, c.y1])])
    owner = np.concatenate([np.arange(n), np.arange(n)])
    sign = np.concatenate([-np.ones(n), np.ones(n)])  # outward along the axis
    ox, oy = sign * ux[owner], sign * uy[owner]
    # Each line long enough to be ended on looks for the ends near it: by the
    # conditions below an end that qualifies lies within half the line's length
    # plus both half widths over the sine of the angle plus two gaps of its centroid.
    lines = np.flatnonzero(c.length_m >= min_line_m)
    if lines.size == 0:
        return clusters
    inv_sin = 1.0 / math.sin(math.radians(angle_deg))
    reach = (0.5 * c.length_m[lines] + 0.5 * inv_sin * (c.width_m[lines] + float(np.max(c.width_m)))
             + 2.0 * gap)
    near = cKDTree(ends).query_ball_point(np.column_stack([c.x[lines], c.y[lines]]), reach)
    b = np.repeat(lines, [len(v) for v in near])
    e_idx = np.fromiter((j for v in near for j in v), np.int64, b.size)
    keep = owner[e_idx] != b
    e_idx, b = e_idx[keep], b[keep]
    if e_idx.size == 0:
        return clusters
    # Crossing of the prolonged axis e + t u with b's axis c_b + s v.
    vx, vy = ux[b], uy[b]
    cross = ox[e_idx] * vy - oy[e_idx] * vx
    sin = np.abs(cross)
    ok = sin >= math.sin(math.radians(angle_deg))
    dx, dy = c.x[b] - ends[e_idx, 0], c.y[b] - ends[e_idx, 1]
    safe = np.where(ok, cross, 1.0)
    t = (dx * vy - dy * vx) / safe
    s_ = (dx * oy[e_idx] - dy * ox[e_idx]) / safe
    ok &= (t > 0) & (t <= 0.5 * c.width_m[b] / np.maximum(sin, 1e-9) + gap)
    # The line the end meets lost its pixels under the stroke too: the crossing
    # may lie in that gap, up to half the stroke's width past the line's end.
    ok &= np.abs(s_) <= 0.5 * c.length_m[b] + 0.5 * c.width_m[owner[e_idx]] / np.maximum(sin, 1e-9) + gap
    # What a marking ends on is a line, not a sliver of a corner.
    ok &= c.length_m[b] >= np.maximum(min_line_m, 2.0 * c.width_m[owner[e_idx]])
    if not ok.any():
        return clusters
    e_idx, t = e_idx[ok], t[ok]
    # The nearest crossing of each end.
    order = np.lexsort((t, e_idx))
    e_idx, t = e_idx[order], t[order]
    first = np.ones(e_idx.size, bool)
    first[1:] = e_idx[1:] != e_idx[:-1]
    e_idx, t = e_idx[first], t[first]
    ends[e_idx, 0] += t * ox[e_idx]
    ends[e_idx, 1] += t * oy[e_idx]
    out = clusters.take(np.arange(n))
    out.x0, out.y0 = ends[:n, 0], ends[:n, 1]
    out.x1, out.y1 = ends[n:, 0], ends[n:, 1]
    out.x = 0.5 * (out.x0 + out.x1)
    out.y = 0.5 * (out.y0 + out.y1)
    out.length_m = np.hypot(out.x1 - out.x0, out.y1 - out.y0)
    out.col, out.row = _world_pixel(transform, out.x, out.y)
    log.debug("extend_to_junctions: %d ends moved", e_idx.size)
    return out


def filter_clusters(clusters: Clusters, params: ClusterParams) -> Clusters:
    """Keep clusters whose shape a lane marking can have."""
    area = clusters.width_m * clusters.length_m
    ok = (
        (clusters.width_m >= params.min_width_m)
        & (clusters.width_m <= params.max_width_m)
        & (clusters.length_m >= params.min_length_m)
        & (area >= params.min_area_m2)
    )
    return clusters.take(ok)


def detect_markings(
    prob: np.ndarray,
    valid: np.ndarray | None,
    transform: Affine,
    params: ClusterParams | None = None,
    rgb: np.ndarray | None = None,
    verifier=None,
    pixel_share: np.ndarray | None = None,
) -> Clusters:
    """Probability image → measured, filtered markings (cluster, split, measure, filter).

    Parameters
    ----------
    prob : (H, W) float
        Probability of "marking" per pixel.
    valid : (H, W) bool or None
        Pixels that may be marking pixels.
    transform : Affine
        Pixel (col, row) of ``prob`` to CRS metres.
    params : ClusterParams, optional
    rgb : (H, W, 3) uint8, optional
        The image window of ``prob``; needed by the verifier.
    verifier : object, optional
        Has ``predict(features) -> (N,) probability`` over :data:`CONTEXT_FEATURES`
        (:class:`mapbuilder.classify.ClusterVerifier`); with ``rgb`` and
        ``params.verify`` it keeps the clusters it scores above
        ``params.verify_threshold``.
    pixel_share : (H, W) bool, optional
        A mask (e.g. painted pixels, for training labels): the result then has
        an attribute ``share``, the share of each cluster's pixels on it.
    """
    params = params or ClusterParams()
    res = _resolution(transform)
    link_px = int(round(params.link_m / res)) if params.link_m > 0 else 0
    labels, n = label_pixels(prob, valid, params.threshold, link_px, params.threshold_low)
    if n == 0:
        return Clusters.empty()
    # Work on the marking pixels only: a few percent of the window.
    flat = labels.ravel()
    idx = np.flatnonzero(flat != 0)
    lab = flat[idx].astype(np.int64)
    # Shapes too small to be anything are dropped before the more costly steps.
    min_px = max(1, int(params.min_area_m2 / (res * res)))
    keep = np.bincount(lab, minlength=n + 1)[lab] >= min_px
    idx, lab = idx[keep], lab[keep]
    if idx.size == 0:
        return Clusters.empty()
    rows, cols = np.divmod(idx, labels.shape[1])
    if params.junction_angle_deg is not None:
        lab = split_junctions(rows, cols, lab, res, params.junction_angle_deg,
                              max_width_m=params.max_width_m)
    if params.join_gap_m > 0:
        lab = join_collinear(rows, cols, lab, transform, params.join_gap_m,
                             params.join_angle_deg, params.join_offset_m)
    lab, cut = _split_sparse(rows, cols, lab, transform, params.max_length_m, params.split_factor,
                             params.direction_step_deg, whole_width_m=params.whole_width_m,
                             whole_max_length_m=params.whole_max_length_m)
    clusters = _measure(rows, cols, lab, prob.ravel()[idx], transform, cut)
    if pixel_share is not None:
        # share of each cluster's pixels that lie on the given mask (labels are 1..m)
        on = np.asarray(pixel_share, bool).ravel()[idx]
        clusters.share = (np.bincount(lab, on, lab.max() + 1)
                          / np.maximum(np.bincount(lab, minlength=lab.max() + 1), 1))[1:]
    clusters = filter_clusters(clusters, params)
    if verifier is not None and rgb is not None and params.verify and len(clusters):
        if hasattr(verifier, "predict_clusters"):
            p = verifier.predict_clusters(clusters, rgb, valid, transform, prob)
        else:
            p = verifier.predict(context_features(clusters, rgb, valid, transform))
        keep = p > params.verify_threshold
        if params.verify_halves_m > 0 and hasattr(verifier, "predict_clusters"):
            keep |= halves_accepted(clusters, ~keep, verifier, rgb, valid, transform, prob,
                                    params.verify_halves_m, params.verify_threshold)
        if params.verify_continuation:
            keep = continues_accepted(clusters, keep, prob=p,
                                      min_prob=params.verify_continuation_min)
        clusters = clusters.take(keep)
    if params.extend_junctions and params.junction_angle_deg is not None:
        clusters = extend_to_junctions(clusters, transform, params.junction_angle_deg)
    return clusters

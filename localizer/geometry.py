"""2D rigid transforms, the weighted rigid fit, a request-local view of the map.

The nearest-marking lookup over that view is compiled (numba).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .index import MapIndex


def rotation(yaw: float) -> np.ndarray:
    """2x2 rotation matrix of ``yaw`` radians (counter-clockwise)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def apply(pose, pts: np.ndarray) -> np.ndarray:
    """Map vehicle-frame points ``(N, 2)`` through ``pose = (x, y, yaw)``: ``R(yaw) p + t``."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.empty_like(pts)
    out[:, 0] = c * pts[:, 0] - s * pts[:, 1] + x
    out[:, 1] = s * pts[:, 0] + c * pts[:, 1] + y
    return out


def homogeneous(pose) -> np.ndarray:
    """3x3 homogeneous matrix of ``pose = (x, y, yaw)`` (vehicle → map)."""
    m = np.eye(3)
    m[:2, :2] = rotation(pose[2])
    m[:2, 2] = pose[:2]
    return m


def weighted_rigid_fit(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray]:
    """Closed-form weighted 2D Procrustes (Kabsch without reflection).

    Minimises ``sum_j w_j |R(theta) src_j + t - dst_j|**2``.

    Parameters
    ----------
    src, dst : (N, 2) ndarray
        Paired points, metres.
    w : (N,) ndarray
        Non-negative weights; at least one positive.

    Returns
    -------
    theta : float
        Rotation, radians counter-clockwise.
    t : (2,) ndarray
        Translation, metres.
    """
    ws = w / w.sum()
    cs = ws @ src
    cd = ws @ dst
    a = src - cs
    b = dst - cd
    sxx = np.sum(ws * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    sxy = np.sum(ws * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    theta = math.atan2(sxy, sxx) if (sxx or sxy) else 0.0
    t = cd - rotation(theta) @ cs
    return theta, t


def compose(delta_theta: float, delta_t: np.ndarray, pose) -> tuple[float, float, float]:
    """Left-compose a map-frame increment ``(R(dθ), dt)`` with ``pose``."""
    x, y, yaw = pose
    c, s = math.cos(delta_theta), math.sin(delta_theta)
    return (
        c * x - s * y + float(delta_t[0]),
        s * x + c * y + float(delta_t[1]),
        yaw + delta_theta,
    )


#: Where an unmatched point's target lies (metres): so far away that it never matches.
_FAR = 1e12 + 0j
#: Cell of the bucket grid that finds a request's nearest markings, metres: a
#: few markings per cell on a road, so that most lookups read nine cells.
GRID_CELL_M = 2.0
#: Nearest centroids whose marking (point or segment) is examined per lookup.
NEAREST_CENTROIDS = 3


class LocalMap:
    """The markings around one request, in coordinates relative to ``origin``.

    Working relative to an origin near the vehicle keeps the numerics well
    conditioned (UTM northings are ~5e6 m). The markings are bucketed in a
    grid of :data:`GRID_CELL_M` cells, which the compiled lookups
    (:func:`closest_points`) and the refinement's inner loop read.
    """

    def __init__(self, index: MapIndex, origin, radius: float):
        self.origin = np.asarray(origin, float)
        self._index = index
        sel = index.near(self.origin, radius)
        self.indices = sel
        self.xy = index.xy[sel] - self.origin
        self.axis = index.axis[sel]
        self.half = index.half_length[sel]
        self.max_half = float(self.half.max()) if sel.size else 0.0
        # Complex tables of the markings: centroid, conjugate axis (0 for
        # point-like markings), half length.
        self._c = np.ascontiguousarray(self.xy[:, 0] + 1j * self.xy[:, 1])
        self._uc = np.ascontiguousarray(self.axis[:, 0] - 1j * self.axis[:, 1])
        self._h = np.ascontiguousarray(self.half, float)
        # What the compiled lookups take: the tables and their bucket grid.
        self.tables = (self._c, self._uc, self._h, self.max_half) + _bucket_grid(self._c, GRID_CELL_M)
        if index.expect_xy is not None and sel.size:
            keep = index.expect_of(sel)
            self.expect_xy = index.expect_xy[keep] - self.origin
            self.expect_solid = index.expect_solid[keep]
            self.expect_axis = index.axis[index.expect_owner[keep]]  # zeros for point markings
        else:
            self.expect_xy = np.zeros((0, 2))
            self.expect_solid = np.zeros(0, bool)
            self.expect_axis = np.zeros((0, 2))

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def nearest_centroid(self, p: np.ndarray, max_dist: float):
        """Nearest map centroid of each point (the paper's pairing): ``(distance, target)``.

        Queries the map's own KD-tree (built once per map), so the pairing may
        reach markings just outside this neighbourhood. ``target`` holds the
        centroid in local coordinates; distance inf and target NaN beyond
        ``max_dist``.
        """
        p = np.asarray(p, float).reshape(-1, 2)
        d = np.full(len(p), np.inf)
        target = np.full((len(p), 2), np.nan)
        if len(self._index):
            d, i = self._index.tree.query(p + self.origin, distance_upper_bound=max_dist)
            hit = np.isfinite(d)
            target[hit] = self._index.xy[i[hit]] - self.origin
        return d, target

    def closest_c(self, p: np.ndarray, max_dist: float, full: bool = True):
        """:meth:`closest` of complex points ``p`` (x + iy, (N,)).

        Returns ``(dist, target, axis, index)``: complex targets, the complex unit
        axis of the matched marking (0 for point-like markings and no match) and
        the local index, ``len(self)`` where nothing lies within ``max_dist``;
        only ``(dist, target)`` unless ``full``.
        """
        p = np.ascontiguousarray(p, complex).ravel()
        d, tgt, i = closest_points(p, float(max_dist), self.tables)
        if not full:
            return d, tgt
        axis = np.zeros(len(p), complex)
        hit = i < len(self)
        axis[hit] = self._uc[i[hit]].conjugate()
        return d, tgt, axis, i

    def closest(self, p: np.ndarray, max_dist: float, return_index: bool = False):
        """Closest map point of each of ``p`` (segments for line-like markings).

        Of the (at most) three nearest centroids within ``max_dist`` plus the
        longest half length, the marking whose centroid or segment lies closest.

        Returns
        -------
        dist : (N,) ndarray
            inf where nothing lies within ``max_dist``.
        target : (N, 2) ndarray
            The closest point on the matched marking.
        normal : (N, 2) ndarray
            Unit normal of a matched segment, zeros for point matches.
        index : (N,) ndarray
            Local index of the matched marking, -1 where unmatched (if ``return_index``).
        """
        p = np.asarray(p, float)
        n = len(p)
        pc = np.empty(n, complex)
        pc.real, pc.imag = p[:, 0], p[:, 1]
        d, tgt, u, i = self.closest_c(pc, max_dist)
        ok = np.isfinite(d)
        target = np.zeros((n, 2))
        target[ok, 0], target[ok, 1] = tgt.real[ok], tgt.imag[ok]
        normal = np.zeros((n, 2))
        normal[ok, 0], normal[ok, 1] = -u.imag[ok], u.real[ok]
        if return_index:
            return d, target, normal, np.where(ok, i, -1)
        return d, target, normal


def _bucket_grid(c: np.ndarray, cell: float) -> tuple:
    """The markings' centroids ``c`` (complex) bucketed in square cells of ``cell`` metres.

    Returns ``(x0, y0, cell, nx, ny, start, items)``: cell ``(i, j)`` (row ``i``
    along y, from ``y0``; column ``j`` along x, from ``x0``) holds the markings
    ``items[start[i * nx + j]:start[i * nx + j + 1]]``.
    """
    if c.size == 0:
        return 0.0, 0.0, cell, 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int64)
    x0, y0 = float(c.real.min()), float(c.imag.min())
    nx = int((c.real.max() - x0) // cell) + 1
    ny = int((c.imag.max() - y0) // cell) + 1
    ids = ((c.imag - y0) // cell).astype(np.int64) * nx + ((c.real - x0) // cell).astype(np.int64)
    items = np.argsort(ids, kind="stable").astype(np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(np.bincount(ids, minlength=nx * ny), out=start[1:])
    return x0, y0, float(cell), nx, ny, start, items


@njit(cache=True, nogil=True, inline="always")
def keep_nearest(best_d, best_i, found, k, d2, i):
    """Offer item ``i`` at squared distance ``d2`` to the ``k`` nearest so far; their new count.

    ``best_d[:found]`` stays sorted, nearest first (ties keep the earlier).
    """
    if found == k and d2 >= best_d[k - 1]:
        return found
    q = min(found, k - 1)
    while q > 0 and best_d[q - 1] > d2:
        best_d[q] = best_d[q - 1]
        best_i[q] = best_i[q - 1]
        q -= 1
    best_d[q] = d2
    best_i[q] = i
    return min(found + 1, k)


@njit(cache=True, nogil=True)
def nearest_marking(p, tables, best_i, best_d):
    """The marking closest to point ``p`` among its nearest centroids (compiled).

    Of the :data:`NEAREST_CENTROIDS` centroids nearest to ``p`` within the
    search radius, the marking that lies closest: a point, or for a line-like
    marking the closest point of its segment. The grid is read ring by ring
    around ``p``'s cell until no unread cell can hold a nearer centroid.

    Parameters
    ----------
    p : complex
        The point, x + iy, metres in the local frame.
    tables : tuple
        :attr:`LocalMap.tables`.
    best_i, best_d : (NEAREST_CENTROIDS,) int64 / float64 arrays
        Scratch space; on entry ``best_d[0]`` holds the squared search radius
        (m²): the longest distance of interest plus the longest half length,
        so that no segment reaching within that distance is missed.

    Returns
    -------
    dist : float
        Distance to the marking, metres; inf when no centroid lies within the radius.
    e : complex
        From the marking's closest point to ``p``.
    index : int
        The marking's local index, ``len(c)`` when none.
    """
    c, uc, h, max_half, x0, y0, cell, nx, ny, start, items = tables
    k = min(NEAREST_CENTROIDS, c.size)
    r2max = best_d[0]
    for q in range(k):
        best_d[q] = np.inf
        best_i[q] = -1
    found = 0
    fx = (p.real - x0) / cell
    fy = (p.imag - y0) / cell
    reach = math.sqrt(r2max)
    if not (abs(fx) < 1e9 and abs(fy) < 1e9):  # also NaN: no cell to start from
        return np.inf, 0j, c.size
    cj, ci = int(math.floor(fx)), int(math.floor(fy))
    r = 0
    while True:
        if r > 0:
            # Every unread cell lies at least (r - 1) cells away.
            lb = (r - 1) * cell
            if lb > reach or (found == k and lb * lb >= best_d[k - 1]):
                break
            if ci - r < 0 and ci + r >= ny and cj - r < 0 and cj + r >= nx:
                break
        for ii in range(max(ci - r, 0), min(ci + r, ny - 1) + 1):
            edge = ii == ci - r or ii == ci + r
            jj = max(cj - r, 0)
            while jj <= min(cj + r, nx - 1):
                if not edge and jj != cj - r and jj != cj + r:
                    jj = cj + r  # inside the ring's rows only its two ends are new
                    continue
                cid = ii * nx + jj
                for t in range(start[cid], start[cid + 1]):
                    m = items[t]
                    dz = p - c[m]
                    d2 = dz.real * dz.real + dz.imag * dz.imag
                    if d2 <= r2max:
                        found = keep_nearest(best_d, best_i, found, k, d2, m)
                jj += 1
        r += 1
    dist = np.inf
    e = 0j
    idx = c.size
    for q in range(found):
        m = best_i[q]
        rr = p - c[m]
        a = (rr * uc[m]).real
        if a > h[m]:
            a = h[m]
        elif a < -h[m]:
            a = -h[m]
        ee = rr - a * uc[m].conjugate()
        de = abs(ee)
        if de < dist:
            dist, e, idx = de, ee, m
    return dist, e, idx


@njit(cache=True, nogil=True)
def closest_points(p, max_dist, tables):
    """:func:`nearest_marking` of each of the complex points ``p`` (N,), compiled.

    Returns ``(dist, target, index)``: ``dist`` inf beyond ``max_dist``,
    ``target`` the closest point of the marking (far away where nothing lies
    within reach), ``index`` ``len(c)`` where nothing does.
    """
    n = p.size
    max_half = tables[3]
    dist = np.empty(n)
    tgt = np.empty(n, np.complex128)
    idx = np.empty(n, np.int64)
    best_i = np.empty(NEAREST_CENTROIDS, np.int64)
    best_d = np.empty(NEAREST_CENTROIDS)
    reach2 = (max_dist + max_half) ** 2
    for j in range(n):
        best_d[0] = reach2
        d, e, m = nearest_marking(p[j], tables, best_i, best_d)
        dist[j] = d if d <= max_dist else np.inf
        tgt[j] = p[j] - e if m < tables[0].size else _FAR
        idx[j] = m
    return dist, tgt, idx

"""2D rigid transforms, the weighted rigid fit, and a request-local view of the map."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

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


#: Where the missing-neighbour row of :class:`LocalMap`'s tables lies (metres).
_FAR = 1e12 + 0j


class LocalMap:
    """The markings around one request, in coordinates relative to ``origin``.

    Working relative to an origin near the vehicle keeps the numerics well
    conditioned (UTM northings are ~5e6 m).
    """

    def __init__(self, index: MapIndex, origin, radius: float):
        self.origin = np.asarray(origin, float)
        self._offsets: dict[tuple[int, int], np.ndarray] = {}
        sel = index.near(self.origin, radius)
        self.indices = sel
        self.xy = index.xy[sel] - self.origin
        self.axis = index.axis[sel]
        self.half = index.half_length[sel]
        self.max_half = float(self.half.max()) if sel.size else 0.0
        # Complex tables of the markings (centroid, conjugate axis, half length),
        # one row more than markings: the KD-tree reports a missing neighbour as
        # index len(self), and that row lies so far away that it never matches.
        # Complex arithmetic halves the number of numpy calls on the small
        # arrays of each refinement iteration, which is what they cost.
        self._c = np.append(self.xy[:, 0] + 1j * self.xy[:, 1], _FAR)
        self._uc = np.append(self.axis[:, 0] - 1j * self.axis[:, 1], 0j)
        self._h = np.append(self.half, 0.0)
        self._nh = -self._h
        self.tree = cKDTree(self.xy) if sel.size else None
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
        """Nearest centroid of each point: ``(distance, index)``, inf/-1 beyond ``max_dist``."""
        if self.tree is None:
            return np.full(len(p), np.inf), np.full(len(p), -1)
        d, i = self.tree.query(p, distance_upper_bound=max_dist)
        i = np.where(np.isfinite(d), i, -1)
        return d, i

    def closest_c(self, p: np.ndarray, max_dist: float, full: bool = True):
        """:meth:`closest` of complex points ``p`` (x + iy, contiguous (N,)).

        Returns ``(dist, target, axis, index)``: complex targets, the complex unit
        axis of the matched marking (0 for point-like markings and no match) and
        the local index, ``len(self)`` where nothing lies within ``max_dist``;
        only ``(dist, target)`` unless ``full``.
        """
        p = np.ascontiguousarray(p, complex)
        n = len(p)
        if self.tree is None or n == 0:
            out = np.full(n, np.inf), np.zeros(n, complex), np.zeros(n, complex), np.full(n, len(self))
            return out if full else out[:2]
        pr = p.view(float).reshape(n, 2)
        if self.max_half == 0.0:
            d, i = self.tree.query(pr, distance_upper_bound=max_dist)
            return (d, self._c[i], np.zeros(n, complex), i) if full else (d, self._c[i])
        k = min(3, len(self))
        _, ii = self.tree.query(pr, k=k, distance_upper_bound=max_dist + self.max_half)
        if k == 1:
            ii = ii[:, None]
        r = p[:, None] - self._c[ii]  # from the marking's centroid to p
        uc = self._uc[ii]
        # Position along the marking's axis, clipped to its half length (0 for points).
        a = np.minimum(np.maximum((r * uc).real, self._nh[ii]), self._h[ii])
        e = r - a * uc.conjugate()  # from the closest point of the marking to p
        dist = np.abs(e)
        best = dist.argmin(axis=1)
        best += self._row_offsets(n, k)
        d = dist.ravel()[best]
        d[d > max_dist] = np.inf
        if not full:
            return d, p - e.ravel()[best]
        return d, p - e.ravel()[best], uc.ravel()[best].conjugate(), ii.ravel()[best]

    def _row_offsets(self, n: int, k: int) -> np.ndarray:
        off = self._offsets.get((n, k))
        if off is None:
            off = self._offsets[(n, k)] = np.arange(n) * k
        return off

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

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


class LocalMap:
    """The markings around one request, in coordinates relative to ``origin``.

    Working relative to an origin near the vehicle keeps the numerics well
    conditioned (UTM northings are ~5e6 m).
    """

    def __init__(self, index: MapIndex, origin, radius: float):
        self.origin = np.asarray(origin, float)
        sel = index.near(self.origin, radius)
        self.indices = sel
        self.xy = index.xy[sel] - self.origin
        self.axis = index.axis[sel]
        self.half = index.half_length[sel]
        self.max_half = float(self.half.max()) if sel.size else 0.0
        self._x, self._y = self.xy[:, 0].copy(), self.xy[:, 1].copy()
        self._ux, self._uy = self.axis[:, 0].copy(), self.axis[:, 1].copy()
        self.tree = cKDTree(self.xy) if sel.size else None
        if index.expect_xy is not None and sel.size:
            keep = index.expect_of(sel)
            self.expect_xy = index.expect_xy[keep] - self.origin
            self.expect_solid = index.expect_solid[keep]
        else:
            self.expect_xy = np.zeros((0, 2))
            self.expect_solid = np.zeros(0, bool)

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def nearest_centroid(self, p: np.ndarray, max_dist: float):
        """Nearest centroid of each point: ``(distance, index)``, inf/-1 beyond ``max_dist``."""
        if self.tree is None:
            return np.full(len(p), np.inf), np.full(len(p), -1)
        d, i = self.tree.query(p, distance_upper_bound=max_dist)
        i = np.where(np.isfinite(d), i, -1)
        return d, i

    def closest(self, p: np.ndarray, max_dist: float, return_index: bool = False):
        """Closest map point of each of ``p`` (segments for line-like markings).

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
        n = len(p)
        target = np.zeros((n, 2))
        normal = np.zeros((n, 2))
        if self.tree is None or n == 0:
            out = (np.full(n, np.inf), target, normal)
            return out + (np.full(n, -1),) if return_index else out
        if self.max_half == 0.0:
            d, i = self.tree.query(p, distance_upper_bound=max_dist)
            ok = np.isfinite(d)
            target[ok] = self.xy[i[ok]]
            return (d, target, normal, np.where(ok, i, -1)) if return_index else (d, target, normal)
        k = min(3, len(self))
        d0, ii = self.tree.query(p, k=k, distance_upper_bound=max_dist + self.max_half)
        if k == 1:
            d0, ii = d0[:, None], ii[:, None]
        valid = np.isfinite(d0)
        ii = np.where(valid, ii, 0)
        # Component arrays (not (n, k, 2) stacks): this runs once per refinement
        # iteration for every candidate's observations, and small-array overhead
        # dominates its cost.
        ux, uy, h = self._ux[ii], self._uy[ii], self.half[ii]
        rx = p[:, 0, None] - self._x[ii]
        ry = p[:, 1, None] - self._y[ii]
        a = np.clip(rx * ux + ry * uy, -h, h)
        ex = rx - a * ux  # from the closest point of the marking to p
        ey = ry - a * uy
        d2 = ex * ex + ey * ey
        d2[~valid] = np.inf
        best = np.argmin(d2, axis=1) + np.arange(n) * k  # flat index of each row's best
        d = np.sqrt(np.take(d2, best))
        d[d > max_dist] = np.inf
        target[:, 0] = p[:, 0] - np.take(ex, best)
        target[:, 1] = p[:, 1] - np.take(ey, best)
        normal[:, 0] = -np.take(uy, best)
        normal[:, 1] = np.take(ux, best)
        if return_index:
            return d, target, normal, np.where(np.isfinite(d), np.take(ii, best), -1)
        return d, target, normal

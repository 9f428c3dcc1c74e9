"""Global correlative search over heading × translation.

For each heading of a grid covering the prior's uncertainty, the rotated
observations are correlated with a *likelihood raster* of the map around the
prior: the per-observation log-likelihood ratio ``log(1 + exp(-d²/2s²)/π)``
of being a marking (``d`` the distance to the nearest map marking) versus being
clutter. Because the raster and the translation grid share their cell size,
the score of every translation at one heading is a sum of shifted raster
windows, one per observation. The GPS prior is added as a Gaussian
log-density. Local maxima of the heading × translation volume are the
candidates handed to the robust refinement.

The raster is built per request from the KD-tree's neighbourhood by stamping
each marking's kernel (line-like markings are sampled along their length), so
the map needs no precomputed global field and any map size costs the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .geometry import LocalMap


#: Local maxima are taken over a (2 PEAK_HALF + 1)³ neighbourhood of the volume.
PEAK_HALF = 2
#: Only the best cells of the volume are examined for local maxima.
PEAK_TOP_K = 4000
#: Candidates closer than this to a better one are the same optimum (metres, degrees).
SEP_M, SEP_DEG = 1.0, 2.5
#: Translation grids of at least this many cells (wide priors) are scored one
#: observation at a time, over chunks of headings of about CHUNK_CELLS cells.
LARGE_WINDOW_CELLS = 8000
CHUNK_CELLS = 100_000

#: Bounds of the heading step, radians: fine enough for the farthest
#: observation to move about a cell per step, never finer than 0.25°, never
#: coarser than 3°.
MIN_HEADING_STEP = math.radians(0.25)
MAX_HEADING_STEP = math.radians(3.0)


def heading_step(cell: float, rho: float) -> float:
    """Heading step of the search, radians, for ``cell`` metres and observations out to ``rho`` metres."""
    return min(max(cell / max(rho, 1.0), MIN_HEADING_STEP), MAX_HEADING_STEP)


def grid_half_sizes(radius: float, yaw_half_range: float, cell: float, rho: float) -> tuple[int, int]:
    """Half sizes ``(translation, heading)`` of the search grid, in steps.

    The volume has ``2 h + 1`` headings of ``(2 t + 1)²`` translations.
    """
    return int(math.ceil(radius / cell)), int(math.ceil(yaw_half_range / heading_step(cell, rho)))


def search_observations(
    obs_xy: np.ndarray,
    order: np.ndarray,
    radius: float,
    yaw_half_range: float,
    cell: float,
    max_cells: int,
    max_work: int,
) -> np.ndarray:
    """The observations the coarse search correlates, within its budget.

    Parameters
    ----------
    obs_xy : ndarray (N, 2)
        Vehicle-frame observations, metres.
    order : ndarray of int
        Candidates for the search, best first (highest weight).
    radius, yaw_half_range, cell : float
        The search's translation radius (m), heading half range (rad) and cell (m).
    max_cells : int
        Most cells of the heading × translation volume. Far observations need a
        fine heading step; those beyond the range whose step keeps the volume
        within this are left out (never the nearest eight).
    max_work : int
        Most volume cells × observations summed; beyond it, only the best
        ``max_work // cells`` observations of ``order`` are kept (at least eight).

    Returns
    -------
    ndarray of int
        The kept entries of ``order``, in its order. Observations left out of
        the coarse search still count in the refinement and the scores.
    """
    order = np.asarray(order)
    if order.size == 0:
        return order
    rng = np.hypot(obs_xy[order, 0], obs_xy[order, 1])

    def volume(rho: float) -> int:
        t, h = grid_half_sizes(radius, yaw_half_range, cell, rho)
        return (2 * h + 1) * (2 * t + 1) ** 2

    n = 2 * grid_half_sizes(radius, yaw_half_range, cell, 1.0)[0] + 1

    least = min(8, order.size)
    if volume(float(rng.max())) > max_cells:
        # The step that fills the budget, and the range at which it moves an
        # observation by a cell.
        step = 2.0 * yaw_half_range * n * n / max(max_cells - n * n, 1)
        reach = max(cell / step, float(np.sort(rng)[least - 1]))
        order, rng = order[rng <= reach], rng[rng <= reach]
    cells = volume(float(rng.max()))
    most = max(least, max_work // cells)
    return order[:most]


@dataclass(frozen=True)
class Candidate:
    x: float
    y: float
    yaw: float
    score: float


def _sample_markings(local_map: LocalMap, step: float, sigma: float):
    """Points standing for the markings and their kernel amplitudes.

    Line-like markings are sampled along their length with an amplitude
    ``sqrt(2 pi) sigma / length`` (their density is spread along the line; the
    same discount as in :func:`localizer.robust.data_score`).
    """
    point = local_map.half == 0
    line = np.flatnonzero(~point)
    h = local_map.half[line]
    n = np.maximum(2, np.ceil(2 * h / step).astype(np.int64) + 1)
    # Evenly spaced along each line, ends included (as np.linspace), all lines at once.
    owner = np.repeat(np.arange(line.size), n)
    k = np.arange(owner.size) - np.repeat(np.cumsum(n) - n, n)
    spacing = (2 * h / (n - 1))[owner]
    a = k * spacing - h[owner]
    a[k == n[owner] - 1] = h[owner][k == n[owner] - 1]
    along = local_map.xy[line][owner] + a[:, None] * local_map.axis[line][owner]
    amp_line = np.minimum(1.0, math.sqrt(2 * math.pi) * sigma / (2 * h))[owner]
    return (np.concatenate([local_map.xy[point], along]),
            np.concatenate([np.ones(int(point.sum())), amp_line]))


def _maximum_filter(volume: np.ndarray, half: int) -> np.ndarray:
    """``scipy.ndimage.maximum_filter(volume, 2 half + 1, mode="nearest")`` of a small 3D volume.

    The filter is separable, and with edges replicated a window reaching past
    an edge only repeats the edge cell, already in the window: each axis is a
    maximum over clipped shifted slices. On the few thousand cells of a tight
    prior's volume this is a few numpy calls, cheaper than the generic filter.
    """
    out = volume.copy()
    for axis in range(volume.ndim):
        src = np.moveaxis(out.copy(), axis, 0)
        dst = np.moveaxis(out, axis, 0)
        for sft in range(1, half + 1):
            if sft >= len(src):
                break
            np.maximum(dst[:-sft], src[sft:], out=dst[:-sft])
            np.maximum(dst[sft:], src[:-sft], out=dst[sft:])
    return out


def _local_maxima(volume: np.ndarray, half: int, top_k: int):
    """Indices ``(a, i, j)`` of finite local maxima of ``volume`` among its ``top_k`` best cells.

    A cell is a local maximum when no cell of its ``(2 half + 1)³``
    neighbourhood (edges replicated) is larger, as with a ``maximum_filter``;
    only the best cells are examined, a small fraction of the volume.
    """
    flat = volume.ravel()
    if flat.size <= 3 * top_k:
        # A small volume (a tight prior): one separable filter over all of it is
        # cheaper than gathering the neighbourhoods of the best cells.
        peak = _maximum_filter(volume, half)
        found = (volume == peak) & np.isfinite(volume)
        if flat.size > top_k:
            found &= volume >= np.partition(flat, flat.size - top_k)[flat.size - top_k]
        return np.nonzero(found)
    k = min(top_k, flat.size)
    if k < flat.size:
        # The k-th best value, then the cells above it: an argpartition of a
        # 20 m prior's volume (tens of millions of cells) would allocate a full
        # int64 index array, twice the volume's own memory.
        kth = np.partition(flat, flat.size - k)[flat.size - k]
        idx = np.flatnonzero(flat > kth)
        idx = np.concatenate([idx, np.flatnonzero(flat == kth)[: k - idx.size]])
    else:
        idx = np.arange(flat.size)
    idx = idx[np.isfinite(flat[idx])]
    a, i, j = np.unravel_index(idx, volume.shape)
    padded = np.pad(volume, half, mode="edge")
    pa, pi, pj = padded.shape
    base = ((a + half) * pi + (i + half)) * pj + (j + half)
    pf = padded.ravel()
    v = flat[idx]
    # Offsets of the neighbourhood in the padded volume, nearest first: most
    # cells lose to an adjacent one, so the farther offsets see few survivors.
    r = np.arange(-half, half + 1)
    da, di, dj = (g.ravel() for g in np.meshgrid(r, r, r, indexing="ij"))
    ring = np.maximum(np.maximum(np.abs(da), np.abs(di)), np.abs(dj))
    off = (da * pi + di) * pj + dj
    keep = np.arange(idx.size)
    for rr in range(1, half + 1):
        o = off[ring == rr]
        ok = np.all(pf[base[keep][None, :] + o[:, None]] <= v[keep][None, :], axis=0)
        keep = keep[ok]
    return a[keep], i[keep], j[keep]


def likelihood_raster(
    points: np.ndarray, x0: float, y0: float, shape: tuple[int, int], cell: float,
    sigma: float, outlier_density: float, amplitude: np.ndarray | None = None,
) -> np.ndarray:
    """Log-likelihood-ratio raster ``log(1 + max_i a_i exp(-d_i²/2σ²) / π)``.

    Cell ``(i, j)`` has its centre at ``(x0 + j*cell, y0 + i*cell)``.
    """
    ny, nx = shape
    r = int(math.ceil(3.0 * sigma / cell))
    off = np.arange(-r, r + 1)
    k = np.zeros(ny * nx)
    if len(points):
        amp = np.ones(len(points)) if amplitude is None else amplitude
        ci = np.rint((points[:, 1] - y0) / cell).astype(np.int64)
        cj = np.rint((points[:, 0] - x0) / cell).astype(np.int64)
        # The Gaussian kernel is separable: one exp per row and per column offset.
        ii = ci[:, None] + off[None]  # (P, 2r+1)
        jj = cj[:, None] + off[None]
        dy = y0 + ii * cell - points[:, 1, None]
        dx = x0 + jj * cell - points[:, 0, None]
        gy = amp[:, None] * np.exp(-0.5 * dy * dy / sigma**2)
        gx = np.exp(-0.5 * dx * dx / sigma**2)
        _stamp_max(k, ny, nx, ci - r, cj - r, gy, gx)
    return np.log1p(k / outlier_density).reshape(ny, nx).astype(np.float32)


@njit(cache=True, nogil=True)
def _stamp_max(k, ny, nx, i0, j0, gy, gx):
    """``k[i, j] = max(k[i, j], gy[p, a] gx[p, b])`` at ``i = i0[p] + a``, ``j = j0[p] + b`` inside
    the ``ny`` x ``nx`` raster ``k`` (flat), for every point ``p``."""
    for p in range(i0.size):
        for a in range(gy.shape[1]):
            i = i0[p] + a
            if i < 0 or i >= ny:
                continue
            row = i * nx
            for b in range(gx.shape[1]):
                j = j0[p] + b
                if 0 <= j < nx:
                    v = gy[p, a] * gx[p, b]
                    if v > k[row + j]:
                        k[row + j] = v


def correlative_search(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    w_obs: np.ndarray,
    prior_pose: tuple[float, float, float],
    radius: float,
    yaw_half_range: float,
    pos_info: np.ndarray | float,
    sigma_yaw: float,
    cell: float,
    outlier_density: float,
    n_candidates: int,
    temperature: float,
) -> list[Candidate]:
    """Best local maxima of the posterior score over the search volume.

    Parameters
    ----------
    local_map : LocalMap
        Markings around the prior (coordinates relative to its origin).
    obs_xy, w_obs : ndarray
        Observations (N, 2) in the vehicle frame and their weights (N,).
    prior_pose : (x, y, yaw)
        Prior in local map coordinates.
    radius, yaw_half_range : float
        Translation radius (m) and heading half range (rad) of the search.
    pos_info : (2, 2) ndarray or float
        The prior position's information (inverse covariance, 1/m², map
        axes), or its isotropic standard deviation (m).
    sigma_yaw : float
        The prior heading's standard deviation (rad).
    cell : float
        Translation step and raster cell, metres; the heading step follows
        from it and the farthest observation.
    """
    px, py, pyaw = prior_pose
    rho = float(np.max(np.hypot(obs_xy[:, 0], obs_xy[:, 1]))) if len(obs_xy) else 1.0
    kernel = max(cell, 0.3)
    half, k = grid_half_sizes(radius, yaw_half_range, cell, rho)
    n = 2 * half + 1
    margin = rho + 3.0 * kernel + cell
    x0 = px - half * cell - margin
    y0 = py - half * cell - margin
    m = int(math.ceil(2 * margin / cell)) + n + 1
    step = heading_step(cell, rho)
    yaws = pyaw + step * np.arange(-k, k + 1)
    tx = (np.arange(n) - half) * cell  # offsets from the prior position
    if np.ndim(pos_info) == 0:
        pos_info = np.eye(2) / float(pos_info) ** 2
    # rows are y offsets, columns x offsets
    prior_t = -0.5 * (pos_info[0, 0] * tx[None, :] ** 2 + 2.0 * pos_info[0, 1] * tx[None, :] * tx[:, None]
                      + pos_info[1, 1] * tx[:, None] ** 2)
    wf = (w_obs / temperature).astype(np.float32)
    cos, sin = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    qx = cos * obs_xy[None, :, 0] - sin * obs_xy[None, :, 1] + px - half * cell
    qy = sin * obs_xy[None, :, 0] + cos * obs_xy[None, :, 1] + py - half * cell
    cj = np.rint((qx - x0) / cell).astype(np.int64)
    ci = np.rint((qy - y0) / cell).astype(np.int64)
    # Only the raster cells under some observation's window are read: a forward
    # camera's observations cover a wedge, not the square around the prior. The
    # markings whose kernels reach no such cell are not stamped (the cells that
    # are read get exactly the same values).
    pts, amp = _sample_markings(local_map, cell / 2, kernel)
    if len(obs_xy):
        r = int(math.ceil(3.0 * kernel / cell))
        lo_i, hi_i = int(ci.min()) - r, int(ci.max()) + n - 1 + r
        lo_j, hi_j = int(cj.min()) - r, int(cj.max()) + n - 1 + r
        pi = np.rint((pts[:, 1] - y0) / cell)
        pj = np.rint((pts[:, 0] - x0) / cell)
        near = (pi >= lo_i) & (pi <= hi_i) & (pj >= lo_j) & (pj <= hi_j)
        pts, amp = pts[near], amp[near]
    raster = likelihood_raster(pts, x0, y0, (m, m), cell, kernel, outlier_density, amp)
    # Every translation window of the raster as a view; the score volume at one
    # heading is the weighted sum of the windows the observations fall into.
    s0, s1 = raster.strides
    windows = np.lib.stride_tricks.as_strided(
        raster, (m - n + 1, m - n + 1, n, n), (s0, s1, s0, s1), writeable=False)
    dyaw = (yaws - pyaw) / sigma_yaw
    volume = np.empty((len(yaws), n, n), np.float32)
    if n * n < LARGE_WINDOW_CELLS:
        # Headings in chunks keep the gathered windows (chunk x N x n x n) small.
        chunk = max(1, int(4_000_000 // max(1, len(obs_xy) * n * n)))
        for a0 in range(0, len(yaws), chunk):
            a1 = min(a0 + chunk, len(yaws))
            block = windows[ci[a0:a1], cj[a0:a1]]  # (chunk, N, n, n)
            acc = np.matmul(wf, block.reshape(a1 - a0, len(obs_xy), n * n)).reshape(a1 - a0, n, n)
            volume[a0:a1] = acc + prior_t[None] - (0.5 * dyaw[a0:a1] ** 2)[:, None, None]
    else:
        # Gathering every observation's window at once would write and read
        # back hundreds of megabytes for a 20 m prior; adding them one by one
        # into a cache-sized chunk of the volume takes 40 % less CPU (same sums).
        chunk = max(1, CHUNK_CELLS // (n * n))
        for a0 in range(0, len(yaws), chunk):
            a1 = min(a0 + chunk, len(yaws))
            acc = volume[a0:a1]
            acc[:] = prior_t[None] - (0.5 * dyaw[a0:a1] ** 2)[:, None, None]
            for j in range(len(obs_xy)):
                g = windows[ci[a0:a1, j], cj[a0:a1, j]]  # (chunk, n, n)
                g *= wf[j]
                acc += g
    # Inside the disc of the search radius only.
    volume[:, (tx[None, :] ** 2 + tx[:, None] ** 2) > radius**2] = -np.inf
    a, i, j = _local_maxima(volume, PEAK_HALF, PEAK_TOP_K)
    order = np.argsort(-volume[a, i, j], kind="stable")
    a, i, j = a[order], i[order], j[order]
    cx, cy, cyaw = px + tx[j], py + tx[i], yaws[a]
    keep = _separated(cx, cy, cyaw, SEP_M, math.radians(SEP_DEG), n_candidates)
    return [Candidate(float(cx[k]), float(cy[k]), float(cyaw[k]), float(volume[a[k], i[k], j[k]])) for k in keep]


@njit(cache=True, nogil=True)
def _separated(x, y, yaw, sep_m, sep_rad, limit):
    """Indices of the optima (best first) kept when each closer than ``sep_m`` and ``sep_rad`` to a kept one is dropped.

    At most ``limit``; a greedy non-maximum suppression over candidates already
    sorted best first. Headings are compared across ±π (a search over every
    heading meets itself there).
    """
    keep = np.empty(min(limit, x.size), np.int64)
    n = 0
    for k in range(x.size):
        if n >= limit:
            break
        near = False
        for q in range(n):
            m = keep[q]
            turn = abs((yaw[k] - yaw[m] + math.pi) % (2.0 * math.pi) - math.pi)
            if math.hypot(x[k] - x[m], y[k] - y[m]) < sep_m and turn < sep_rad:
                near = True
                break
        if not near:
            keep[n] = k
            n += 1
    return keep[:n]

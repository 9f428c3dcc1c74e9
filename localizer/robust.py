"""Robust refinement, hypothesis scoring and covariance of the default method."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .geometry import _FAR, NEAREST_CENTROIDS, LocalMap, apply, keep_nearest, nearest_marking
from .types import Options


#: Floor of the scoring kernel's width, metres: the map's own placement error.
SCORE_FLOOR_M = 0.15


def noise_sigma(obs_xy: np.ndarray, options: Options) -> np.ndarray:
    """Per-observation position noise of a flat-ground camera, metres: ``a + b r²``.

    This is the noise along the viewing ray (range); see :func:`bearing_sigma`.
    """
    r2 = np.einsum("nd,nd->n", obs_xy, obs_xy)
    return options.noise_m + options.noise_range_coeff * r2


def bearing_sigma(obs_xy: np.ndarray, options: Options) -> np.ndarray:
    """Per-observation noise across the viewing ray, metres: ``a + bearing_noise_rad · r``.

    Requires ``options.bearing_noise_rad`` (not None).
    """
    return options.noise_m + options.bearing_noise_rad * np.hypot(obs_xy[:, 0], obs_xy[:, 1])


def data_weights(gamma: np.ndarray) -> np.ndarray:
    """Pixel counts relative to their median, capped at 1.5.

    The paper weighs by pixel count γ so that a marking split into several
    clusters does not count several times; the cap keeps a large cluster (the
    edges of a preceding vehicle) from outweighing the markings. The cap was
    chosen on ``benchmarks/localize_calibrate.py`` (3 and 2 gave more
    confidently wrong answers under heavy clutter).
    """
    med = float(np.median(gamma)) if gamma.size else 1.0
    return np.minimum(gamma / max(med, 1e-12), 1.5)


def crowd_weights(obs_xy: np.ndarray, w: np.ndarray, radius_m: float) -> np.ndarray:
    """Share the weight of observations that crowd together, keeping the frame's total.

    Each weight is divided by the observation's Gaussian count of neighbours,
    ``n_j = sum_k exp(-d_jk² / 2 R²)`` (itself included), and the result is
    scaled so that the weights still sum to ``sum(w)``.

    Parameters
    ----------
    obs_xy : (N, 2) ndarray
        Observations in the vehicle frame, metres.
    w : (N,) ndarray
        Their data weights (see :func:`data_weights`).
    radius_m : float
        The kernel's width R, metres.

    Returns
    -------
    (N,) ndarray
        The shared weights.

    Notes
    -----
    Clusters a few decimetres apart (the edges of a preceding vehicle, a curb,
    a marking split by the clustering) are not independent evidence, yet each
    counts as much as an isolated dash. A rival pose that lays three of them on
    markings then scores like one that matches three separate markings; on the
    benchmark's near scenes such rivals, turned 10-30°, made the answer
    ambiguous. Sharing their weight lets the spread-out matches decide.
    """
    n = np.ones(len(obs_xy))
    if len(obs_xy) > 1:
        pairs = cKDTree(obs_xy).query_pairs(4.0 * radius_m, output_type="ndarray")
        if len(pairs):
            d2 = np.sum((obs_xy[pairs[:, 0]] - obs_xy[pairs[:, 1]]) ** 2, axis=1)
            k = np.exp(-d2 / (2.0 * radius_m**2))
            n += np.bincount(pairs[:, 0], k, len(obs_xy)) + np.bincount(pairs[:, 1], k, len(obs_xy))
    shared = w / n
    return shared * (float(np.sum(w)) / max(float(np.sum(shared)), 1e-300))


@dataclass
class RefineResult:
    pose: tuple[float, float, float]
    iterations: int
    trace: list[tuple[float, float, float]] = field(default_factory=list)


def robust_refine(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    w_obs: np.ndarray,
    sigma_obs: np.ndarray,
    inits,
    options: Options,
    record: bool = False,
    start_scale=None,
) -> list[RefineResult]:
    """IRLS with a Geman-McClure kernel whose scale is annealed coarse to fine.

    At annealing scale ``c`` an observation's scale is ``s_j = sqrt(c² + σ_j²)``
    (σ_j its noise), its normalised residual ``u = d / s_j`` and its weight
    ``w_j / s_j² / (1 + u²)²``; pairs beyond ``3 s_j`` are dropped. Coarse scales
    weigh all observations alike (no near-range observation can drag the pose
    far), the finest weighs them by their noise. Pairs are point-to-point for
    point-like markings and point-to-segment for line-like ones.

    All initial poses ``inits`` (K, 3) are refined in one call of a compiled
    loop (:func:`_refine_batch`; each pose on its own, as if refined alone):
    at a few hundred pairs per iteration, numpy's fixed cost per call would
    dominate. ``record`` keeps the trace of the first.
    ``start_scale`` (K,), optional: index into ``options.anneal_m`` at which
    each pose starts (default 0); a pose starting at the last two scales is
    refined exactly as with ``anneal_m[-2:]``, so coarse-to-fine and fine-only
    refinements share one batch.

    At the last scale, unless ``options.bearing_noise_rad`` is None, each step
    is a Gauss-Newton step in which a pair's residual along the viewing ray
    counts with the range noise and across it with the (smaller) bearing
    noise; Procrustes weighs both alike.
    """
    poses = np.array(inits, float).reshape(-1, 3)
    K, N = len(poses), len(obs_xy)
    start = np.zeros(K, np.int64) if start_scale is None else np.asarray(start_scale, np.int64).reshape(K)
    pos = np.ascontiguousarray(poses[:, 0] + 1j * poses[:, 1])
    yaw = poses[:, 2].copy()  # the kernel updates pos and yaw in place
    obs = np.ascontiguousarray(obs_xy[:, 0] + 1j * obs_xy[:, 1])
    var = np.ascontiguousarray(sigma_obs, float) ** 2
    aniso = options.bearing_noise_rad is not None and N > 0
    if aniso:
        var_t = bearing_sigma(obs_xy, options) ** 2
        ray = obs / np.maximum(np.abs(obs), 1e-9)
    else:
        var_t, ray = var, obs
    iters, trace = _refine_batch(
        pos, yaw, obs, np.ascontiguousarray(w_obs, float), var, var_t, ray, start,
        np.asarray(options.anneal_m, float), int(options.iterations_per_scale),
        float(options.tolerance_m), float(options.tolerance_rad), aniso, record, local_map.tables,
    )
    first = [(float(poses[0, 0]), float(poses[0, 1]), float(poses[0, 2]))] if record else []
    trace = first + [tuple(float(v) for v in t) for t in trace]
    return [
        RefineResult(pose=(float(pos[k].real), float(pos[k].imag), float(yaw[k])), iterations=int(iters[k]),
                     trace=trace if k == 0 else [])
        for k in range(K)
    ]


@njit(cache=True, nogil=True)
def _refine_batch(pos, yaw, obs, w_obs, var, var_t, ray, start, anneal, per_scale, tol_m, tol_rad,
                  aniso, record, tables):
    """The iterations of :func:`robust_refine`, compiled; updates ``pos`` and ``yaw`` in place.

    Each pose is refined on its own (their pairs do not interact). Returns the
    iterations per pose and the trace of pose 0 (an (T, 3) array, empty
    unless ``record``).
    """
    K, N = pos.size, obs.size
    iters = np.zeros(K, np.int64)
    trace = np.empty((anneal.size * per_scale if record else 0, 3))
    n_trace = 0
    pts = np.empty(N, np.complex128)
    tgt = np.empty(N, np.complex128)
    w = np.empty(N)
    best_i = np.empty(NEAREST_CENTROIDS, np.int64)
    best_d = np.empty(NEAREST_CENTROIDS)
    H = np.empty((3, 3))
    b = np.empty(3)
    n_map = tables[0].size
    max_half = tables[3]
    c_last = anneal[anneal.size - 1]
    for si in range(anneal.size):
        c = anneal[si]
        last = c == c_last
        gmax = 0.0
        for j in range(N):
            gmax = max(gmax, 3.0 * math.sqrt(c * c + var[j]))
        reach2 = (gmax + max_half) ** 2
        tol = tol_m if last else max(tol_m, 0.01)
        for k in range(K):
            if start[k] > si:
                continue
            for _ in range(per_scale):
                P, Y = pos[k], yaw[k]
                rot = complex(math.cos(Y), math.sin(Y))
                n_match = 0
                wsum = 0.0
                for j in range(N):
                    pts[j] = rot * obs[j] + P
                    best_d[0] = reach2
                    d, e, m = nearest_marking(pts[j], tables, best_i, best_d)
                    tgt[j] = pts[j] - e if m < n_map else _FAR
                    s2 = c * c + var[j]
                    w[j] = 0.0
                    # Pairs beyond 3 s_j are dropped; Geman-McClure weight within.
                    if d <= gmax and d <= 3.0 * math.sqrt(s2):
                        t = d * d / s2 + 1.0
                        w[j] = (1.0 if last else w_obs[j]) / s2 / (t * t)
                        n_match += 1
                        wsum += w[j]
                if n_match < 2 or not wsum > 0.0:
                    break
                if last and aniso:
                    H[:] = 0.0
                    b[:] = 0.0
                    for j in range(N):
                        if w[j] == 0.0:
                            continue
                        sr2 = c * c + var[j]
                        st2 = c * c + var_t[j]
                        # The ray in the map frame, conjugated: real parts along it, imaginary across.
                        u = (rot * ray[j]).conjugate()
                        eu = (pts[j] - tgt[j]) * u
                        j0, j1, j2 = u, 1j * u, 1j * (pts[j] - P) * u
                        wr = w[j]
                        wt = w[j] * (sr2 / st2)
                        jr = (j0.real, j1.real, j2.real)
                        jt = (j0.imag, j1.imag, j2.imag)
                        for a in range(3):
                            b[a] -= wr * jr[a] * eu.real + wt * jt[a] * eu.imag
                            for bb in range(3):
                                H[a, bb] += wr * jr[a] * jr[bb] + wt * jt[a] * jt[bb]
                    for a in range(3):
                        H[a, a] += 1e-9
                    dx, dy, th = _solve3(H, b)
                    new = P + complex(dx, dy)
                else:
                    cs = 0j
                    cd = 0j
                    for j in range(N):
                        if w[j] > 0.0:
                            cs += w[j] / wsum * pts[j]
                            cd += w[j] / wsum * tgt[j]
                    acc = 0j
                    for j in range(N):
                        if w[j] > 0.0:
                            acc += w[j] / wsum * (pts[j] - cs).conjugate() * (tgt[j] - cd)
                    # Weighted 2D Procrustes: the rotation is the angle of acc.
                    th = math.atan2(acc.imag, acc.real)
                    new = complex(math.cos(th), math.sin(th)) * (P - cs) + cd
                step = abs(new - P)
                pos[k] = new
                yaw[k] = Y + th
                iters[k] += 1
                if record and k == 0:
                    trace[n_trace, 0] = new.real
                    trace[n_trace, 1] = new.imag
                    trace[n_trace, 2] = Y + th
                    n_trace += 1
                if step < tol and abs(th) < tol_rad:
                    break
    return iters, trace[:n_trace]


@njit(cache=True, nogil=True)
def _solve3(H, b):
    """``H x = b`` for a 3x3 system by Gaussian elimination with partial pivoting; zeros if singular."""
    A = H.copy()
    x = b.copy()
    for col in range(3):
        piv = col
        for r in range(col + 1, 3):
            if abs(A[r, col]) > abs(A[piv, col]):
                piv = r
        if A[piv, col] == 0.0:
            return 0.0, 0.0, 0.0
        if piv != col:
            for cc in range(3):
                A[col, cc], A[piv, cc] = A[piv, cc], A[col, cc]
            x[col], x[piv] = x[piv], x[col]
        for r in range(col + 1, 3):
            f = A[r, col] / A[col, col]
            for cc in range(col, 3):
                A[r, cc] -= f * A[col, cc]
            x[r] -= f * x[col]
    for r in range(2, -1, -1):
        acc = x[r]
        for cc in range(r + 1, 3):
            acc -= A[r, cc] * x[cc]
        x[r] = acc / A[r, r]
    return x[0], x[1], x[2]


def log_prior(pose, prior_pose, pos_info, sigma_yaw: float) -> float:
    """Gaussian log-density of a pose under the prior, up to a constant.

    ``pos_info`` is the position's information (2x2 inverse covariance,
    1/m²) or, for an isotropic prior, its standard deviation in metres.
    """
    dx = pose[0] - prior_pose[0]
    dy = pose[1] - prior_pose[1]
    dyaw = (pose[2] - prior_pose[2] + math.pi) % (2 * math.pi) - math.pi
    if np.ndim(pos_info) == 0:
        q = (dx * dx + dy * dy) / float(pos_info) ** 2
    else:
        q = pos_info[0, 0] * dx * dx + 2.0 * pos_info[0, 1] * dx * dy + pos_info[1, 1] * dy * dy
    return -0.5 * (float(q) + (dyaw / sigma_yaw) ** 2)


def view_of(obs_xy: np.ndarray, options: Options) -> tuple[float, float, float]:
    """The camera's ground view ``(min range, max range, half angle rad)``.

    The configured view (``view_*`` options, by default a forward camera seeing
    the ground 4-25 m ahead within ±30°), widened to cover every observation: a
    camera that demonstrably sees farther than configured sees at least that
    far. A view option set to None is taken from the extent of the observations
    alone (shrunk a little, so it is never larger than what the camera saw).
    """
    if len(obs_xy) == 0:
        return 0.0, 0.0, 0.0
    r = np.hypot(obs_xy[:, 0], obs_xy[:, 1])
    b = np.abs(np.arctan2(obs_xy[:, 1], obs_xy[:, 0]))
    o = options
    rmin = min(o.view_min_range_m, float(r.min())) if o.view_min_range_m is not None else float(r.min()) + 0.5
    rmax = max(o.view_max_range_m, float(r.max())) if o.view_max_range_m is not None else float(r.max()) - 0.5
    half = (
        max(math.radians(o.view_half_fov_deg), float(b.max()))
        if o.view_half_fov_deg is not None
        else float(b.max()) - math.radians(2.0)
    )
    return rmin, rmax, half


def data_score(
    local_map: LocalMap, obs_xy, w_obs, sigma_obs, pose, options: Options, view=None
) -> float:
    """Log-likelihood ratio of the observations at ``pose``, with negative evidence.

    See :func:`data_scores`.
    """
    return float(data_scores(local_map, obs_xy, w_obs, sigma_obs, [pose], options, view)[0])


def data_scores(
    local_map: LocalMap, obs_xy, w_obs, sigma_obs, poses, options: Options, view=None
) -> np.ndarray:
    """Log-likelihood ratio of the observations at each of ``poses`` (K, 3).

    Positive evidence: each observation adds ``w log(1 + N(d; s) / π)`` (matched
    marking versus clutter; a match on a segment counts less, its density being
    spread along it). The kernel is anisotropic unless
    ``options.bearing_noise_rad`` is None: the residual along the viewing ray
    is scaled by the range noise, across it by the bearing noise (both with a
    0.15 m floor for the map's own placement).

    Negative evidence: each place where the map says the camera should report a
    centroid at a pose (a point-like marking, or a point every few metres along
    a solid line; :attr:`MapIndex.expect_xy`) that lies inside ``view`` (shrunk
    by ``view_margin_m`` / ``view_margin_deg`` against edge effects) and that no
    observation explains within ``explain_distance_m`` (on a solid line, also
    within ``solid_explain_along_m`` along the line and
    ``solid_explain_across_m`` across it) costs ``log(1 / miss_probability)``
    (``solid_miss_probability`` on solid lines).
    A pose shifted by one dash period explains the observed dashes as well as
    the true one, but at the end of a dashed line, a stop line or a change of
    line type it predicts markings that nobody saw.
    """
    P = np.ascontiguousarray(np.asarray(poses, float).reshape(-1, 3))
    s = np.sqrt(SCORE_FLOOR_M**2 + np.asarray(sigma_obs, float) ** 2)
    aniso = options.bearing_noise_rad is not None
    st = np.sqrt(SCORE_FLOOR_M**2 + bearing_sigma(obs_xy, options) ** 2) if aniso else s
    score = _positive_scores(P, np.ascontiguousarray(obs_xy, float), np.ascontiguousarray(w_obs, float), s, st,
                             aniso, float(options.outlier_density), 4.0 * float(s.max()) if s.size else 0.0,
                             local_map.tables)  # fmt: skip
    return score - miss_costs(local_map, obs_xy, P, options, view)


@njit(cache=True, nogil=True)
def _positive_scores(P, obs, w, s, st, aniso, outlier_density, max_dist, tables):
    """The positive evidence of :func:`data_scores`, compiled: per pose, ``Σ w log(1 + k / outlier_density)``.

    ``k`` is the Gaussian kernel of the residual to the closest marking
    within ``max_dist`` (anisotropic: ``s`` along the viewing ray, ``st``
    across it), divided by a segment's length over ``sqrt(2π) s`` where the
    match lies on a line-like marking (capped at 1).
    """
    K, N = P.shape[0], obs.shape[0]
    h = tables[2]
    reach2 = (max_dist + tables[3]) ** 2
    best_i = np.empty(NEAREST_CENTROIDS, np.int64)
    best_d = np.empty(NEAREST_CENTROIDS)
    out = np.zeros(K)
    for k in range(K):
        rot = complex(math.cos(P[k, 2]), math.sin(P[k, 2]))
        pos = complex(P[k, 0], P[k, 1])
        for j in range(N):
            p = rot * complex(obs[j, 0], obs[j, 1]) + pos
            best_d[0] = reach2
            d, e, m = nearest_marking(p, tables, best_i, best_d)
            if not d <= max_dist:
                continue
            if aniso:
                bear = P[k, 2] + math.atan2(obs[j, 1], obs[j, 0])
                cb, sb = math.cos(bear), math.sin(bear)
                er = e.real * cb + e.imag * sb
                et = -e.real * sb + e.imag * cb
                u2 = (er / s[j]) ** 2 + (et / st[j]) ** 2
            else:
                u2 = (d / s[j]) ** 2
            kv = math.exp(-0.5 * u2)
            # A solid-line piece explains an observation anywhere along its
            # length: its density is spread over the length.
            if h[m] > 0:
                kv *= min(1.0, math.sqrt(2 * math.pi) * s[j] / max(2 * h[m], 1e-9))
            out[k] += w[j] * math.log1p(kv / outlier_density)
    return out


def miss_costs(local_map: LocalMap, obs_xy, poses, options: Options, view=None) -> np.ndarray:
    """Negative evidence of each pose (K,): expected centroids in view that nobody saw."""
    points, solid = missed_counts(local_map, obs_xy, poses, options, view)
    return (points * math.log(1.0 / options.miss_probability)
            + solid * math.log(1.0 / options.solid_miss_probability))


def missed_counts(local_map: LocalMap, obs_xy, poses, options: Options, view=None):
    """Expected centroids in view that no observation explains, per pose: ``(points, solid)``.

    ``points`` counts point-like markings, ``solid`` the expected clusters of
    solid lines (see :attr:`MapIndex.expect_xy`); both (K,) arrays.
    """
    P = np.asarray(poses, float).reshape(-1, 3)
    out = np.zeros(len(P)), np.zeros(len(P))
    E = local_map.expect_xy
    if view is None or len(E) == 0 or len(obs_xy) == 0:
        return out
    rmin, rmax, halfang = view
    rmin += options.view_margin_m
    rmax -= options.view_margin_m
    halfang -= math.radians(options.view_margin_deg)
    if rmax <= rmin or halfang <= 0:
        return out
    return _missed_batch(
        np.ascontiguousarray(P), np.ascontiguousarray(E, float), np.ascontiguousarray(local_map.expect_solid),
        np.ascontiguousarray(local_map.expect_axis, float), np.ascontiguousarray(obs_xy, float),
        rmin, rmax, math.tan(halfang), float(options.explain_distance_m),
        float(options.solid_explain_along_m), float(options.solid_explain_across_m),
    )


#: Observations examined when an expected solid-line cluster may be explained along its line.
ALONG_LINE_NEIGHBOURS = 4


@njit(cache=True, nogil=True)
def _missed_batch(P, E, solid, axis, obs, rmin, rmax, tan_half, explain, along_max, across_max):
    """The counting of :func:`missed_counts`, compiled: ``(points, solid)`` per pose.

    An expected centroid in view is explained by an observation within
    ``explain`` metres; one of a solid line also by one of the
    :data:`ALONG_LINE_NEIGHBOURS` observations nearest to it (within
    ``along_max``) that lies within ``along_max`` along the line and
    ``across_max`` across it (the camera clusters a line at its own phase).
    """
    K, M, N = P.shape[0], E.shape[0], obs.shape[0]
    points = np.zeros(K)
    lines = np.zeros(K)
    n_near = min(ALONG_LINE_NEIGHBOURS, N)
    near_i = np.empty(ALONG_LINE_NEIGHBOURS, np.int64)
    near_d = np.empty(ALONG_LINE_NEIGHBOURS)
    ex2, al2 = explain * explain, along_max * along_max
    for k in range(K):
        c, s = math.cos(P[k, 2]), math.sin(P[k, 2])
        for e in range(M):
            dx, dy = E[e, 0] - P[k, 0], E[e, 1] - P[k, 1]
            vx = c * dx + s * dy
            vy = -s * dx + c * dy
            r2 = vx * vx + vy * vy
            if not (r2 >= rmin * rmin and r2 <= rmax * rmax and abs(vy) <= tan_half * vx and vx > 0):
                continue
            found = 0
            best = np.inf
            point = not solid[e]
            for j in range(N):
                ox, oy = obs[j, 0] - vx, obs[j, 1] - vy
                d2 = ox * ox + oy * oy
                best = min(best, d2)
                if point:
                    if best < ex2:
                        break  # explained; only a solid line's neighbours are needed
                elif d2 < al2:
                    found = keep_nearest(near_d, near_i, found, n_near, d2, j)
            if best < ex2:
                continue
            if not solid[e]:
                points[k] += 1.0
                continue
            explained = False
            if along_max > 0:
                # The line's direction in the vehicle frame.
                ux = c * axis[e, 0] + s * axis[e, 1]
                uy = -s * axis[e, 0] + c * axis[e, 1]
                for q in range(found):
                    ox, oy = obs[near_i[q], 0] - vx, obs[near_i[q], 1] - vy
                    if abs(ox * ux + oy * uy) <= along_max and abs(oy * ux - ox * uy) <= across_max:
                        explained = True
                        break
            if not explained:
                lines[k] += 1.0
    return points, lines


def count_inliers(local_map: LocalMap, obs_xy, sigma_obs, poses, options: Options) -> np.ndarray:
    """Observations within the inlier gate of the map at each pose (K,), as in :func:`fit_statistics`."""
    P = np.asarray(poses, float).reshape(-1, 3)
    if len(P) == 0 or len(obs_xy) == 0:
        return np.zeros(len(P), int)
    cos, sin = np.cos(P[:, 2]), np.sin(P[:, 2])
    px = cos[:, None] * obs_xy[None, :, 0] - sin[:, None] * obs_xy[None, :, 1] + P[:, 0, None]
    py = sin[:, None] * obs_xy[None, :, 0] + cos[:, None] * obs_xy[None, :, 1] + P[:, 1, None]
    gate = np.maximum(options.inlier_distance_m, 3.0 * sigma_obs)
    d = local_map.closest(np.stack([px, py], -1).reshape(-1, 2), float(gate.max()))[0]
    return np.sum(d.reshape(len(P), -1) <= gate[None], axis=1)


@dataclass
class Fit:
    """Statistics of a pose: inliers, RMS and covariance (x, y, yaw)."""

    inliers: int
    rms_m: float | None
    covariance: np.ndarray | None
    inlier_mask: np.ndarray


def fit_statistics(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    w_obs: np.ndarray,
    sigma_obs: np.ndarray,
    pose,
    options: Options,
    prior_info: np.ndarray | None = None,
    pitch_var: float | None = None,
) -> Fit:
    """Inliers, RMS residual and covariance of ``pose``.

    The covariance is the average of the model-based ``s² H⁻¹`` (``s²`` the
    weighted residual variance) and the sandwich estimate ``H⁻¹ B H⁻¹``, which
    follows anisotropic residuals, plus the propagated effect of a camera
    pitch error (``pitch_sigma_deg``: all ranges stretch together); segment pairs contribute only across their
    line, so a view of a single solid line leaves the along-line direction to
    the prior information ``prior_info`` (3x3, added to the data information).
    """
    gate = np.maximum(options.inlier_distance_m, 3.0 * np.asarray(sigma_obs, float))
    lever = pitch_lever(np.hypot(obs_xy[:, 0], obs_xy[:, 1]), options)
    m, sum_d2, H, G, B, chi2, dof = _fit_sums(
        np.asarray(pose, float), np.ascontiguousarray(obs_xy, float), np.ascontiguousarray(w_obs, float),
        np.ascontiguousarray(sigma_obs, float), gate, float(gate.max()) if gate.size else 0.0, lever,
        local_map.tables,
    )
    n = int(m.sum())
    if n == 0:
        return Fit(0, None, None, m)
    rms = math.sqrt(sum_d2 / n)
    if n < 2:
        return Fit(n, rms, None, m)
    s2 = chi2 / max(dof - 3.0, 1.0)
    s2 = max(s2, 0.25)  # optimistic residuals from few points must not shrink the ellipse
    info_prior = np.zeros((3, 3)) if prior_info is None else prior_info
    Hr = H + s2 * info_prior
    try:
        Hinv = np.linalg.inv(Hr)
    except np.linalg.LinAlgError:
        Hinv = np.linalg.pinv(Hr)
    model = s2 * Hinv
    sandwich = Hinv @ B @ Hinv * (dof / max(dof - 3.0, 1.0))
    # A pitch error stretches all ranges together (flat-ground camera), a
    # correlated error that the residuals do not reveal; propagate it explicitly.
    gp = Hinv @ G
    var_pitch = math.radians(options.pitch_sigma_deg) ** 2
    if pitch_var is not None:
        var_pitch = pitch_var
    pitch = np.outer(gp, gp) * var_pitch
    cov = 0.5 * (model + sandwich) + pitch
    cov = options.covariance_inflation * 0.5 * (cov + cov.T)
    return Fit(n, rms, cov, m)


def mixture_covariance(about, poses, weights, covariances) -> np.ndarray | None:
    """Expected outer product of the error of pose ``about`` over a mixture of pose hypotheses.

    Parameters
    ----------
    about : (x, y, yaw)
        The reported pose: metres, metres, radians.
    poses : sequence of (x, y, yaw)
        The hypotheses' poses, in the same frame.
    weights : sequence of float
        Their probabilities; rescaled to sum to one.
    covariances : sequence of (3, 3) array_like or None
        Each hypothesis's covariance of (x m, y m, yaw rad).

    Returns
    -------
    (3, 3) ndarray or None
        ``sum p_i (C_i + d_i d_i^T)`` with ``d_i = pose_i - about``, the yaw
        difference wrapped to [-pi, pi); None if a covariance is None or no
        weight is positive.
    """
    w = np.asarray(weights, float)
    if any(c is None for c in covariances) or not w.sum() > 0:
        return None
    w = w / w.sum()
    d = np.asarray(poses, float).reshape(-1, 3) - np.asarray(about, float)
    d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
    c = np.asarray(covariances, float).reshape(-1, 3, 3)
    out = np.einsum("k,kij->ij", w, c) + np.einsum("k,ki,kj->ij", w, d, d)
    return 0.5 * (out + out.T)


def along_across_sigmas(covariance, yaw: float) -> tuple[float, float]:
    """Standard deviations of a pose's position along and across its heading.

    Parameters
    ----------
    covariance : (2, 2) or (3, 3) array_like
        Covariance whose first two axes are map x and y, square metres.
    yaw : float
        The heading in the same frame, radians counter-clockwise from x.

    Returns
    -------
    (along, across) : tuple of float
        Metres.
    """
    m = np.asarray(covariance, float)[:2, :2]
    u = np.array([math.cos(yaw), math.sin(yaw)])
    v = np.array([-u[1], u[0]])
    return math.sqrt(max(0.0, float(u @ m @ u))), math.sqrt(max(0.0, float(v @ m @ v)))


@njit(cache=True, nogil=True)
def _fit_sums(pose, obs, w_obs, sigma, gate, gmax, lever, tables):
    """The sums behind :func:`fit_statistics`, compiled.

    Pairs each observation with its closest marking within its ``gate`` and
    accumulates, over the pairs, the information ``H = Σ w JᵀJ``, the
    pitch sensitivity ``G = Σ w Jᵀ s`` (``s`` the shift a unit pitch error
    gives the observation along its ray, ``lever`` metres per radian), the
    scores' outer products ``B = Σ (w Jᵀ r)(w Jᵀ r)ᵀ``, ``χ² = Σ w |r|²``
    and the degrees of freedom; ``w = w_obs / σ²``. A point pair has two
    rows (x, y) in ``J``; a segment pair one, across its line.

    Returns ``(inlier mask, Σ d², H, G, B, χ², dof)``.
    """
    N = obs.shape[0]
    uc, max_half = tables[1], tables[3]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    mask = np.zeros(N, np.bool_)
    H = np.zeros((3, 3))
    G = np.zeros(3)
    B = np.zeros((3, 3))
    J1 = np.empty(3)
    J2 = np.empty(3)
    best_i = np.empty(NEAREST_CENTROIDS, np.int64)
    best_d = np.empty(NEAREST_CENTROIDS)
    sum_d2 = chi2 = dof = 0.0
    for j in range(N):
        qx = c * obs[j, 0] - s * obs[j, 1]  # lever arm from the vehicle origin
        qy = s * obs[j, 0] + c * obs[j, 1]
        best_d[0] = (gmax + max_half) ** 2
        d, e, m = nearest_marking(complex(qx + pose[0], qy + pose[1]), tables, best_i, best_d)
        if not (d <= gmax and d <= gate[j]):
            continue
        mask[j] = True
        sum_d2 += d * d
        w = w_obs[j] / sigma[j] ** 2
        rng = max(math.hypot(obs[j, 0], obs[j, 1]), 1e-9)
        sx, sy = qx / rng * lever[j], qy / rng * lever[j]
        # Rows x: (1, 0, -qy), y: (0, 1, qx); a segment's row is the normal times them.
        nx, ny = uc[m].imag, uc[m].real  # the normal (-axis_y, axis_x); axis = conj(uc)
        if nx != 0.0 or ny != 0.0:
            J1[0], J1[1], J1[2] = nx, ny, -nx * qy + ny * qx
            J2[:] = 0.0
            r1, r2 = nx * e.real + ny * e.imag, 0.0
            s1, s2 = nx * sx + ny * sy, 0.0
            dof += 1.0
        else:
            J1[0], J1[1], J1[2] = 1.0, 0.0, -qy
            J2[0], J2[1], J2[2] = 0.0, 1.0, qx
            r1, r2 = e.real, e.imag
            s1, s2 = sx, sy
            dof += 2.0
        chi2 += w * (r1 * r1 + r2 * r2)
        for a in range(3):
            G[a] += w * (s1 * J1[a] + s2 * J2[a])
            ga = w * (J1[a] * r1 + J2[a] * r2)
            for b in range(3):
                H[a, b] += w * (J1[a] * J1[b] + J2[a] * J2[b])
                B[a, b] += ga * w * (J1[b] * r1 + J2[b] * r2)
    return mask, sum_d2, H, G, B, chi2, dof


#: Information of the weak prior that keeps :func:`refine_with_pitch` near its
#: start: 1 m in position, 2° in heading (a pitch error of 0.05° moves a
#: marking 25 m ahead by 0.36 m).
PITCH_FIT_DAMPING = np.diag([1.0, 1.0, 1.0 / math.radians(2.0) ** 2])


def refine_with_pitch(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    sigma_obs: np.ndarray,
    pose,
    options: Options,
    iterations: int = 5,
) -> tuple[tuple[float, float, float], float, float]:
    """Refine ``pose`` jointly with the camera's pitch error (flat-ground camera).

    A pitch error ``δ`` (radians) moves every ground point along its viewing
    ray by ``(r² + h²) / h · δ`` (``h`` the camera height): the far markings
    stretch together, which a rigid fit can only absorb by shifting the pose
    along the road. Here ``δ`` is a fourth parameter with the prior
    ``N(0, pitch_sigma_deg²)``, estimated by Gauss-Newton with the anisotropic
    pair information of :func:`robust_refine`'s last scale (Geman-McClure
    weights at the finest annealing scale, inliers within the inlier gate;
    segment pairs count across their line only). The pairs are made once, at
    ``pose``, and the pose has a weak prior there
    (:data:`PITCH_FIT_DAMPING`): this is a correction of a few decimetres to
    an optimum already chosen, and where nothing pins the pose along the road
    it stays where the ranking put it.

    Returns
    -------
    pose : (x, y, yaw)
    pitch : float
        The estimated pitch error, radians (undo it with :func:`pitch_corrected`).
    pitch_var : float
        Its posterior variance, radians² (the prior's if nothing matched).
    """
    pose = np.array(pose, float)
    info_pitch = 1.0 / math.radians(options.pitch_sigma_deg) ** 2
    pairs = pitch_pairs(local_map, obs_xy, sigma_obs, pose, options)
    if pairs is None:
        return tuple(float(v) for v in pose), 0.0, 1.0 / info_pitch
    pose, delta, var = _pitch_fit(
        pose, *pairs, float(options.camera_height_m), info_pitch, np.ascontiguousarray(np.diag(PITCH_FIT_DAMPING)),
        float(options.tolerance_m), float(options.tolerance_rad), int(iterations),
    )  # fmt: skip
    return (float(pose[0]), float(pose[1]), float(pose[2])), float(delta), float(var)


def pitch_pairs(local_map: LocalMap, obs_xy: np.ndarray, sigma_obs: np.ndarray, pose, options: Options):
    """The pairs of :func:`refine_with_pitch`, made once at ``pose``; None if fewer than two.

    The pairs are those of the chosen pose and stay fixed: re-paired at every
    step, a fit with no prior on the pose could walk along a road that only a
    few dashes pin down, a dash period in a few steps.

    Returns
    -------
    tuple of arrays, one row per pair
        The observations, their unit viewing rays, their pitch levers
        (metres per radian), their variances along and across the ray at
        the finest annealing scale, the closest points of their markings and
        the markings' unit normals (zero for point-like markings).
    """
    if len(obs_xy) < 2:
        return None
    gate = np.maximum(options.inlier_distance_m, 3.0 * sigma_obs)
    d, tgt, normal = local_map.closest(apply(tuple(pose), obs_xy), float(gate.max()))
    m = np.isfinite(d) & (d <= gate)
    if m.sum() < 2:
        return None
    rng_j = np.hypot(obs_xy[m, 0], obs_xy[m, 1])
    c = options.anneal_m[-1]
    var_t = bearing_sigma(obs_xy[m], options) ** 2 if options.bearing_noise_rad is not None else sigma_obs[m] ** 2
    return (np.ascontiguousarray(obs_xy[m], float), obs_xy[m] / np.maximum(rng_j, 1e-9)[:, None],
            pitch_lever(rng_j, options), c * c + sigma_obs[m] ** 2, c * c + var_t,
            np.ascontiguousarray(tgt[m]), np.ascontiguousarray(normal[m]))  # fmt: skip


@njit(cache=True, nogil=True)
def _pitch_fit(pose, obs, ray, lever, var_r, var_t, tgt, normal, h, info_pitch, damping, tol_m, tol_rad,
               iterations):  # fmt: skip
    """The Gauss-Newton iterations of :func:`refine_with_pitch` over its fixed pairs, compiled.

    ``obs``, ``ray`` (unit viewing rays), ``lever`` (metres per radian of
    pitch), the variances along and across the ray, ``tgt`` and ``normal``
    (zero for point pairs) are those of the paired observations. Returns
    ``(pose, pitch, pitch variance)``.
    """
    n = obs.shape[0]
    pose = pose.copy()
    start = pose.copy()
    delta = 0.0
    var = 1.0 / info_pitch
    H = np.empty((4, 4))
    b = np.empty(4)
    J = np.empty((2, 4))
    info = np.empty((2, 2))
    JtI = np.empty((4, 2))
    for _ in range(iterations):
        H[:] = 0.0
        b[:] = 0.0
        c, s = math.cos(pose[2]), math.sin(pose[2])
        for j in range(n):
            # The observation moved along its ray to undo the pitch (see pitch_corrected).
            r = math.hypot(obs[j, 0], obs[j, 1])
            rr = max(r, 1e-9)
            alpha = math.atan2(h, rr) - delta
            f = h / math.tan(max(alpha, 1e-3)) / rr
            ox, oy = obs[j, 0] * f, obs[j, 1] * f
            qx, qy = c * ox - s * oy, s * ox + c * oy
            ux, uy = c * ray[j, 0] - s * ray[j, 1], s * ray[j, 0] + c * ray[j, 1]
            vx, vy = -uy, ux
            ex, ey = qx + pose[0] - tgt[j, 0], qy + pose[1] - tgt[j, 1]
            nx, ny = normal[j, 0], normal[j, 1]
            seg = nx != 0.0 or ny != 0.0
            if seg:  # on a line only the distance across it is a residual
                en = ex * nx + ey * ny
                ex, ey = en * nx, en * ny
            gm = 1.0 / (1.0 + (ex * ex + ey * ey) / var_r[j]) ** 2
            if seg:
                nu, nv = nx * ux + ny * uy, nx * vx + ny * vy
                g = gm / (nu * nu * var_r[j] + nv * nv * var_t[j])
                info[0, 0], info[0, 1], info[1, 1] = g * nx * nx, g * nx * ny, g * ny * ny
            else:
                info[0, 0] = gm * (ux * ux / var_r[j] + vx * vx / var_t[j])
                info[0, 1] = gm * (ux * uy / var_r[j] + vx * vy / var_t[j])
                info[1, 1] = gm * (uy * uy / var_r[j] + vy * vy / var_t[j])
            info[1, 0] = info[0, 1]
            J[0, 0], J[0, 1], J[0, 2], J[0, 3] = 1.0, 0.0, -qy, ux * lever[j]
            J[1, 0], J[1, 1], J[1, 2], J[1, 3] = 0.0, 1.0, qx, uy * lever[j]
            for a in range(4):
                for t in range(2):
                    JtI[a, t] = J[0, a] * info[0, t] + J[1, a] * info[1, t]
                b[a] -= JtI[a, 0] * ex + JtI[a, 1] * ey
                for bb in range(4):
                    H[a, bb] += JtI[a, 0] * J[0, bb] + JtI[a, 1] * J[1, bb]
        H[3, 3] += info_pitch
        b[3] -= info_pitch * delta
        # A weak prior on the pose, centred where the fit starts: along a road
        # that only solid lines (and dashes matched across only) constrain, the
        # information along it is nearly zero, and an undamped step there is
        # noise amplified, metres long.
        for a in range(3):
            H[a, a] += damping[a]
            b[a] -= damping[a] * (pose[a] - start[a])
        for a in range(4):
            H[a, a] += 1e-9
        try:
            Hinv = np.linalg.inv(H)
        except Exception:  # singular: keep the last pose
            break
        step = Hinv @ b
        var = Hinv[3, 3]
        pose[0] += step[0]
        pose[1] += step[1]
        pose[2] += step[2]
        delta += step[3]
        if math.hypot(step[0], step[1]) < tol_m and abs(step[2]) < tol_rad:
            break
    return pose, delta, var


def pitch_lever(range_m: np.ndarray, options: Options) -> np.ndarray:
    """How far a pitch error moves a ground point along its ray, metres per radian: ``(r² + h²) / h``."""
    h = options.camera_height_m
    return (range_m**2 + h * h) / h


def pitch_corrected(obs_xy: np.ndarray, pitch: float, options: Options) -> np.ndarray:
    """Observations moved along their viewing rays to undo a pitch error (radians), exactly."""
    h = options.camera_height_m
    r = np.hypot(obs_xy[:, 0], obs_xy[:, 1])
    alpha = np.arctan2(h, np.maximum(r, 1e-9)) - pitch
    r_new = h / np.tan(np.maximum(alpha, 1e-3))
    return obs_xy * (r_new / np.maximum(r, 1e-9))[:, None]

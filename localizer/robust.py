"""Robust refinement, hypothesis scoring and covariance of the default method."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .geometry import LocalMap, apply, rotation
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

    All initial poses ``inits`` (K, 3) are refined together (one KD-tree query
    per iteration for all of them). ``record`` keeps the trace of the first.
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
    iters = np.zeros(K, int)
    trace = [tuple(poses[0])] if record else []
    var = sigma_obs**2
    start = np.zeros(K, int) if start_scale is None else np.asarray(start_scale, int).reshape(K)
    # Positions and observations as complex numbers, rotations as unit complex
    # factors: each iteration is a few dozen operations on small (K, N) arrays,
    # so the number of numpy calls is the cost.
    pos = poses[:, 0] + 1j * poses[:, 1]
    yaw = poses[:, 2].copy()
    obs = obs_xy[:, 0] + 1j * obs_xy[:, 1]
    aniso = None
    if options.bearing_noise_rad is not None and N:
        aniso = (var, bearing_sigma(obs_xy, options) ** 2, obs / np.maximum(np.abs(obs), 1e-9))
    for si, c in enumerate(options.anneal_m):
        s2 = c * c + var
        gate = 3.0 * np.sqrt(s2)
        gmax = float(gate.max())
        last = c == options.anneal_m[-1]
        tol = options.tolerance_m if last else max(options.tolerance_m, 0.01)
        wo = np.ones_like(w_obs) if last else w_obs
        wo_s2 = wo / s2
        inv_s2 = 1.0 / s2
        active = start <= si
        for _ in range(options.iterations_per_scale):
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            P, Y = pos[idx], yaw[idx]
            pts = np.multiply.outer(np.exp(1j * Y), obs)
            pts += P[:, None]
            d, tgt = local_map.closest_c(pts.ravel(), gmax, full=False)
            d, tgt = d.reshape(-1, N), tgt.reshape(-1, N)
            m = d <= gate
            # Unmatched observations (d = inf) get t = inf and so weight 0.
            t = d * d
            t *= inv_s2
            t += 1.0
            w = wo_s2 / (t * t)
            w *= m
            wsum = np.add.reduce(w, 1)
            ok = (np.add.reduce(m, 1) >= 2) & (wsum > 0)
            if last and aniso is not None:
                new, th = _gauss_newton_step(pts, tgt, P, Y, w, m, aniso, c)
                new = np.where(ok, new, P)
                th = np.where(ok, th, 0.0)
            else:
                w /= np.where(wsum > 0, wsum, 1.0)[:, None]
                cs = np.add.reduce(w * pts, 1)
                cd = np.add.reduce(w * tgt, 1)
                # Weighted 2D Procrustes: the rotation is the angle of
                # sum w conj(p - cs) (g - cd).
                pts -= cs[:, None]
                tgt -= cd[:, None]
                th = np.where(ok, np.angle(np.add.reduce(w * pts.conjugate() * tgt, 1)), 0.0)
                new = np.where(ok, np.exp(1j * th) * (P - cs) + cd, P)
            step = np.abs(new - P)
            pos[idx] = new
            yaw[idx] = Y + th
            iters[idx[ok]] += 1
            if record and idx[0] == 0 and ok[0]:
                trace.append((float(new[0].real), float(new[0].imag), float(Y[0] + th[0])))
            done = ~ok | ((step < tol) & (np.abs(th) < options.tolerance_rad))
            active[idx[done]] = False
    poses = np.column_stack([pos.real, pos.imag, yaw])
    return [
        RefineResult(pose=tuple(float(v) for v in poses[k]), iterations=int(iters[k]),
                     trace=trace if k == 0 else [])
        for k in range(K)
    ]


def _gauss_newton_step(pts, tgt, P, Y, w_iso, m, aniso, c):
    """One Gauss-Newton step of the rigid fit with anisotropic pair weights.

    A flat-ground camera measures bearing far better than range: along the
    viewing ray an observation's scale is ``s_r = sqrt(c² + σ_r²)``, across
    it ``s_t = sqrt(c² + σ_t²)``. ``w_iso`` holds each pair's Geman-McClure
    weight over ``s_r²`` (from the isotropic residual); the pair's
    information is that times ``u uᵀ + (s_r² / s_t²) v vᵀ``, u the ray and v
    across it. The step is linearised about the current pose and moves the
    vehicle origin by ``(dx, dy)`` and the heading by ``dθ``.
    """
    var_r, var_t, ray = aniso
    sr2 = c * c + var_r
    st2 = c * c + var_t
    uc = (np.exp(1j * Y)[:, None] * ray[None]).conjugate()  # the ray in the map frame, conjugated (K, N)
    eu = np.where(m, pts - tgt, 0.0) * uc  # residual: real part along the ray, imaginary across
    # Jacobian of the point in complex form: d/dx = 1, d/dy = i, d/dθ = i (p - t);
    # rotated into the ray's frame, real parts along the ray, imaginary across.
    J = np.stack([uc, 1j * uc, 1j * (pts - P[:, None]) * uc], axis=-1)  # (K, N, 3)
    Jr, Jt = J.real, J.imag
    Wr = w_iso[..., None] * Jr  # w_iso: Geman-McClure weight / s_r²
    Wt = (w_iso * (sr2 / st2)[None])[..., None] * Jt
    Wr_t, Wt_t = Wr.transpose(0, 2, 1), Wt.transpose(0, 2, 1)
    H = Wr_t @ Jr + Wt_t @ Jt
    b = -(Wr_t @ eu.real[..., None] + Wt_t @ eu.imag[..., None])[..., 0]
    H += np.eye(3) * 1e-9
    try:
        d = np.linalg.solve(H, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        d = np.zeros_like(b)
    return P + d[:, 0] + 1j * d[:, 1], d[:, 2]


def log_prior(pose, prior_pose, sigma_p: float, sigma_yaw: float) -> float:
    dx = pose[0] - prior_pose[0]
    dy = pose[1] - prior_pose[1]
    dyaw = (pose[2] - prior_pose[2] + math.pi) % (2 * math.pi) - math.pi
    return -0.5 * ((dx * dx + dy * dy) / sigma_p**2 + (dyaw / sigma_yaw) ** 2)


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
    P = np.asarray(poses, float).reshape(-1, 3)
    K, N = len(P), len(obs_xy)
    cos, sin = np.cos(P[:, 2]), np.sin(P[:, 2])
    px = cos[:, None] * obs_xy[None, :, 0] - sin[:, None] * obs_xy[None, :, 1] + P[:, 0, None]
    py = sin[:, None] * obs_xy[None, :, 0] + cos[:, None] * obs_xy[None, :, 1] + P[:, 1, None]
    pts = np.stack([px, py], -1)
    s = np.sqrt(SCORE_FLOOR_M**2 + sigma_obs**2)
    d, tgt, _, which = local_map.closest(pts.reshape(-1, 2), 4.0 * float(s.max()), return_index=True)
    d, which = d.reshape(K, N), which.reshape(K, N)
    fin = np.isfinite(d)
    if options.bearing_noise_rad is None:
        u2 = (np.where(fin, d, 0.0) / s[None]) ** 2
    else:
        st = np.sqrt(SCORE_FLOOR_M**2 + bearing_sigma(obs_xy, options) ** 2)
        e = (pts.reshape(-1, 2) - tgt).reshape(K, N, 2)
        bear = P[:, 2, None] + np.arctan2(obs_xy[None, :, 1], obs_xy[None, :, 0])
        er = e[..., 0] * np.cos(bear) + e[..., 1] * np.sin(bear)
        et = -e[..., 0] * np.sin(bear) + e[..., 1] * np.cos(bear)
        u2 = np.where(fin, (er / s[None]) ** 2 + (et / st[None]) ** 2, 0.0)
    k = np.where(fin, np.exp(-0.5 * u2), 0.0)
    # A solid-line piece explains an observation anywhere along its length: its
    # density is spread over the length, so a match on it is weaker evidence.
    half = np.where(which >= 0, local_map.half[np.maximum(which, 0)], 0.0)
    seg = half > 0
    k[seg] *= np.minimum(1.0, (math.sqrt(2 * math.pi) * s[None] / np.maximum(2 * half, 1e-9))[seg])
    score = np.sum(w_obs[None] * np.log1p(k / options.outlier_density), axis=1)
    return score - miss_costs(local_map, obs_xy, P, options, view)


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
    cos, sin = np.cos(P[:, 2]), np.sin(P[:, 2])
    dx = E[None, :, 0] - P[:, 0, None]
    dy = E[None, :, 1] - P[:, 1, None]
    vx = cos[:, None] * dx + sin[:, None] * dy
    vy = -sin[:, None] * dx + cos[:, None] * dy
    r2 = vx * vx + vy * vy
    seen = (r2 >= rmin * rmin) & (r2 <= rmax * rmax) & (np.abs(vy) <= np.tan(halfang) * vx) & (vx > 0)
    kk, ee = np.nonzero(seen)
    if kk.size == 0:
        return out
    tree = cKDTree(obs_xy)
    q = np.column_stack([vx[kk, ee], vy[kk, ee]])
    dist, _ = tree.query(q, distance_upper_bound=options.explain_distance_m)
    missed = ~np.isfinite(dist)
    on_line = local_map.expect_solid[ee]
    if options.solid_explain_along_m > 0 and (line := np.flatnonzero(missed & on_line)).size:
        missed[line] = ~_explained_along_line(tree, obs_xy, q[line], local_map.expect_axis[ee[line]],
                                              cos[kk[line]], sin[kk[line]], options)
    np.add.at(out[0], kk[missed & ~on_line], 1.0)
    np.add.at(out[1], kk[missed & on_line], 1.0)
    return out


def _explained_along_line(tree, obs_xy, q, axis, cos, sin, options: Options) -> np.ndarray:
    """Which expected solid-line clusters ``q`` (vehicle frame) an observation explains along their line.

    ``axis`` is each line's direction in the map, ``cos``/``sin`` the pose's
    heading: explained where one of the (four) nearest observations lies within
    ``solid_explain_along_m`` along the line and ``solid_explain_across_m``
    across it.
    """
    along_max = options.solid_explain_along_m
    d, i = tree.query(q, k=min(4, len(obs_xy)), distance_upper_bound=along_max)
    d, i = d.reshape(len(q), -1), i.reshape(len(q), -1)
    near = np.isfinite(d)
    ux = cos * axis[:, 0] + sin * axis[:, 1]  # the line's direction in the vehicle frame
    uy = -sin * axis[:, 0] + cos * axis[:, 1]
    ob = obs_xy[np.where(near, i, 0)]
    ex, ey = ob[..., 0] - q[:, None, 0], ob[..., 1] - q[:, None, 1]
    along = np.abs(ex * ux[:, None] + ey * uy[:, None])
    across = np.abs(ey * ux[:, None] - ex * uy[:, None])
    return (near & (along <= along_max) & (across <= options.solid_explain_across_m)).any(axis=1)


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
    p = apply(pose, obs_xy)
    gate = np.maximum(options.inlier_distance_m, 3.0 * sigma_obs)
    d, tgt, normal = local_map.closest(p, float(gate.max()))
    m = np.isfinite(d) & (d <= gate)
    n = int(m.sum())
    if n == 0:
        return Fit(0, None, None, m)
    rms = float(np.sqrt(np.mean(d[m] ** 2)))
    if n < 2:
        return Fit(n, rms, None, m)
    q = (rotation(pose[2]) @ obs_xy[m].T).T  # lever arms from the vehicle origin
    r = p[m] - tgt[m]
    w = w_obs[m] / sigma_obs[m] ** 2
    rng_j = np.hypot(obs_xy[m, 0], obs_xy[m, 1])
    drdp = pitch_lever(rng_j, options)
    radial = q / np.maximum(rng_j, 1e-9)[:, None]
    shift = radial * drdp[:, None]
    # Rows of the Jacobian: two per point pair (x, y), one per segment pair
    # (across the line: the normal times the point rows).
    nv = normal[m]
    seg = nv.any(axis=1)
    jx = np.column_stack([np.ones(n), np.zeros(n), -q[:, 1]])
    jy = np.column_stack([np.zeros(n), np.ones(n), q[:, 0]])
    js = nv[:, :1] * jx + nv[:, 1:] * jy
    # Per pair: first row (x, or across the line), second row (y; zero for segments).
    J1 = np.where(seg[:, None], js, jx)
    J2 = np.where(seg[:, None], 0.0, jy)
    r1 = np.where(seg, np.einsum("nd,nd->n", nv, r), r[:, 0])
    r2 = np.where(seg, 0.0, r[:, 1])
    s1 = np.where(seg, np.einsum("nd,nd->n", nv, shift), shift[:, 0])
    s2_ = np.where(seg, 0.0, shift[:, 1])
    H = (J1 * w[:, None]).T @ J1 + (J2 * w[:, None]).T @ J2
    G = (w * s1) @ J1 + (w * s2_) @ J2
    g = (J1 * r1[:, None] + J2 * r2[:, None]) * w[:, None]
    B = g.T @ g
    chi2 = float(np.sum(w * (r1 * r1 + r2 * r2)))
    dof = float(np.sum(np.where(seg, 1.0, 2.0)))
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
    n = len(obs_xy)
    if n < 2:
        return tuple(float(v) for v in pose), 0.0, math.radians(options.pitch_sigma_deg) ** 2
    rng_j = np.hypot(obs_xy[:, 0], obs_xy[:, 1])
    ray_v = obs_xy / np.maximum(rng_j, 1e-9)[:, None]
    k = pitch_lever(rng_j, options)
    c = options.anneal_m[-1]
    var_r = c * c + sigma_obs**2
    bn = options.bearing_noise_rad
    var_t = c * c + (bearing_sigma(obs_xy, options) ** 2 if bn is not None else sigma_obs**2)
    gate = np.maximum(options.inlier_distance_m, 3.0 * sigma_obs)
    info_pitch = 1.0 / math.radians(options.pitch_sigma_deg) ** 2
    delta = 0.0
    var = 1.0 / info_pitch
    # The pairs are those of the chosen pose and stay fixed: re-paired at
    # every step, a fit with no prior on the pose could walk along a road
    # that only a few dashes pin down, a dash period in a few steps.
    d, tgt, normal = local_map.closest(apply(tuple(pose), obs_xy), float(gate.max()))
    m = np.isfinite(d) & (d <= gate)
    if m.sum() < 2:
        return tuple(float(v) for v in pose), 0.0, 1.0 / info_pitch
    tgt, normal = tgt[m], normal[m]
    seg = normal.any(axis=1)
    start = pose.copy()
    for _ in range(iterations):
        o = pitch_corrected(obs_xy, delta, options)
        p = apply(tuple(pose), o)[m]
        R = rotation(pose[2])
        q = (R @ o[m].T).T
        u = (R @ ray_v[m].T).T
        v = np.column_stack([-u[:, 1], u[:, 0]])
        e = p - tgt
        # On a line only the distance across it is a residual.
        e[seg] = (e[seg] * normal[seg]).sum(1, keepdims=True) * normal[seg]
        d2 = (e * e).sum(1)
        gm = 1.0 / (1.0 + d2 / var_r[m]) ** 2
        # Per pair: a 2x2 information (ray / across) for points, the normal's
        # variance for segments.
        info = gm[:, None, None] * (np.einsum("ni,nj->nij", u, u) / var_r[m][:, None, None]
                                    + np.einsum("ni,nj->nij", v, v) / var_t[m][:, None, None])
        if seg.any():
            nv = normal[seg]
            var_n = (nv * u[seg]).sum(1) ** 2 * var_r[m][seg] + (nv * v[seg]).sum(1) ** 2 * var_t[m][seg]
            info[seg] = gm[seg, None, None] * np.einsum("ni,nj->nij", nv, nv) / var_n[:, None, None]
        J = np.zeros((len(e), 2, 4))
        J[:, 0, 0] = 1.0
        J[:, 1, 1] = 1.0
        J[:, 0, 2] = -q[:, 1]
        J[:, 1, 2] = q[:, 0]
        J[:, :, 3] = u * k[m][:, None]
        JtI = np.einsum("nki,nkl->nil", J, info)
        H = np.einsum("nil,nlj->ij", JtI, J)
        b = -np.einsum("nil,nl->i", JtI, e)
        H[3, 3] += info_pitch
        b[3] -= info_pitch * delta
        # A weak prior on the pose, centred where the fit starts: along a road
        # that only solid lines (and dashes matched across only) constrain, the
        # information along it is nearly zero, and an undamped step there is
        # noise amplified, metres long.
        H[:3, :3] += PITCH_FIT_DAMPING
        b[:3] -= PITCH_FIT_DAMPING @ (pose - start)
        try:
            Hinv = np.linalg.inv(H + np.eye(4) * 1e-9)
        except np.linalg.LinAlgError:
            break
        step = Hinv @ b
        var = float(Hinv[3, 3])
        pose += step[:3]
        delta += step[3]
        if np.hypot(step[0], step[1]) < options.tolerance_m and abs(step[2]) < options.tolerance_rad:
            break
    return tuple(float(v) for v in pose), float(delta), var


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

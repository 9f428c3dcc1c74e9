"""Robust refinement, hypothesis scoring and covariance of the default method."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import LocalMap, apply, compose, rotation, weighted_rigid_fit
from .types import Options


def noise_sigma(obs_xy: np.ndarray, options: Options) -> np.ndarray:
    """Per-observation position noise of a flat-ground camera, metres: ``a + b r²``."""
    r2 = np.einsum("nd,nd->n", obs_xy, obs_xy)
    return options.noise_m + options.noise_range_coeff * r2


def data_weights(gamma: np.ndarray) -> np.ndarray:
    """Pixel counts scaled to mean-like 1 and capped, so no single cluster dominates."""
    med = float(np.median(gamma)) if gamma.size else 1.0
    return np.minimum(gamma / max(med, 1e-12), 3.0)


@dataclass
class RefineResult:
    pose: tuple[float, float, float]
    iterations: int
    trace: list[tuple[float, float, float]] = field(default_factory=list)


def robust_refine(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    w_obs: np.ndarray,
    init,
    options: Options,
    iterations_per_scale: int = 8,
    record: bool = False,
) -> RefineResult:
    """IRLS with a Geman-McClure kernel whose scale is annealed coarse to fine.

    Pairs are point-to-point for point-like markings and point-to-segment for
    line-like ones; a pair's weight is ``w_obs * c**4 / (c**2 + d**2)**2`` at
    scale ``c`` (pairs beyond ``3 c`` are dropped).
    """
    pose = tuple(float(v) for v in init)
    trace = [pose] if record else []
    total = 0
    for c in options.anneal_m:
        for _ in range(iterations_per_scale):
            p = apply(pose, obs_xy)
            d, tgt, _ = local_map.closest(p, 3.0 * c)
            m = np.isfinite(d)
            if m.sum() < 2:
                break
            c2 = c * c
            w = w_obs[m] * (c2 / (c2 + d[m] ** 2)) ** 2
            dtheta, dt = weighted_rigid_fit(p[m], tgt[m], w)
            new = compose(dtheta, dt, pose)
            step = math.hypot(new[0] - pose[0], new[1] - pose[1])
            pose = new
            total += 1
            if record:
                trace.append(pose)
            if step < options.tolerance_m and abs(dtheta) < options.tolerance_rad:
                break
    return RefineResult(pose=pose, iterations=total, trace=trace)


def log_prior(pose, prior_pose, sigma_p: float, sigma_yaw: float) -> float:
    dx = pose[0] - prior_pose[0]
    dy = pose[1] - prior_pose[1]
    dyaw = (pose[2] - prior_pose[2] + math.pi) % (2 * math.pi) - math.pi
    return -0.5 * ((dx * dx + dy * dy) / sigma_p**2 + (dyaw / sigma_yaw) ** 2)


def data_score(local_map: LocalMap, obs_xy, w_obs, sigma_obs, pose, options: Options) -> float:
    """Weighted log-likelihood ratio (matched vs outlier) of the observations at ``pose``."""
    p = apply(pose, obs_xy)
    s = np.sqrt(0.15**2 + sigma_obs**2)
    d, _, _ = local_map.closest(p, 4.0 * float(s.max()))
    k = np.where(np.isfinite(d), np.exp(-0.5 * (np.where(np.isfinite(d), d, 0.0) / s) ** 2), 0.0)
    return float(np.sum(w_obs * np.log1p(k / options.outlier_density)))


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
) -> Fit:
    """Inliers, RMS residual and covariance of ``pose``.

    The covariance is the average of the model-based ``s² H⁻¹`` (``s²`` the
    weighted residual variance) and the sandwich estimate ``H⁻¹ B H⁻¹``, which
    follows anisotropic residuals; segment pairs contribute only across their
    line, so a view of a single solid line leaves the along-line direction to
    the prior information ``prior_info`` (3x3, added to the data information).
    """
    p = apply(pose, obs_xy)
    d, tgt, normal = local_map.closest(p, options.inlier_distance_m)
    m = np.isfinite(d)
    n = int(m.sum())
    if n == 0:
        return Fit(0, None, None, m)
    rms = float(np.sqrt(np.mean(d[m] ** 2)))
    if n < 2:
        return Fit(n, rms, None, m)
    q = (rotation(pose[2]) @ obs_xy[m].T).T  # lever arms from the vehicle origin
    r = p[m] - tgt[m]
    w = w_obs[m] / sigma_obs[m] ** 2
    H = np.zeros((3, 3))
    B = np.zeros((3, 3))
    chi2 = 0.0
    dof = 0.0
    for j in range(n):
        J = np.array([[1.0, 0.0, -q[j, 1]], [0.0, 1.0, q[j, 0]]])
        nv = normal[m][j]
        if nv.any():
            J = nv[None, :] @ J
            rr = np.array([nv @ r[j]])
        else:
            rr = r[j]
        H += w[j] * J.T @ J
        g = J.T @ rr * w[j]
        B += np.outer(g, g)
        chi2 += w[j] * float(rr @ rr)
        dof += rr.size
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
    cov = 0.5 * (model + sandwich)
    cov = options.covariance_inflation * 0.5 * (cov + cov.T)
    return Fit(n, rms, cov, m)

"""The matching of Pink (2008), section 4: robust ICP on marking centroids.

Each iteration pairs every observation with its nearest map centroid (pairs
farther than a maximum distance are dropped), weights each pair by the mixed
l1/l2 iteratively-reweighted-least-squares weight ``1 / max(d, ε)`` times the
observation's pixel count γ, and solves the weighted 2D rigid fit in closed
form. The increment is composed onto the pose until it becomes smaller than a
tolerance or an iteration cap is reached. The paper leaves ε and the maximum
distance open; the defaults in :class:`localizer.types.Options` were chosen
on the benchmark (``benchmarks/localize_paper.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import LocalMap, apply, compose, weighted_rigid_fit
from .types import Options


@dataclass
class IcpResult:
    """Outcome of :func:`pink2008_icp` (poses relative to the local map origin)."""

    pose: tuple[float, float, float]
    iterations: int
    converged: bool
    distances: np.ndarray  # final pairing distance of each observation (inf: unpaired)
    trace: list[tuple[float, float, float]] = field(default_factory=list)


def pink2008_icp(
    local_map: LocalMap,
    obs_xy: np.ndarray,
    gamma: np.ndarray,
    init,
    options: Options = Options(),
) -> IcpResult:
    """Run the paper's ICP/IRLS from ``init`` = (x, y, yaw) in local map coordinates.

    Parameters
    ----------
    local_map : LocalMap
        Map centroids around the prior (only centroids are used, as in the paper).
    obs_xy : (N, 2) ndarray
        Observed centroids in the vehicle frame, metres.
    gamma : (N,) ndarray
        Pixel counts of the observations.
    init : tuple
        Initial pose (x, y, yaw grid radians).
    options : Options
        ``max_pair_distance_m``, ``epsilon_m``, ``max_iterations``, ``tolerance_*``.
    """
    pose = tuple(float(v) for v in init)
    trace = [pose]
    converged = False
    it = 0
    d = np.full(len(obs_xy), np.inf)
    for it in range(1, options.max_iterations + 1):
        p = apply(pose, obs_xy)
        d, target = local_map.nearest_centroid(p, options.max_pair_distance_m)
        m = np.isfinite(d)
        if m.sum() < 2:
            it -= 1
            break
        w = gamma[m] / np.maximum(d[m], options.epsilon_m)
        dtheta, dt = weighted_rigid_fit(p[m], target[m], w)
        new = compose(dtheta, dt, pose)
        step = math.hypot(new[0] - pose[0], new[1] - pose[1])
        pose = new
        trace.append(pose)
        if step < options.tolerance_m and abs(dtheta) < options.tolerance_rad:
            converged = True
            break
    p = apply(pose, obs_xy)
    d, _ = local_map.nearest_centroid(p, options.max_pair_distance_m)
    return IcpResult(pose=pose, iterations=it, converged=converged, distances=d, trace=trace)

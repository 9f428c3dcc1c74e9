"""The public entry point :func:`localize`."""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .errors import LocalizationInputError
from .frames import GeoFrame, wrap_angle
from .geometry import LocalMap, homogeneous
from .index import MapIndex
from .pink2008 import pink2008_icp
from .robust import (
    count_inliers,
    data_scores,
    crowd_weights,
    data_weights,
    fit_statistics,
    log_prior,
    miss_costs,
    missed_counts,
    mixture_covariance,
    noise_sigma,
    pitch_corrected,
    refine_with_pitch,
    robust_refine,
    view_of,
)
from .search import Candidate, correlative_search, search_observations
from .types import ErrorEllipse, Hypothesis, Options, Pose, Prior

log = logging.getLogger(__name__)

METHODS = ("default", "pink2008")

#: Accepted prior standard deviations. Below the lower bounds a prior would
#: override every observation (and make the search grid degenerate); the upper
#: bounds are those of the HTTP API.
PRIOR_POSITION_SIGMA_RANGE_M = (0.01, 1000.0)
PRIOR_HEADING_SIGMA_RANGE_DEG = (0.01, 180.0)

#: Coarsest translation step of the global search, metres. The step grows with
#: the search radius (a thirtieth of it) up to this: with 1.4 m cells a 20 m /
#: ±30° prior found a candidate near the true pose in fewer than half of the
#: scenes (the correlation kernel, as wide as a cell, blurs neighbouring
#: markings together); with 0.75 m cells success from there rose from 38 % to
#: 52 % on the calibration seed, and such a search costs 25-35 ms of CPU.
MAX_SEARCH_CELL_M = 0.75


#: The benchmarked options. Options validate every field when built, which a
#: request would otherwise pay each time; they are frozen, so one is shared.
DEFAULT_OPTIONS = Options()


def parse_observations(
    observations, max_count: int = 500, max_range_m: float = 150.0
) -> np.ndarray:
    """Validate observations into an ``(N, 3)`` array of ``x, y, weight``.

    Parameters
    ----------
    observations : array_like (N, 3) or sequence of mappings
        Vehicle-frame centroids (x forward, y left, metres) and weights γ > 0;
        a mapping needs ``x`` and ``y``, ``weight`` defaults to 1.
    max_count : int
        Largest accepted N.
    max_range_m : float
        Observations farther from the vehicle are rejected (a camera sees the
        ground a few tens of metres ahead; far values are unit or frame errors).

    Raises
    ------
    LocalizationInputError
        On malformed, non-finite or non-positive-weight values, or too many rows.
    """
    if isinstance(observations, Mapping):
        raise LocalizationInputError("observations: expected a list or an (N, 3) array, got a mapping")
    if isinstance(observations, np.ndarray):
        arr = observations
    elif isinstance(observations, Sequence) and observations and isinstance(observations[0], Mapping):
        rows = []
        for k, ob in enumerate(observations):
            if not isinstance(ob, Mapping) or "x" not in ob or "y" not in ob:
                raise LocalizationInputError(f"observations[{k}]: needs keys 'x' and 'y'")
            try:
                rows.append((float(ob["x"]), float(ob["y"]), float(ob.get("weight", 1.0))))
            except (TypeError, ValueError) as exc:
                raise LocalizationInputError(f"observations[{k}]: values must be numbers") from exc
        arr = np.array(rows, float)
    else:
        try:
            arr = np.asarray(observations, float)
        except (TypeError, ValueError) as exc:
            raise LocalizationInputError("observations: not an array of numbers") from exc
    try:
        arr = np.asarray(arr, float)
    except (TypeError, ValueError) as exc:
        raise LocalizationInputError("observations: not an array of numbers") from exc
    if arr.size == 0:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise LocalizationInputError(f"observations: expected shape (N, 3), got {arr.shape}")
    if arr.shape[1] == 2:
        arr = np.column_stack([arr, np.ones(len(arr))])
    if len(arr) > max_count:
        raise LocalizationInputError(
            f"observations: {len(arr)} given, at most {max_count} are accepted per frame"
        )
    if not np.all(np.isfinite(arr)):
        raise LocalizationInputError("observations: contain NaN or infinite values")
    if np.any(arr[:, 2] <= 0):
        raise LocalizationInputError("observations: weights must be positive")
    far = np.hypot(arr[:, 0], arr[:, 1]) > max_range_m
    if far.any():
        raise LocalizationInputError(
            f"observations: {int(far.sum())} lie farther than {max_range_m:g} m from the vehicle "
            "(expected metres in the vehicle frame)"
        )
    return arr


def _check_prior(prior: Prior) -> None:
    if not isinstance(prior, Prior):
        raise LocalizationInputError("prior: expected a localizer.Prior")
    for name in ("lat", "lon", "heading_deg", "position_sigma_m", "heading_sigma_deg"):
        v = getattr(prior, name)
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
            raise LocalizationInputError(f"prior.{name}: must be a finite number, got {v!r}")
    if not -90.0 <= prior.lat <= 90.0:
        raise LocalizationInputError(f"prior.lat: {prior.lat} is outside [-90, 90]")
    if not -180.0 <= prior.lon <= 180.0:
        raise LocalizationInputError(f"prior.lon: {prior.lon} is outside [-180, 180]")
    lo, hi = PRIOR_POSITION_SIGMA_RANGE_M
    if not lo <= prior.position_sigma_m <= hi:
        raise LocalizationInputError(
            f"prior.position_sigma_m: {prior.position_sigma_m!r} is outside [{lo:g}, {hi:g}] m "
            "(a GPS fix is never exact, and a sigma of kilometres says nothing)"
        )
    if prior.position_ellipse is not None:
        _check_ellipse(prior.position_ellipse)
    lo, hi = PRIOR_HEADING_SIGMA_RANGE_DEG
    if not lo <= prior.heading_sigma_deg <= hi:
        raise LocalizationInputError(
            f"prior.heading_sigma_deg: {prior.heading_sigma_deg!r} is outside [{lo:g}, {hi:g}] degrees"
        )


def _check_ellipse(e) -> None:
    if not isinstance(e, ErrorEllipse):
        raise LocalizationInputError("prior.position_ellipse: expected a localizer.ErrorEllipse")
    for name in ("sigma_major_m", "sigma_minor_m", "orientation_deg"):
        v = getattr(e, name)
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
            raise LocalizationInputError(f"prior.position_ellipse.{name}: must be a finite number, got {v!r}")
    lo, hi = PRIOR_POSITION_SIGMA_RANGE_M
    for name in ("sigma_major_m", "sigma_minor_m"):
        v = getattr(e, name)
        if not lo <= v <= hi:
            raise LocalizationInputError(
                f"prior.position_ellipse.{name}: {v!r} is outside [{lo:g}, {hi:g}] m")
    if e.sigma_minor_m > e.sigma_major_m:
        raise LocalizationInputError(
            f"prior.position_ellipse: sigma_minor_m {e.sigma_minor_m!r} is larger than "
            f"sigma_major_m {e.sigma_major_m!r}")


def position_covariance(prior: Prior, frame: GeoFrame) -> np.ndarray:
    """The prior's 2x2 position covariance in the map CRS's axes, m².

    An error ellipse's orientation is a true bearing; it is turned into the
    grid by the meridian convergence at the fix, like a heading.
    """
    e = prior.position_ellipse
    if e is None:
        return np.eye(2) * float(prior.position_sigma_m) ** 2
    a = float(frame.heading_to_grid_yaw(e.orientation_deg, prior.lon, prior.lat))
    u = np.array([math.cos(a), math.sin(a)])
    v = np.array([-u[1], u[0]])
    return e.sigma_major_m**2 * np.outer(u, u) + e.sigma_minor_m**2 * np.outer(v, v)


def localize(
    map_index: MapIndex,
    observations,
    prior: Prior,
    method: str = "default",
    options: Options | None = None,
) -> Pose:
    """Localize a vehicle against a marking map.

    Parameters
    ----------
    map_index : MapIndex
        The map (see :meth:`MapIndex.from_arrays`), shared between calls.
    observations : (N, 3) array_like or list of {"x", "y", "weight"}
        Marking centroids seen by the camera in the vehicle frame (x forward,
        y left, metres) with their pixel counts γ.
    prior : Prior
        GPS fix (WGS84, heading clockwise from true north) with its uncertainty.
    method : {"default", "pink2008"}
        ``default``: global correlative search over the prior's uncertainty,
        robust annealed refinement, ambiguity detection and a calibrated
        covariance. ``pink2008``: the paper's ICP with mixed l1/l2 IRLS from the prior.
    options : Options, optional
        Tuning; defaults are the benchmarked ones.

    Returns
    -------
    Pose
        ``status`` is ``ok``, ``ambiguous`` (see ``hypotheses``) or ``failed``
        (see ``reason``).

    Raises
    ------
    LocalizationInputError
        For malformed input (NaN/inf, non-positive weights, too many
        observations, an invalid prior or method).
    """
    options = options or DEFAULT_OPTIONS
    if method not in METHODS:
        raise LocalizationInputError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    if not isinstance(map_index, MapIndex):
        raise LocalizationInputError("map_index: expected a localizer.MapIndex")
    obs = parse_observations(observations, options.max_observations, options.max_observation_range_m)
    _check_prior(prior)
    frame = map_index.frame
    crs = map_index.crs
    if len(obs) == 0:
        return Pose(status="failed", crs=crs, reason="no observations")
    px, py = frame.to_xy(prior.lon, prior.lat)
    if not (math.isfinite(px) and math.isfinite(py)):
        raise LocalizationInputError("prior: lat/lon cannot be projected to the map CRS")
    # the widest direction of the position prior sets the search's reach
    sigma_p = float(prior.position_sigma_m if prior.position_ellipse is None
                    else prior.position_ellipse.sigma_major_m)
    sigma_yaw = math.radians(prior.heading_sigma_deg)
    obs_xy = obs[:, :2]
    gamma = obs[:, 2]
    rho = float(np.max(np.hypot(obs_xy[:, 0], obs_xy[:, 1])))

    edge = None  # why a sure answer is not (Options.edge_share)
    if method == "pink2008":
        reach = options.max_pair_distance_m * 3 + rho
        radius = reach
    else:
        radius = min(
            max(options.search_sigmas * sigma_p, options.min_search_radius_m),
            options.max_search_radius_m,
        )
        reach = radius + rho + 5.0
    local = LocalMap(map_index, (px, py), reach)
    if len(local) == 0:
        return Pose(
            status="failed",
            crs=crs,
            reason=f"no map markings within {reach:.0f} m of the prior",
        )
    # Only now: far outside the CRS's area (where a map never is) the meridian
    # convergence is undefined.
    yaw0 = float(frame.heading_to_grid_yaw(prior.heading_deg, prior.lon, prior.lat))
    if not math.isfinite(yaw0):
        raise LocalizationInputError("prior: the heading cannot be converted to the map CRS at this position")
    prior_pose = (0.0, 0.0, yaw0)
    pos_cov = position_covariance(prior, frame)
    pos_info = np.linalg.inv(pos_cov)
    prior_info = np.zeros((3, 3))
    prior_info[:2, :2] = pos_info
    prior_info[2, 2] = 1 / sigma_yaw**2
    w_data = data_weights(gamma) if method == "pink2008" else _observation_weights(obs, options)
    sig = noise_sigma(obs_xy, options)

    if method == "pink2008":
        res = pink2008_icp(local, obs_xy, gamma, prior_pose, options)
        pose, iterations, trace = res.pose, res.iterations, res.trace
        hyps: list[tuple[tuple[float, float, float], float]] = [(pose, 1.0)]
        log_scores = [None]
        probability = None
        fits = {}
        status = "ok"
        diagnostics = {}
        need = options.min_inliers
    else:
        cell = options.search_cell_m or float(np.clip(radius / 30.0, 0.5, MAX_SEARCH_CELL_M))
        yaw_half_range = min(options.search_sigmas * sigma_yaw, math.pi)
        top = search_observations(
            obs_xy, np.argsort(-w_data, kind="stable")[: options.max_search_observations], radius,
            yaw_half_range, cell, options.max_search_cells, options.max_search_work,
        )
        if len(top) < min(len(obs_xy), options.max_search_observations):
            log.debug("coarse search within its budget: %d of %d observations", len(top), len(obs_xy))
        n_refine = options.candidates + options.extra_candidates
        cands = correlative_search(
            local, obs_xy[top], w_data[top], prior_pose, radius, yaw_half_range, pos_info, sigma_yaw, cell,
            options.outlier_density, max(n_refine, options.coarse_pool), options.temperature,
        )
        view = view_of(obs_xy, options)
        if options.coarse_pool:
            cands = _with_negative_evidence(local, obs_xy, cands, options, view)[:n_refine]
        if cands:
            # Candidates far below the best cannot become competitive.
            floor = cands[0].score - options.candidate_margin
            cands = [c for k, c in enumerate(cands) if k < 4 or c.score >= floor]
        # Each refinement iterates over every observation: hundreds of them
        # (clutter) get fewer candidates, the best ones.
        per_pass = max(4, options.max_refine_work // len(obs_xy))
        if per_pass < max(options.candidates, options.extra_candidates):
            log.debug("refinement within its budget: %d candidates a pass for %d observations",
                      per_pass, len(obs_xy))
        first = cands[: min(options.candidates, per_pass)]
        extra = cands[options.candidates: options.candidates + min(options.extra_candidates, per_pass)]
        # The prior itself is always refined too: when clutter dominates the
        # coarse correlation, the few true matches may still pull a refinement
        # started at the GPS fix to the right pose.
        if first and not any(math.hypot(c.x, c.y) < 0.5 and abs(wrap_angle(c.yaw - yaw0)) < math.radians(1.0)
                             for c in first):
            first.append(Candidate(0.0, 0.0, yaw0, -math.inf))
        scene = _Scene(local, obs_xy, w_data, sig, options, view, prior_pose, pos_info, sigma_yaw, prior_info)
        refined = _refine_candidates(scene, first)
        if not refined:
            return Pose(status="failed", crs=crs, reason="the global search found no candidate")
        ranked = _rank_hypotheses(scene, refined)
        # An answer that is not beyond doubt gets the coarse optima after the
        # first ones refined too: they hold the truth when clutter or a wide
        # prior crowded it out of the first, and a rival found there makes an
        # answer ambiguous that would otherwise have been confidently wrong.
        searched = first
        if extra and ranked.prob[0] < options.extra_search_probability:
            refined = refined + _refine_candidates(scene, extra)
            ranked = _rank_hypotheses(scene, refined)
            searched = first + extra
        if options.heading_restarts and sigma_p >= _HEADING_RESTART_MIN_M:
            turned = _heading_restarts(ranked, searched, options.heading_restarts)
            if turned:
                refined = refined + _refine_candidates(scene, turned)
                ranked = _rank_hypotheses(scene, refined)
        if options.neighbour_starts:
            # The coarse grid's cells are about as wide as a basin on a map with
            # short or shifted markings: the best candidate's refinement can
            # settle in a basin next to the truth's while no coarse candidate
            # lay in the truth's. Restarts around the answer find the
            # neighbouring basins; a better one wins, an equal one makes the
            # answer ambiguous instead of confidently wrong.
            near = _neighbour_starts(ranked.kept[0][1].pose, options)
            refined = refined + _refine_candidates(scene, near, fine_only=True)
            ranked = _rank_hypotheses(scene, refined)
        all_search = [(c.x + px, c.y + py, c.yaw, c.score) for c in searched]
        kept, scores, prob, score_options = ranked.kept, ranked.scores, ranked.prob, ranked.score_options
        need = ranked.need
        kept_poses = [k[1].pose for k in kept]
        fits = {ranked.best_pose: ranked.best_fit}
        best = kept[0][1]
        pose, iterations = best.pose, best.iterations
        if options.estimate_pitch:
            # The joint fit corrects the chosen optimum. One that leaves it fewer
            # matches than a fix needs answers `failed`: the rigid optimum's
            # matches did not survive a small change of the camera model, and
            # keeping it was measured to answer poses 0.8-0.9 m off (a drive's
            # frame with one marking among clutter; a single frame whose truth
            # ranked second).
            pose, pitch, pitch_var = refine_with_pitch(local, obs_xy, sig, pose, options)
            kept[0] = (kept[0][0], replace(best, pose=pose)) + tuple(kept[0][2:])
            fit_obs = pitch_corrected(obs_xy, pitch, options)
            fits = {pose: fit_statistics(local, fit_obs, w_data, noise_sigma(fit_obs, options), pose,
                                         options, prior_info, pitch_var=pitch_var)}
        trace = []
        if options.record_trace:
            start = (kept[0][2].x, kept[0][2].y, kept[0][2].yaw)
            again = robust_refine(local, obs_xy, w_data, sig, [start], kept[0][3], record=True)[0]
            trace = [prior_pose] + again.trace
            if options.estimate_pitch:
                trace.append(pose)  # the joint fit with the pitch is the last step
        hyps = [(k[1].pose, float(p)) for k, p in zip(kept, prob)]
        log_scores = [float(v) for v in scores]
        diagnostics = {"search": all_search, "search_observations": len(top)}
        if options.record_candidates:
            n_pt, n_sol = missed_counts(local, obs_xy, kept_poses, options, view)
            pos = data_scores(local, obs_xy, w_data, sig, kept_poses,
                              replace(score_options, miss_probability=1.0, solid_miss_probability=1.0), view)
            diagnostics["candidates"] = [
                {"pose": (k[1].pose[0] + px, k[1].pose[1] + py, k[1].pose[2]), "score": k[0],
                 "prior": log_prior(k[1].pose, prior_pose, pos_info, sigma_yaw),
                 "positive": float(pos[i]), "missed_points": int(n_pt[i]),
                 "missed_solid": int(n_sol[i]),
                 "search": (k[2].x + px, k[2].y + py, k[2].yaw, k[2].score)}
                for i, k in enumerate(kept)
            ]
        probability = float(prob[0])
        # At the map's edge a sure answer is not, and no answer's hypotheses
        # can be trusted to hold the truth (see with_prior_uncertainty).
        edge = _beyond_edge(map_index, local.origin, obs_xy, w_data, pose, pos_cov, options)
        status = "ok" if probability >= options.ambiguity_probability and edge is None else "ambiguous"

    fit = fits.get(pose) or fit_statistics(local, obs_xy, w_data, sig, pose, options, prior_info)
    if fit.inliers < need:
        return Pose(
            status="failed",
            crs=crs,
            iterations=iterations,
            inliers=fit.inliers,
            reason=(
                f"only {fit.inliers} of {len(obs)} observations match the map within "
                f"{options.inlier_distance_m} m (3 sigma at long range; need {need})"
            ),
        )
    log.debug(
        "localize %s: %s, %d/%d inliers, rms %.3f m, %d hypotheses",
        method, status, fit.inliers, len(obs), fit.rms_m or 0.0, len(hyps),
    )
    out = _make_pose(frame, local.origin, pose, status, crs)
    out.reason = edge
    out.covariance = fit.covariance
    out.iterations = int(iterations)
    out.inliers = fit.inliers
    out.rms_m = fit.rms_m
    out.probability = probability
    out.diagnostics = diagnostics
    out.log_score = log_scores[0]
    if options.record_trace:
        out.trace = [(t[0] + local.origin[0], t[1] + local.origin[1], t[2]) for t in trace]
    if status == "ambiguous":
        listed = []
        for k, ((hp, p), ls) in enumerate(zip(hyps[: options.max_hypotheses], log_scores)):
            if p < options.min_hypothesis_probability:
                break
            h = _make_pose(frame, local.origin, hp, "ok", crs)
            cov = fit.covariance if k == 0 else fit_statistics(local, obs_xy, w_data, sig, hp, options,
                                                                 prior_info).covariance
            out.hypotheses.append(
                Hypothesis(h.lat, h.lon, h.heading_deg, h.easting, h.northing, p, log_score=ls, covariance=cov)
            )
            listed.append(hp)
        out.mixture_covariance = mixture_covariance(
            pose, listed, [h.score for h in out.hypotheses], [h.covariance for h in out.hypotheses])
        if edge is not None:
            out.mixture_covariance = with_prior_uncertainty(
                fit.covariance if out.mixture_covariance is None else out.mixture_covariance,
                pose, prior_pose, pos_cov, sigma_yaw)
    return out


def with_prior_uncertainty(cov: np.ndarray, pose, prior_pose, pos_cov: np.ndarray, sigma_yaw: float) -> np.ndarray:
    """``cov`` plus the prior's second moment about ``pose``: the observations are not trusted past the prior.

    At a map's edge (``Options.edge_share``) the truth may be a pose whose
    view the map does not hold, which the posterior scored down and need not
    list: the answer is known no better than the prior knows it. Adds
    ``P + o o'`` to the position block (``P`` the prior's position
    covariance, m², ``o`` the prior's position less ``pose``'s) and
    ``sigma_yaw² + dyaw²`` to the yaw's (radians; ``dyaw`` wrapped).
    """
    o = np.asarray(prior_pose[:2], float) - np.asarray(pose[:2], float)
    dyaw = math.remainder(float(prior_pose[2]) - float(pose[2]), 2 * math.pi)
    out = np.array(cov, float)
    out[:2, :2] += np.asarray(pos_cov, float) + np.outer(o, o)
    out[2, 2] += sigma_yaw**2 + dyaw**2
    return out


def _observation_weights(obs: np.ndarray, options: Options) -> np.ndarray:
    """The default method's weight of each observation: its ``gamma``'s, shared among those
    that crowd together (``Options.crowd_radius_m``)."""
    w = data_weights(obs[:, 2])
    return w if options.crowd_radius_m is None else crowd_weights(obs[:, :2], w, options.crowd_radius_m)


def _edge_reach(pose, pos_cov: np.ndarray, options: Options) -> float | None:
    """How far along ``pose``'s heading (metres) a rival may lie for ``Options.edge_share``; None
    where the check does not apply.

    ``pos_cov`` is the prior's position covariance (map axes, m²): its sigma along the heading
    sets the reach (a receiver sure along the road reaches no rival a dash period away).
    """
    if options.edge_share is None:
        return None
    u = np.array([math.cos(pose[2]), math.sin(pose[2])])
    sigma = math.sqrt(max(float(u @ pos_cov @ u), 0.0))
    return None if 3.0 * sigma < options.edge_rival_m else min(3.0 * sigma, options.edge_reach_m)


def _beyond_edge(map_index: MapIndex, origin, obs_xy: np.ndarray, w: np.ndarray, pose,
                 pos_cov: np.ndarray, options: Options, centre=(0.0, 0.0)) -> str | None:  # fmt: skip
    """Why an answer cannot be trusted: the camera sees beyond the map's edge from it or from a
    pose within the prior's reach along its heading (``Options.edge_share``); None if not.

    ``pose`` and the prior's position ``centre`` are in coordinates about ``origin`` (map CRS,
    metres). The reach is measured from the prior's position, not from the answer: a rival
    the prior admits may lie farther from an answer at the side of the prior's region than
    the reach itself (a drive's track that settled three dash periods behind the truth)."""
    reach = _edge_reach(pose, pos_cov, options)
    if reach is None or not w.sum() > 0:
        return None
    extent = map_index.extent  # drawn here on first use, where a check needs it
    if extent is None:
        return None
    ox, oy = float(origin[0]) + pose[0], float(origin[1]) + pose[1]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = c * (float(centre[0]) - pose[0]) + s * (float(centre[1]) - pose[1])  # the prior, along the heading
    # The pose, then the far ends of the prior's reach ahead and behind, and the prior's own
    # position between them: no stretch of the reach is out of every camera's view.
    shifts = np.array([0.0, d + reach, d - reach, d])
    fwd = obs_xy[None, :, 0] + shifts[:, None]  # (4, N)
    x = ox + c * fwd - s * obs_xy[None, :, 1]
    y = oy + s * fwd + c * obs_xy[None, :, 1]
    shares = extent.beyond(x, y) @ w / w.sum()  # one query of the extent for all four
    for shift, share in zip(shifts.tolist(), shares.tolist()):
        if share > options.edge_share:
            where = ("from this pose" if abs(shift) < 0.5 else
                     f"from {abs(shift):.0f} m {'ahead of' if shift > 0 else 'behind'} it, within the prior's reach")
            return (f"{share:.0%} of what the camera sees lies beyond the map's edge {where}: "
                    "there a pose a dash period away may explain as much")
    return None


def edge_reason(map_index: MapIndex, obs: np.ndarray, pose, pos_cov: np.ndarray, options: Options,
                centre=None) -> str | None:  # fmt: skip
    """:func:`localize`'s check at the map's edge (``Options.edge_share``) for a pose found otherwise.

    Parameters
    ----------
    map_index : MapIndex
        The map.
    obs : (N, 3) ndarray
        Checked observations ``(x forward m, y left m, weight)``, as
        :func:`parse_observations` returns them.
    pose : tuple of float
        ``(easting, northing, grid yaw)`` in the map's CRS (metres, radians).
    pos_cov : (2, 2) ndarray
        The covariance of the position that rivals were searched in (map
        axes, m²): its sigma along ``pose``'s heading sets the reach.
    options : Options
        ``edge_share``, ``edge_rival_m``, ``edge_reach_m`` and the weights'
        ``crowd_radius_m``.
    centre : tuple of float, optional
        ``(easting, northing)`` that rivals were searched around, such as a
        GPS fix (map CRS, metres): the reach is measured from it. None:
        from ``pose``.

    Returns
    -------
    str or None
        Why an answer at ``pose`` cannot be trusted to be sure, or to list its
        rivals: the camera sees beyond the map's edge from it or from a pose
        within reach; None if not.
    """
    pos_cov = np.asarray(pos_cov, float)
    if len(obs) == 0 or _edge_reach(pose, pos_cov, options) is None:
        return None
    return _beyond_edge(map_index, (0.0, 0.0), obs[:, :2], _observation_weights(obs, options), pose, pos_cov,
                        options, pose[:2] if centre is None else centre)


def warm_up() -> float:
    """Compile the localizer's kernels, or load them from numba's cache; seconds taken.

    The nearest-marking lookup, the refinement's iterations, the hypothesis
    scores and the fits' sums are compiled with numba on first use (about
    13 s on a 2-core machine, then cached on disk next to the package or in
    ``NUMBA_CACHE_DIR``). A server calls this once at start so that no
    request waits for it; it localizes once on a small synthetic map, which
    runs every kernel.
    """
    import time

    t0 = time.perf_counter()
    rows = np.arange(-2, 3) * 3.5
    x = np.concatenate([np.arange(0.0, 60.0, 9.0) for _ in rows]) + 500_000.0
    y = np.repeat(rows, 7) + 5_400_000.0
    index = MapIndex.from_arrays(x, y, crs="EPSG:25832", bearing_deg=np.full(x.size, 90.0),
                                 length_m=np.full(x.size, 3.0))
    frame = index.frame
    lon, lat = frame.to_lonlat(500_010.0, 5_400_000.0)
    obs = np.column_stack([x - 500_010.0, y - 5_400_000.0, np.ones(x.size)])
    obs = obs[(obs[:, 0] > 4) & (obs[:, 0] < 25)]
    localize(index, obs, Prior(lat, lon, float(frame.grid_yaw_to_heading(0.0, lon, lat))))
    return time.perf_counter() - t0


@dataclass(frozen=True)
class _Scene:
    """What every candidate of one request is refined and scored against."""

    local: LocalMap
    obs_xy: np.ndarray
    w_data: np.ndarray
    sig: np.ndarray
    options: Options
    view: tuple[float, float, float]
    prior_pose: tuple[float, float, float]
    pos_info: np.ndarray  # 2x2 inverse covariance of the prior position, 1/m²
    sigma_yaw: float
    prior_info: np.ndarray


@dataclass
class _Ranked:
    kept: list  # (score, RefineResult, Candidate, schedule Options), best first
    scores: np.ndarray
    prob: np.ndarray
    score_options: Options
    best_pose: tuple[float, float, float]
    best_fit: Any
    need: int  # matched observations the answer needs: min_inliers, or the fallback's


def _with_negative_evidence(local: LocalMap, obs_xy, cands: list[Candidate], options: Options,
                            view) -> list[Candidate]:
    """Coarse candidates charged the markings they put in view that nobody saw, best first.

    The same charge as the hypotheses' scores (:func:`miss_costs`, divided by
    the temperature), so a coarse optimum that matches clutter while
    predicting unseen dashes yields its place to one that explains the view.
    """
    if not cands:
        return cands
    cost = miss_costs(local, obs_xy, [(c.x, c.y, c.yaw) for c in cands], options, view) / options.temperature
    charged = [replace(c, score=c.score - float(m)) for c, m in zip(cands, cost)]
    return sorted(charged, key=lambda c: -c.score)


def _heading_restarts(ranked: "_Ranked", searched: list[Candidate], n: int) -> list[Candidate]:
    """The best ``n`` coarse optima away from the best hypothesis, turned to its heading.

    Only those whose heading differs from it by more than 1.5°. Next to the
    best pose the neighbour starts already search; these look for a rival (or
    the truth) that the coarse grid's heading step hid elsewhere.
    """
    bx, by, yaw = ranked.kept[0][1].pose
    out = []
    for c in sorted(searched, key=lambda c: -c.score)[:n]:
        turned = abs(wrap_angle(c.yaw - yaw)) > _TURN_RAD
        if turned and math.hypot(c.x - bx, c.y - by) > _HEADING_RESTART_MIN_M:
            out.append(Candidate(c.x, c.y, yaw, -math.inf))
    return out


def _neighbour_starts(pose, options: Options) -> list[Candidate]:
    """Starts around ``pose``: along and across its heading, and turned, by ``options.neighbour_starts``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = []
    for along, across, turn_deg in options.neighbour_starts:
        out.append(Candidate(pose[0] + along * c - across * s, pose[1] + along * s + across * c,
                             pose[2] + math.radians(turn_deg), -math.inf))
    return out


# Options validate every field when built; these two are derived several
# times per request, from a handful of distinct inputs.
@functools.lru_cache(maxsize=64)
def _fine_options(o: Options) -> Options:
    """``o`` with its last two annealing scales only (a refinement next to an optimum)."""
    return replace(o, anneal_m=o.anneal_m[-2:])


@functools.lru_cache(maxsize=256)
def _score_options(o: Options, n_clutter: int) -> Options:
    """``o`` with the outlier density raised in proportion to ``n_clutter`` unexplained observations."""
    return replace(o, outlier_density=o.outlier_density * max(1.0, n_clutter / o.clutter_reference))


# A refinement that turned its start by more than this has travelled (and may
# have been dragged off; _refine_candidates). The restart at the refined
# heading uses the same bound under its own name, so it can be switched off.
_TURN_RAD = math.radians(1.5)
# Heading restarts look for optima beyond the neighbour starts' reach (1.5 m),
# and only under a prior at least that wide (see Options.heading_restarts).
_HEADING_RESTART_MIN_M = 3.0
_RESTART_TURN_RAD = _TURN_RAD


def _refine_candidates(sc: _Scene, cands: list[Candidate], fine_only: bool = False) -> list:
    """Refine coarse candidates; ``(score, RefineResult, candidate, schedule)`` per candidate.

    ``fine_only``: starts next to an optimum (:func:`_neighbour_starts`) run
    the last two annealing scales only, at half the cost.
    """
    if not cands:
        return []
    o = sc.options
    inits = [(c.x, c.y, c.yaw) for c in cands]
    fine_options = _fine_options(o)
    if fine_only:
        runs = robust_refine(sc.local, sc.obs_xy, sc.w_data, sc.sig, inits, fine_options)
        data = data_scores(sc.local, sc.obs_xy, sc.w_data, sc.sig, [r.pose for r in runs], o, sc.view)
        return [(float(d) / o.temperature + log_prior(r.pose, sc.prior_pose, sc.pos_info, sc.sigma_yaw),
                 r, c, fine_options) for d, r, c in zip(data, runs, cands)]
    # The coarse-to-fine schedule can be dragged off a right candidate by heavy
    # clutter; a fine-only refinement from the same start cannot go far. Keep
    # whichever explains the observations better. Both run in one batch (the
    # fine-only ones join at the last two scales).
    n_c = len(inits)
    both_runs = robust_refine(
        sc.local, sc.obs_xy, sc.w_data, sc.sig, inits + inits, o,
        start_scale=[0] * n_c + [max(0, len(o.anneal_m) - 2)] * n_c,
    )
    coarse = both_runs[:n_c]
    # Only a refinement that travelled can have been dragged off: the others
    # would end where the fine-only one does.
    moved = [k for k, (c, r) in enumerate(zip(cands, coarse))
             if math.hypot(r.pose[0] - c.x, r.pose[1] - c.y) > 0.5
             or abs(wrap_angle(r.pose[2] - c.yaw)) > _TURN_RAD]
    # A refinement dragged off by clutter while it turned has often found the
    # heading and lost the position: the coarse start had it the other way
    # round. Those also restart fine-only from the start's position at the
    # refined heading. Every pose is scored once, in one batch.
    turned = [k for k in moved if abs(wrap_angle(coarse[k].pose[2] - cands[k].yaw)) > _RESTART_TURN_RAD]
    restarts = robust_refine(sc.local, sc.obs_xy, sc.w_data, sc.sig,
                             [(cands[k].x, cands[k].y, coarse[k].pose[2]) for k in turned],
                             fine_options) if turned else []
    alternatives = [(k, both_runs[n_c + k]) for k in moved] + list(zip(turned, restarts))
    scores = data_scores(sc.local, sc.obs_xy, sc.w_data, sc.sig,
                         [r.pose for r in coarse] + [r.pose for _, r in alternatives], o, sc.view)
    fine, fine_score = {}, {}
    for (k, r), s in zip(alternatives, scores[n_c:]):
        if s > fine_score.get(k, -math.inf):
            fine[k], fine_score[k] = r, s
    refined = []
    for k, cand in enumerate(cands):
        a, sa = coarse[k], scores[k]
        b, sb = fine.get(k), fine_score.get(k, -math.inf)
        r, s, sched = (a, sa, o) if sa >= sb else (b, sb, fine_options)
        score = s / o.temperature + log_prior(r.pose, sc.prior_pose, sc.pos_info, sc.sigma_yaw)
        refined.append((score, r, cand, sched))
    return refined


def _rank_hypotheses(sc: _Scene, refined: list) -> _Ranked:
    """Distinct hypotheses among refined candidates, with their posterior probabilities."""
    o = sc.options
    refined = sorted(refined, key=lambda t: -t[0])
    # A pose that matches fewer observations than a fix needs is no hypothesis,
    # however well it scores (a pose looking at bare road predicts nothing it
    # could miss); it only decides the answer when nothing better exists. Two
    # matches fix a pose too, but while poses matching three exist, letting
    # two-match poses compete made more answers ambiguous than it made right.
    n_inl = count_inliers(sc.local, sc.obs_xy, sc.sig, [r[1].pose for r in refined], o)
    need = o.min_inliers if (n_inl >= o.min_inliers).any() else min(o.min_inliers, o.fallback_min_inliers)
    if (n_inl >= need).any():
        refined = [r for r, n in zip(refined, n_inl) if n >= need]
    best_fit = fit_statistics(sc.local, sc.obs_xy, sc.w_data, sc.sig, refined[0][1].pose, o, sc.prior_info)
    # Refinements that end inside the best one's uncertainty are the same optimum
    # (e.g. sliding along a solid line), not an alternative.
    info = _information(best_fit.covariance)
    kept = [refined[0]]
    for item in refined[1:]:
        if not any(_same_optimum(item[1].pose, k[1].pose, info) for k in kept):
            kept.append(item)
    # The clutter rate: observations that the best pose leaves unexplained. The
    # more clutter, the likelier a chance match, the less each match tells.
    n_clutter = len(sc.obs_xy) - best_fit.inliers
    score_options = _score_options(o, n_clutter)
    if score_options.outlier_density != o.outlier_density:
        data = data_scores(sc.local, sc.obs_xy, sc.w_data, sc.sig, [k[1].pose for k in kept],
                           score_options, sc.view)
        kept = [(float(d) / o.temperature + log_prior(k[1].pose, sc.prior_pose, sc.pos_info, sc.sigma_yaw),)
                + tuple(k[1:]) for d, k in zip(data, kept)]
        kept.sort(key=lambda t: -t[0])
    scores = np.array([k[0] for k in kept])
    # "None of these": every observation clutter, the vehicle somewhere the
    # search found nothing. A best hypothesis that explains little more than
    # that cannot be confident, however poor its rivals.
    top = max(float(scores.max()), o.null_score)
    prob = np.exp(scores - top)
    prob /= prob.sum() + math.exp(o.null_score - top)
    return _Ranked(kept, scores, prob, score_options, refined[0][1].pose, best_fit, need)


def _information(cov) -> list[list[float]] | None:
    """The inverse of a 3x3 covariance as nested floats (None if there is none or it is singular)."""
    if cov is None:
        return None
    try:
        return np.linalg.inv(cov).tolist()
    except np.linalg.LinAlgError:
        return None


def _same_optimum(a, b, info) -> bool:
    """Whether poses ``a`` and ``b`` are one optimum: within 0.75 m and 2°, or 3σ of ``info``'s covariance.

    Plain floats: called for every pair of refined candidates.
    """
    d = (a[0] - b[0], a[1] - b[1], (a[2] - b[2] + math.pi) % (2 * math.pi) - math.pi)
    if abs(d[2]) > math.radians(2.0):
        return False
    if math.hypot(d[0], d[1]) < 0.75:
        return True
    if info is None:
        return False
    return sum(d[i] * info[i][j] * d[j] for i in range(3) for j in range(3)) < 9.0


def _make_pose(frame, origin, pose, status, crs) -> Pose:
    e = float(pose[0] + origin[0])
    n = float(pose[1] + origin[1])
    yaw = float(wrap_angle(pose[2]))
    lon, lat = frame.to_lonlat(e, n)
    heading = float(frame.grid_yaw_to_heading(yaw, lon, lat))
    return Pose(
        status=status,
        crs=crs,
        lat=float(lat),
        lon=float(lon),
        heading_deg=heading,
        easting=e,
        northing=n,
        yaw_enu_rad=float(wrap_angle(math.pi / 2 - math.radians(heading))),
        yaw_grid_rad=yaw,
        transformation=homogeneous((e, n, yaw)),
    )

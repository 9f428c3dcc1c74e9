"""Localization over a short sequence of frames: a multi-hypothesis filter on :func:`localize`.

One camera frame on a straight road with 9 m dashes can be explained equally
well by poses one dash period apart; :func:`localize` then answers
``ambiguous``. As the vehicle drives on, the rivals predict different things
(the end of a dashed line, a stop line, a change of line type) and all but one
stop explaining what the camera sees. :func:`localize_sequence` follows every
hypothesis through the frames with the vehicle's odometry:

1. the first frame is localized against the GPS prior; each of its hypotheses
   (one when ``ok``) starts a track, weighted by its unnormalised log posterior
   (:attr:`Pose.log_score`);
2. at each later frame every track is moved by the odometry and the frame is
   localized with that prediction as a tight prior (its uncertainty grown by
   the odometry's noise). Each hypothesis of the answer continues the track:
   its weight gains the frame's evidence (the answer's log score without the
   prior term) scaled by the share of new ground the frame sees, and the prior
   term itself (agreement with the prediction). The same markings stay in
   view for many frames, so counting every frame in full would make a filter
   sure of the map's own ambiguity; scaled, each marking counts a few times
   (``TrackOptions.evidence_scale``) over its passage. The track also goes on
   at its prediction as "this frame is all clutter", at a small cost;
3. while no track is confident, the frame is also searched around the GPS fix
   (carried along by the odometry), so a pose the first frame missed can still
   start a track;
4. tracks ending within ``merge_distance_m`` / ``merge_heading_deg`` of each
   other are merged, the weakest are dropped; "none of these" (the first
   frame's ``Options.null_score``: every observation clutter) takes its share
   of the posterior.

Each frame's estimate is the best track's pose, ``ok`` when that track holds
``Options.ambiguity_probability`` of the posterior, else ``ambiguous`` with the
tracks as hypotheses. This is the filtering the paper names as future work,
kept stateless: the caller sends the frames of a window (e.g. the last second
or two) and gets the pose of each.

Odometry is the motion from the previous frame to this one in the previous
vehicle frame: ``dx`` forward, ``dy`` left (metres), ``dyaw`` counter-clockwise
(radians) — what wheel odometry or an IMU integrates between two frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .core import DEFAULT_OPTIONS, _make_pose, localize, parse_observations
from .errors import LocalizationInputError
from .frames import wrap_angle
from .index import MapIndex
from .types import Hypothesis, Options, Pose, Prior

#: Most frames one call accepts (a window of a few seconds at 10 Hz).
MAX_FRAMES = 50


@dataclass(frozen=True)
class Frame:
    """One camera frame of a sequence.

    Attributes
    ----------
    observations : (N, 3) array_like or list of {"x", "y", "weight"}
        As for :func:`localize`: vehicle-frame centroids (x forward, y left, m) and weights γ.
    motion : (dx, dy, dyaw)
        Odometry from the previous frame to this one, in the previous vehicle
        frame: metres forward, metres left, radians counter-clockwise. Ignored
        for the first frame.
    """

    observations: object
    motion: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class TrackOptions:
    """Odometry noise and hypothesis bookkeeping of :func:`localize_sequence`.

    Attributes
    ----------
    odometry_sigma_m : float
        Position noise the odometry adds per frame, metres (per axis).
    odometry_sigma_ratio : float
        Further position noise per metre driven (per axis): 0.03 is 3 %.
    odometry_sigma_yaw_deg : float
        Heading noise the odometry adds per frame, degrees.
    min_position_sigma_m, min_heading_sigma_deg : float
        Floor of a track's uncertainty before the odometry noise is added: the
        refinement's own covariance is optimistic at this scale, and a tight
        prior must still let the next frame correct the pose.
    max_tracks : int
        Tracks kept after each frame (most probable first).
    min_track_probability : float
        Tracks less probable than this are dropped.
    merge_distance_m, merge_heading_deg : float
        Tracks whose poses are this close are one.
    evidence_scale : float
        How many times one marking's evidence counts while it passes through the
        view: a frame's evidence is weighted by ``evidence_scale`` times the
        share of new ground it sees (metres driven over the view's depth, plus
        the turn over its width), at most 1. Detections and misses are
        independent from frame to frame, the map's ambiguity is not. The default
        and ``unexplained_penalty`` were chosen on ``benchmarks/localize_track.py
        --seed 7`` (no confidently wrong answer there), not on the reported seed.
    unexplained_penalty : float
        Log weight a track loses per view's worth of frames that it explains as
        all clutter.
    """

    odometry_sigma_m: float = 0.05
    odometry_sigma_ratio: float = 0.03
    odometry_sigma_yaw_deg: float = 0.3
    min_position_sigma_m: float = 0.3
    min_heading_sigma_deg: float = 1.0
    max_tracks: int = 8
    min_track_probability: float = 1e-4
    merge_distance_m: float = 0.75
    merge_heading_deg: float = 2.0
    evidence_scale: float = 3.0
    unexplained_penalty: float = 8.0


@dataclass
class SequenceResult:
    """Result of :func:`localize_sequence`.

    Attributes
    ----------
    poses : list of Pose
        The estimate at each frame, from the frames up to it (a causal filter);
        ``poses[-1]`` is the current pose.
    tracks : int
        Tracks alive after the last frame.
    """

    poses: list[Pose] = field(default_factory=list)
    tracks: int = 0

    @property
    def pose(self) -> Pose:
        """The estimate at the last frame."""
        return self.poses[-1]


@dataclass
class _Track:
    pose: tuple[float, float, float]  # easting, northing, grid yaw
    sigma_m: float
    sigma_yaw: float
    log_w: float
    matched: bool  # has any frame matched along this track
    answer: Pose | None = None  # this frame's match (None: the track is a prediction)


def localize_sequence(
    map_index: MapIndex,
    frames: Sequence[Frame],
    prior: Prior,
    options: Options | None = None,
    track_options: TrackOptions | None = None,
) -> SequenceResult:
    """Localize each frame of a sequence, following every hypothesis with odometry.

    Parameters
    ----------
    map_index : MapIndex
        The map, shared between calls.
    frames : sequence of Frame
        Consecutive camera frames, oldest first, each with the odometry since the one before.
    prior : Prior
        GPS fix at the first frame, with its uncertainty.
    options : Options, optional
        Options of the default method, used for every frame.
    track_options : TrackOptions, optional
        Odometry noise and hypothesis bookkeeping.

    Returns
    -------
    SequenceResult
        The pose at every frame; ``result.pose`` is the last.

    Raises
    ------
    LocalizationInputError
        For malformed input: no frames, too many, bad observations or odometry.
    """
    options = options or DEFAULT_OPTIONS
    topt = track_options or TrackOptions()
    if not isinstance(frames, Sequence) or isinstance(frames, (str, bytes)) or not frames:
        raise LocalizationInputError("frames: expected a non-empty list of frames")
    if len(frames) > MAX_FRAMES:
        raise LocalizationInputError(f"frames: {len(frames)} given, at most {MAX_FRAMES} are accepted")
    parsed = []
    for k, f in enumerate(frames):
        if not isinstance(f, Frame):
            raise LocalizationInputError(f"frames[{k}]: expected a localizer.track.Frame")
        try:
            motion = tuple(float(v) for v in f.motion)
        except (TypeError, ValueError) as exc:
            raise LocalizationInputError(f"frames[{k}].motion: expected three numbers") from exc
        if len(motion) != 3 or not all(math.isfinite(v) for v in motion):
            raise LocalizationInputError(f"frames[{k}].motion: expected three finite numbers (dx, dy, dyaw)")
        try:
            obs = parse_observations(f.observations, options.max_observations,
                                     options.max_observation_range_m)  # fmt: skip
        except LocalizationInputError as exc:
            raise LocalizationInputError(f"frames[{k}].{exc}") from exc
        parsed.append((obs, motion))

    frame_geo = map_index.frame
    crs = map_index.crs
    null = options.null_score
    view = _view_depth(options)
    gps = _Track(_grid_pose(frame_geo, prior), prior.position_sigma_m, math.radians(prior.heading_sigma_deg),
                 null, False)  # fmt: skip
    first = localize(map_index, parsed[0][0], prior, options=options)
    tracks = _prune(_children(first, gps, 0.0, 1.0, frame_geo), null, topt)
    result = SequenceResult(poses=[first])

    for obs, motion in parsed[1:]:
        # The share of new ground this frame sees: its evidence counts in that
        # proportion (times evidence_scale), see the module docstring.
        weight = min(1.0, topt.evidence_scale
                     * (math.hypot(motion[0], motion[1]) / view[0] + abs(motion[2]) / view[1]))
        children: list[_Track] = []
        for t in tracks:
            parent = _predict(t, motion, topt)
            r = localize(map_index, obs, _prior_of(parent, frame_geo), options=options)
            children.extend(_children(r, parent, parent.log_w, weight, frame_geo, -topt.unexplained_penalty))
        gps = _predict(gps, motion, topt, floor=False)
        prob = _posterior(tracks, null)
        if not tracks or prob[0] < options.ambiguity_probability:
            # No confident track: search around the GPS fix again, as the first
            # frame did. What it finds starts from "none of these" with this
            # frame's evidence in full (those poses explained nothing before).
            r = localize(map_index, obs, _prior_of(gps, frame_geo), options=options)
            children.extend(_children(r, gps, null, 1.0, frame_geo))
        tracks = _prune(children, null, topt)
        result.poses.append(_estimate(tracks, null, options, frame_geo, crs))
    result.tracks = len(tracks)
    return result


def _view_depth(options: Options) -> tuple[float, float]:
    """Metres of road and radians of heading after which a frame sees all-new ground."""
    lo = options.view_min_range_m if options.view_min_range_m is not None else 4.0
    hi = options.view_max_range_m if options.view_max_range_m is not None else 25.0
    fov = options.view_half_fov_deg if options.view_half_fov_deg is not None else 30.0
    return max(hi - lo, 1.0), 2.0 * math.radians(max(fov, 1.0))


def _grid_pose(frame_geo, prior: Prior) -> tuple[float, float, float]:
    x, y = frame_geo.to_xy(prior.lon, prior.lat)
    return float(x), float(y), float(frame_geo.heading_to_grid_yaw(prior.heading_deg, prior.lon, prior.lat))


def _prior_of(t: _Track, frame_geo) -> Prior:
    lon, lat = frame_geo.to_lonlat(t.pose[0], t.pose[1])
    return Prior(
        lat=float(lat), lon=float(lon),
        heading_deg=float(frame_geo.grid_yaw_to_heading(t.pose[2], lon, lat)) % 360.0,
        position_sigma_m=float(np.clip(t.sigma_m, 0.01, 1000.0)),
        heading_sigma_deg=float(np.clip(math.degrees(t.sigma_yaw), 0.01, 180.0)),
    )  # fmt: skip


def _predict(t: _Track, motion, topt: TrackOptions, floor: bool = True) -> _Track:
    """The track moved by the odometry, its uncertainty grown by the odometry's noise."""
    dx, dy, dyaw = motion
    c, s = math.cos(t.pose[2]), math.sin(t.pose[2])
    pose = (t.pose[0] + c * dx - s * dy, t.pose[1] + s * dx + c * dy, float(wrap_angle(t.pose[2] + dyaw)))
    odo = topt.odometry_sigma_m + topt.odometry_sigma_ratio * math.hypot(dx, dy)
    s_m = max(t.sigma_m, topt.min_position_sigma_m) if floor else t.sigma_m
    s_yaw = max(t.sigma_yaw, math.radians(topt.min_heading_sigma_deg)) if floor else t.sigma_yaw
    return replace(t, pose=pose, sigma_m=math.hypot(s_m, odo),
                   sigma_yaw=math.hypot(s_yaw, math.radians(topt.odometry_sigma_yaw_deg)), answer=None)  # fmt: skip


def _log_prior(pose, t: _Track) -> float:
    d = (pose[0] - t.pose[0], pose[1] - t.pose[1], wrap_angle(pose[2] - t.pose[2]))
    return -0.5 * ((d[0] ** 2 + d[1] ** 2) / t.sigma_m**2 + (d[2] / t.sigma_yaw) ** 2)


def _children(r: Pose, parent: _Track, base: float, weight: float, frame_geo,
              parent_miss: float = 0.0) -> list[_Track]:
    """The tracks that one frame's answer from ``parent``'s prior continues.

    Each hypothesis of the answer continues the track; its weight grows by the
    frame's evidence (its log score less the prior term) times ``weight``, plus
    the prior term (how well it agrees with the prediction). The track also goes
    on at its prediction, "this frame's observations are all clutter", its
    weight changed by ``parent_miss`` (≤ 0) times ``weight`` (a frame under heavy
    clutter, or one whose answer jumped away from the prediction, must not end a
    good track, but a track that stops explaining what the camera sees fades).
    """
    keep = [replace(parent, log_w=parent.log_w + weight * parent_miss)] if parent.matched else []
    if r.status == "failed" or r.log_score is None:
        return keep
    items = [((h.easting, h.northing, _grid_yaw(h, frame_geo)), h.log_score)
             for h in r.hypotheses if h.log_score is not None]  # fmt: skip
    if not items:  # ok, or ambiguous with every hypothesis below the listing threshold
        items = [((r.easting, r.northing, r.yaw_grid_rad), r.log_score)]
    cov = r.covariance
    s_m, s_yaw = parent.sigma_m, parent.sigma_yaw
    if cov is not None and np.all(np.isfinite(cov)):
        s_m, s_yaw = math.sqrt(max(cov[0, 0], cov[1, 1], 0.0)), math.sqrt(max(cov[2, 2], 0.0))
    out = []
    for pose, ls in items:
        pose = tuple(float(v) for v in pose)
        lp = _log_prior(pose, parent)
        out.append(_Track(pose, s_m, s_yaw, base + weight * (ls - lp) + lp, True, r))
    return out + keep


def _grid_yaw(h: Hypothesis, frame_geo) -> float:
    return float(frame_geo.heading_to_grid_yaw(h.heading_deg, h.lon, h.lat))


def _prune(tracks: list[_Track], null: float, topt: TrackOptions) -> list[_Track]:
    tracks = sorted(tracks, key=lambda t: -t.log_w)
    kept: list[_Track] = []
    for t in tracks:
        for k in kept:
            if (math.hypot(t.pose[0] - k.pose[0], t.pose[1] - k.pose[1]) <= topt.merge_distance_m
                    and abs(wrap_angle(t.pose[2] - k.pose[2])) <= math.radians(topt.merge_heading_deg)):
                k.log_w = float(np.logaddexp(k.log_w, t.log_w))
                k.matched = k.matched or t.matched
                break
        else:
            kept.append(replace(t))
    prob = _posterior(kept, null)
    return [t for t, p in zip(kept, prob) if p >= topt.min_track_probability][: topt.max_tracks]


def _posterior(tracks: list[_Track], null: float) -> np.ndarray:
    """Probabilities of the tracks; the rest is "none of these" (every observation clutter)."""
    w = np.array([t.log_w for t in tracks] + [null], float)
    w = np.exp(w - w.max())
    return w[:-1] / w.sum()


def _estimate(tracks, null, options: Options, frame_geo, crs) -> Pose:
    if not tracks:
        return Pose(status="failed", crs=crs, reason="no frame so far matched the map")
    best = tracks[0]
    prob = _posterior(tracks, null)
    status = "ok" if prob[0] >= options.ambiguity_probability else "ambiguous"
    out = _pose_at(best, status, frame_geo, crs)
    out.probability = float(prob[0])
    if status == "ambiguous":
        for t, p in zip(tracks[: options.max_hypotheses], prob):
            if p < options.min_hypothesis_probability:
                break
            h = _pose_at(t, "ok", frame_geo, crs)
            out.hypotheses.append(
                Hypothesis(h.lat, h.lon, h.heading_deg, h.easting, h.northing, float(p), log_score=t.log_w)
            )
    return out


def _pose_at(t: _Track, status: str, frame_geo, crs) -> Pose:
    out = _make_pose(frame_geo, (0.0, 0.0), t.pose, status, crs)
    a = t.answer
    if a is not None and a.covariance is not None:
        out.covariance = np.array(a.covariance, float)
    else:
        out.covariance = np.diag([t.sigma_m**2, t.sigma_m**2, t.sigma_yaw**2])
    if a is not None:
        out.inliers, out.rms_m, out.iterations = a.inliers, a.rms_m, a.iterations
    else:
        out.reason = "no match in this frame: the pose is the odometry's prediction"
    out.log_score = t.log_w
    return out

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
   at its prediction as "this frame is all clutter", at a cost that grows
   with the markings the map puts in view there (none on unpainted road);
3. while no track is confident, the frame is also searched around the GPS fix
   (carried along by the odometry), so a pose the first frame missed can still
   start a track. The fix carries a full covariance: an error in its heading
   moves it across the direction driven, the same error at every frame, so
   its error ellipse grows across the road and hardly along it
   (:func:`carry_prior` does the same for a single frame's prior). A pose
   found there that no track follows is scored on the last few frames too,
   moved back along the odometry (``TrackOptions.retrodiction_frames``), and
   weighed as if it had been followed from the earliest of them: a truth the
   first frame's search missed is not outweighed by the rivals followed since;
4. tracks ending within ``merge_distance_m`` / ``merge_heading_deg`` of each
   other are merged, the weakest are dropped; "none of these" (the first
   frame's ``Options.null_score``: every observation clutter) takes its share
   of the posterior.

Each frame's estimate is the best track's pose, ``ok`` when that track holds
``Options.ambiguity_probability`` of the posterior, else ``ambiguous`` with the
tracks as hypotheses. At a map's edge the camera sees markings the map
lacks, and a rival a dash period away, whose view stays on the map, explains
more of them than the truth does, frame after frame, until the truth's track
is dropped. So until the drive has been sure of a track with no edge within
the GPS fix's reach (``Options.edge_share``, as for a single frame; the track
is then *established*, and keeps it through the drive and into the next
map; while one is followed the drive goes on as any), a frame that sees
beyond the edge from the best track or a pose within that reach, and the
frame after it, start the drive again: its answer is the single frame's,
and the tracks go on from it (those followed so far go on by the odometry,
their evidence taken off). This is the filtering the paper names as future
work.
It keeps no state between calls: the caller either sends the frames of a
window (e.g. the last second or two) and gets the pose of each, or streams a
drive a few frames at a time, passing back the :class:`TrackState` of the
previous call (``SequenceResult.state``); a drive continued that way gives
the same poses as one call over all its frames, at the cost of the new
frames only, however long the drive.

Odometry is the motion from the previous frame to this one in the previous
vehicle frame: ``dx`` forward, ``dy`` left (metres), ``dyaw`` counter-clockwise
(radians) — what wheel odometry or an IMU integrates between two frames.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .core import (
    DEFAULT_OPTIONS,
    _check_prior,
    _make_pose,
    edge_reason,
    localize,
    parse_observations,
    position_covariance,
)
from .errors import LocalizationInputError
from .frames import shared_frame, wrap_angle
from .geometry import LocalMap
from .index import MapIndex
from .robust import log_prior, missed_counts, mixture_covariance
from .types import ErrorEllipse, Hypothesis, Options, Pose, Prior

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
        --seed 7``, not on the reported seed. The scale is the one whose
        drive answers' probability has the lowest log-loss there (frames 2-10:
        0.0775 at 3, 0.0701 at 4.5, 0.0658 at 6, 0.0683 at 8, 0.0708 at 10),
        also the largest with no 10-frame drive ending confidently wrong
        (re-fitted when ``Options.temperature`` went from 1.35 to 1).
    unexplained_penalty : float
        Log weight a track loses per view's worth of frames that it explains as
        all clutter, times the probability that the camera would have reported
        one of the markings the map puts in view there: nothing, through a
        stretch without markings, where the track goes on by the odometry.
    max_lead : float
        Most log units the best track may lead "none of these" by; beyond it
        every track's weight is lowered by the excess (their probabilities
        among themselves unchanged). Evidence adds up frame after frame, and a
        drive streamed for minutes would otherwise build a lead no later frame
        could undo: a track that stops matching the road (odometry gone wrong,
        a map change) would stay sure for as many frames as it had matched.
        With the lead capped it loses its certainty within about
        ``max_lead / unexplained_penalty`` views of unmatched frames, and the
        frames are searched around the GPS fix again. 30 (a posterior of
        1 - 1e-13) is far beyond any threshold of ``ok``.
    retrodiction_frames : int
        Previous frames on which a pose first found around the GPS fix is
        scored, as if a track had followed it from the earliest of them (the
        pose moved back by their odometry and refined in each). Without it
        such a pose starts from "none of these" with one frame's evidence,
        while the tracks followed since the first frame hold the evidence of
        every frame, and a truth the first frame's search missed could not
        catch up with a rival that had been found. A retrodicted weight only
        ever raises the new track's. The frames' observations travel in the
        :class:`TrackState`. 0: no retrodiction.
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
    evidence_scale: float = 6.0
    unexplained_penalty: float = 8.0
    max_lead: float = 30.0
    retrodiction_frames: int = 3

    def __post_init__(self) -> None:
        n = self.retrodiction_frames
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n <= MAX_FRAMES:
            raise LocalizationInputError(
                f"track_options.retrodiction_frames: must be an integer in [0, {MAX_FRAMES}], got {n!r}")


#: Most tracks a :class:`TrackState` may hold (``TrackOptions.max_tracks`` keeps fewer).
MAX_STATE_TRACKS = 64

#: Largest standard deviations a track carries (metres, radians): a prior's
#: largest, and a heading that could be anything.
MAX_SIGMA_M, MAX_SIGMA_YAW = 1000.0, math.pi
#: Smallest that a state records: a track's sigma is floored before use, the
#: GPS fix's is at least a prior's smallest (0.01 m / 0.01°).
_MIN_STATE_SIGMA = 1e-9
_SIGMA_LIMITS = {"sigma_m": MAX_SIGMA_M, "sigma_yaw_rad": MAX_SIGMA_YAW}
_TRACK_KEYS = ("easting", "northing", "yaw_grid_rad", "sigma_m", "sigma_yaw_rad", "log_weight", "matched",
               "established")
_GPS_KEYS = ("easting", "northing", "yaw_grid_rad", "sigma_m", "sigma_yaw_rad")


@dataclass(frozen=True)
class TrackState:
    """Where the filter stands after a drive's last frame: continue the drive from it.

    Pass it to :func:`localize_sequence` with the next frames (the first of
    them carrying the odometry since the last frame seen) and the drive goes on
    as if all its frames had been sent in one call. :meth:`to_dict` and
    :meth:`from_dict` carry it through JSON unchanged (floats round-trip
    exactly), so a stateless server can hand it to its client and back.

    Attributes
    ----------
    crs : str
        The map CRS the poses are in.
    frames : int
        Frames the drive has had so far.
    tracks : tuple of tuple
        ``(easting, northing, grid yaw, sigma_m, sigma_yaw_rad, log_weight,
        matched, established)`` per hypothesis followed, most probable first;
        ``established``: the drive was sure of it once with no map edge within
        the GPS fix's reach (a state from before it was kept reads false).
    gps : tuple
        ``(easting, northing, grid yaw, sigma_m, sigma_yaw_rad)``: the first
        GPS fix carried along by the odometry (searched around while no track
        is sure); ``sigma_m`` is its error ellipse's major axis.
    gps_covariance : tuple of tuple, optional
        The carried fix's 3x3 covariance of (easting, northing, grid yaw), m
        and rad: its uncertainty grows across the road as the odometry carries
        a heading error along. A state without it (from before it was kept)
        starts one from the sigmas.
    history : tuple of tuple
        The last frames, oldest first, for ``TrackOptions.retrodiction_frames``:
        ``(observations, motion, weight, first)`` each, with the observations
        as ``(x, y, weight)`` rows, the odometry into that frame, the share of
        its evidence a track gained there, and whether it was the drive's
        first frame. Empty in a state from before it was kept.
    shift : float
        Log weight taken off every track so far by ``TrackOptions.max_lead``
        (retrodicted weights are put on the same footing).
    """

    crs: str
    frames: int
    tracks: tuple[tuple[float, float, float, float, float, float, bool, bool], ...]
    gps: tuple[float, float, float, float, float]
    gps_covariance: tuple[tuple[float, float, float], ...] | None = None
    history: tuple = ()
    shift: float = 0.0

    def to_dict(self) -> dict:
        """JSON-safe form (the API's ``state``)."""
        gps = dict(zip(_GPS_KEYS, (float(v) for v in self.gps)))
        if self.gps_covariance is not None:
            gps["covariance"] = [[float(v) for v in row] for row in self.gps_covariance]
        return {
            "crs": self.crs,
            "frames": self.frames,
            "tracks": [dict(zip(_TRACK_KEYS, (*(float(v) for v in t[:6]), bool(t[6]), bool(t[7]))))
                       for t in self.tracks],
            "gps": gps,
            "history": [{"observations": [[float(v) for v in row] for row in obs],
                         "motion": [float(v) for v in motion], "weight": float(weight), "first": bool(first)}
                        for obs, motion, weight, first in self.history],
            "shift": float(self.shift),
        }

    def to_crs(self, crs: str) -> TrackState:
        """The same state with its poses in another projected CRS: a drive handed to another map.

        Every pose keeps its place on the ground and its true heading; the
        grid yaw takes the other CRS's meridian convergence, and the sigmas and
        the fix's covariance the local scale and turn between the two grids
        (their Jacobian, taken 1 m around each pose). The frames kept for
        retrodiction are in the vehicle frame and stay as they are.

        Parameters
        ----------
        crs : str
            The other map's CRS (projected, metres).

        Raises
        ------
        LocalizationInputError
            If either CRS is not a projected metric one, or a pose falls
            outside the other CRS's domain.
        """
        if crs == self.crs:
            return self
        src, dst = shared_frame(self.crs), shared_frame(crs)
        poses = np.array([t[:3] for t in self.tracks] + [self.gps[:3]], float)
        e, n = poses[:, 0], poses[:, 1]
        # each pose, and a metre east and north of it, through WGS84 into the other grid
        x = np.concatenate([e, e + 1.0, e])
        y = np.concatenate([n, n, n + 1.0])
        tx, ty = dst.to_xy(*src.to_lonlat(x, y))
        tx, ty = np.asarray(tx, float).reshape(3, -1), np.asarray(ty, float).reshape(3, -1)
        if not (np.all(np.isfinite(tx)) and np.all(np.isfinite(ty))):
            raise LocalizationInputError(f"state: its poses lie outside the domain of {crs}")
        jac = np.empty((len(poses), 2, 2))
        jac[:, :, 0] = np.column_stack([tx[1] - tx[0], ty[1] - ty[0]])
        jac[:, :, 1] = np.column_stack([tx[2] - tx[0], ty[2] - ty[0]])
        heading = np.einsum("kij,kj->ki", jac, np.column_stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])]))
        yaw = np.arctan2(heading[:, 1], heading[:, 0])
        scale = np.sqrt(np.abs(np.linalg.det(jac)))
        tracks = tuple(
            (float(tx[0, k]), float(ty[0, k]), float(yaw[k]), float(t[3] * scale[k]), *t[4:])
            for k, t in enumerate(self.tracks)
        )
        g = len(self.tracks)
        gps = (float(tx[0, g]), float(ty[0, g]), float(yaw[g]), float(self.gps[3] * scale[g]), self.gps[4])
        cov = None
        if self.gps_covariance is not None:
            j = np.eye(3)
            j[:2, :2] = jac[g]
            c = j @ np.asarray(self.gps_covariance, float) @ j.T
            c = 0.5 * (c + c.T)
            cov = tuple(tuple(float(v) for v in row) for row in c)
        return replace(self, crs=str(crs), tracks=tracks, gps=gps, gps_covariance=cov)

    @classmethod
    def from_dict(cls, data) -> TrackState:
        """Read :meth:`to_dict`'s form back, checking every value.

        Raises
        ------
        LocalizationInputError
            Naming the first field that is missing or out of range.
        """
        if not isinstance(data, dict):
            raise LocalizationInputError("state: expected an object, as returned with the previous frames")
        crs, frames, tracks, gps = (data.get(k) for k in ("crs", "frames", "tracks", "gps"))
        if not isinstance(crs, str) or not crs:
            raise LocalizationInputError("state.crs: expected the map's CRS")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise LocalizationInputError("state.frames: expected a positive integer")
        if not isinstance(tracks, list) or len(tracks) > MAX_STATE_TRACKS:
            raise LocalizationInputError(f"state.tracks: expected a list of at most {MAX_STATE_TRACKS} tracks")
        out = []
        for k, t in enumerate(tracks):
            values = _state_numbers(t, _TRACK_KEYS[:6], f"state.tracks[{k}]")
            if not isinstance(t.get("matched"), bool):
                raise LocalizationInputError(f"state.tracks[{k}].matched: expected true or false")
            if not isinstance(t.get("established", False), bool):
                raise LocalizationInputError(f"state.tracks[{k}].established: expected true or false")
            out.append((*values, t["matched"], t.get("established", False)))
        gps_values = _state_numbers(gps, _GPS_KEYS, "state.gps")
        cov = gps.get("covariance")
        shift = data.get("shift", 0.0)
        if shift is None:
            shift = 0.0
        if isinstance(shift, bool) or not isinstance(shift, (int, float)) or not 0.0 <= shift < math.inf:
            raise LocalizationInputError("state.shift: expected a finite number, at least 0")
        return cls(crs, frames, tuple(out), gps_values, None if cov is None else _state_covariance(cov),
                   _state_history(data.get("history")), float(shift))


def _state_history(history) -> tuple:
    if history is None:
        return ()
    if not isinstance(history, list) or len(history) > MAX_FRAMES:
        raise LocalizationInputError(f"state.history: expected a list of at most {MAX_FRAMES} frames")
    out = []
    for k, h in enumerate(history):
        where = f"state.history[{k}]"
        if not isinstance(h, dict):
            raise LocalizationInputError(f"{where}: expected an object")
        try:
            obs = parse_observations(h.get("observations"), DEFAULT_OPTIONS.max_observations,
                                     DEFAULT_OPTIONS.max_observation_range_m)
        except LocalizationInputError as exc:
            raise LocalizationInputError(f"{where}.{exc}") from exc
        motion = _motion(h.get("motion"), f"{where}.motion")
        weight, first = h.get("weight"), h.get("first")
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0.0 <= weight <= 1.0:
            raise LocalizationInputError(f"{where}.weight: expected a number in [0, 1]")
        if not isinstance(first, bool):
            raise LocalizationInputError(f"{where}.first: expected true or false")
        out.append((_frozen(obs), motion, float(weight), first))
    return tuple(out)


def _motion(m, where: str) -> tuple[float, float, float]:
    """Odometry ``(dx, dy, dyaw)`` as three finite floats, or an error naming ``where``."""
    try:
        if isinstance(m, (str, bytes)) or any(isinstance(v, (bool, str, bytes)) for v in m):
            raise TypeError
        values = tuple(float(v) for v in m)
    except (TypeError, ValueError) as exc:
        raise LocalizationInputError(f"{where}: expected three numbers (dx, dy, dyaw)") from exc
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise LocalizationInputError(f"{where}: expected three finite numbers (dx, dy, dyaw)")
    return values


def _frozen(obs) -> tuple[tuple[float, ...], ...]:
    """Rows (observations, a covariance) as nested tuples of floats, as a :class:`TrackState` keeps them."""
    return tuple(tuple(float(v) for v in row) for row in obs)


def _last(frames: list, n: int) -> list:
    """The last ``n`` of ``frames`` (none for 0)."""
    return frames[max(0, len(frames) - n):] if n else []


def _state_covariance(cov) -> tuple[tuple[float, float, float], ...]:
    where = "state.gps.covariance"
    if (not isinstance(cov, list) or len(cov) != 3
            or not all(isinstance(row, list) and len(row) == 3 for row in cov)):
        raise LocalizationInputError(f"{where}: expected a 3x3 matrix (easting, northing, grid yaw)")
    for row in cov:
        for v in row:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise LocalizationInputError(f"{where}: expected finite numbers")
    a = np.array(cov, float)
    if not np.array_equal(a, a.T):
        raise LocalizationInputError(f"{where}: expected a symmetric matrix")
    limits = (MAX_SIGMA_M**2, MAX_SIGMA_M**2, MAX_SIGMA_YAW**2)
    if not all(0.0 < a[k, k] <= limits[k] * (1 + 1e-9) for k in range(3)):
        raise LocalizationInputError(f"{where}: a variance is not positive or beyond a prior's largest")
    if np.linalg.eigvalsh(a)[0] < -1e-9 * float(np.max(np.diag(a))):
        raise LocalizationInputError(f"{where}: expected a positive semi-definite matrix")
    return _frozen(a)


def _state_numbers(item, keys, where: str) -> tuple[float, ...]:
    if not isinstance(item, dict):
        raise LocalizationInputError(f"{where}: expected an object")
    values = []
    for key in keys:
        v = item.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise LocalizationInputError(f"{where}.{key}: expected a finite number")
        top = _SIGMA_LIMITS.get(key)
        if top is not None and not 0.0 < v <= top:
            raise LocalizationInputError(f"{where}.{key}: expected a standard deviation in (0, {top:g}]")
        values.append(float(v))
    return tuple(values)


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
    state : TrackState or None
        Where the filter stands: pass it with the next frames to continue the drive.
    """

    poses: list[Pose] = field(default_factory=list)
    tracks: int = 0
    state: TrackState | None = None

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
    # (east, north, grid yaw) covariance; only the GPS fix carries one (its
    # sigmas above then follow from it)
    cov: np.ndarray | None = None
    # was sure once with no map edge within the GPS fix's reach (module docstring)
    established: bool = False


def localize_sequence(
    map_index: MapIndex,
    frames: Sequence[Frame],
    prior: Prior | None = None,
    options: Options | None = None,
    track_options: TrackOptions | None = None,
    state: TrackState | None = None,
) -> SequenceResult:
    """Localize each frame of a sequence, following every hypothesis with odometry.

    Parameters
    ----------
    map_index : MapIndex
        The map, shared between calls.
    frames : sequence of Frame
        Consecutive camera frames, oldest first, each with the odometry since
        the one before (the first frame's: since the ``state``'s last frame,
        when continuing; else ignored).
    prior : Prior, optional
        GPS fix at the first frame, with its uncertainty. Required to start a
        drive; when continuing one it replaces the fix carried in ``state``
        (a newer fix is a better place to search while no track is sure).
    options : Options, optional
        Options of the default method, used for every frame.
    track_options : TrackOptions, optional
        Odometry noise and hypothesis bookkeeping.
    state : TrackState, optional
        ``SequenceResult.state`` of the drive's previous frames: continue the
        drive instead of starting one. The poses are those one call over all
        the frames would have given.

    Returns
    -------
    SequenceResult
        The pose at every frame; ``result.pose`` is the last; ``result.state``
        continues the drive.

    Raises
    ------
    LocalizationInputError
        For malformed input: no frames, too many, bad observations, odometry
        or state, a state of another CRS, or neither a prior nor a state.
    """
    steps = iter_sequence(map_index, frames, prior, options, track_options, state)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def iter_sequence(
    map_index: MapIndex,
    frames: Sequence[Frame],
    prior: Prior | None = None,
    options: Options | None = None,
    track_options: TrackOptions | None = None,
    state: TrackState | None = None,
) -> Generator[Pose, None, SequenceResult]:
    """:func:`localize_sequence` a frame at a time: a generator of each frame's pose.

    It checks the whole input when first advanced (raising
    :class:`LocalizationInputError` as :func:`localize_sequence` does, before
    any frame is localized), then yields the pose of each frame in turn, and
    returns the :class:`SequenceResult` (``StopIteration.value``). A server
    advances it in turns with other requests, so that a long drive holds
    the localizer for one frame at a time.
    """
    options = options or DEFAULT_OPTIONS
    topt = track_options or TrackOptions()
    if not isinstance(frames, Sequence) or isinstance(frames, (str, bytes)) or not frames:
        raise LocalizationInputError("frames: expected a non-empty list of frames")
    if len(frames) > MAX_FRAMES:
        raise LocalizationInputError(f"frames: {len(frames)} given, at most {MAX_FRAMES} are accepted")
    if prior is None and state is None:
        raise LocalizationInputError(
            "prior: a GPS fix is needed to start a drive (or a state to continue one)")
    if state is not None:
        if not isinstance(state, TrackState):
            raise LocalizationInputError("state: expected a localizer.TrackState")
        if state.crs != map_index.crs:
            raise LocalizationInputError(
                f"state: its poses are in {state.crs}, this map's CRS is {map_index.crs} "
                "(a state continues a drive on the map it came from)"
            )
    parsed = []
    for k, f in enumerate(frames):
        if not isinstance(f, Frame):
            raise LocalizationInputError(f"frames[{k}]: expected a localizer.track.Frame")
        motion = _motion(f.motion, f"frames[{k}].motion")
        try:
            obs = parse_observations(f.observations, options.max_observations,
                                     options.max_observation_range_m)  # fmt: skip
        except LocalizationInputError as exc:
            raise LocalizationInputError(f"frames[{k}].{exc}") from exc
        parsed.append((obs, motion))

    frame_geo = map_index.frame
    crs = map_index.crs
    null = options.null_score
    result = SequenceResult()
    if state is None:
        gps = _gps_track(frame_geo, prior, null)
        first = localize(map_index, parsed[0][0], prior, options=options)
        tracks, shift = _prune(_children(first, gps, 0.0, 1.0, frame_geo), null, topt)
        _edge_hold(map_index, tracks, gps, parsed[0][0], null, options)  # its answer had the check
        result.poses.append(first)
        yield first
        rest, seen = parsed[1:], 1
        history = [(parsed[0][0], parsed[0][1], 1.0, True)]
    else:
        tracks = [_Track(t[:3], t[3], t[4], t[5], t[6], established=t[7]) for t in state.tracks]
        cov = (np.array(state.gps_covariance, float) if state.gps_covariance is not None
               else np.diag([state.gps[3] ** 2, state.gps[3] ** 2, state.gps[4] ** 2]))
        gps = _with_cov(_Track(state.gps[:3], state.gps[3], state.gps[4], null, False), cov)
        if prior is not None:
            # A newer fix, at the first of these frames: carried back by its
            # odometry, so that the step below brings it to where it was taken.
            gps = _unpredict(_gps_track(frame_geo, prior, null), parsed[0][1])
        rest, seen = parsed, state.frames
        history = [(np.array(obs, float).reshape(-1, 3), motion, weight, first)
                   for obs, motion, weight, first in state.history]
        shift = state.shift
    for obs, motion in rest:
        past = _last(history, topt.retrodiction_frames)
        # The frame before started the drive (anew) with the edge in reach:
        # its evidence carries the edge's bias too.
        held = bool(past) and past[-1][3] and _edge_hold(map_index, tracks, gps, past[-1][0], null, options,
                                                          establish=False) is not None  # fmt: skip
        if not held:
            tracks, gps, weight, excess = _step(map_index, tracks, gps, obs, motion, options, topt, frame_geo,
                                                past, shift)
            shift += excess
            history = past + [(obs, motion, weight, False)]
            held = _edge_hold(map_index, tracks, gps, obs, null, options) is not None
            if not held:
                result.poses.append(_estimate(tracks, null, options, frame_geo, crs))
        else:
            gps = _predict(gps, motion, topt, floor=False)
            tracks = [_predict(t, motion, topt) for t in tracks]
        if held:
            # No track has been sure with no edge in reach, and one is in reach
            # now or was at the frame before: the frames so far carry the
            # edge's bias, so the drive starts again at this frame, as its
            # first, with a single frame's check. The tracks go on by the
            # odometry with that bias taken off (each as likely as "none of
            # these"), so that a frame which matches nothing does not end them.
            first = localize(map_index, obs, _prior_of(gps, frame_geo), options=options)
            carried = [replace(t, log_w=null) for t in tracks]
            tracks, shift = _prune(_children(first, gps, 0.0, 1.0, frame_geo) + carried, null, topt)
            _edge_hold(map_index, tracks, gps, obs, null, options)
            history = [(obs, motion, 1.0, True)]
            result.poses.append(first if first.status != "failed" or not tracks
                                else _estimate(tracks, null, options, frame_geo, crs))
        yield result.poses[-1]
    history = _last(history, topt.retrodiction_frames)
    result.tracks = len(tracks)
    result.state = TrackState(
        crs, seen + len(rest),
        tuple((*(float(v) for v in t.pose), *_state_sigmas(t), float(t.log_w), bool(t.matched), bool(t.established))
              for t in tracks),
        (*(float(v) for v in gps.pose), *_state_sigmas(gps)),
        _frozen(gps.cov),
        tuple((_frozen(obs), motion, float(weight), bool(first)) for obs, motion, weight, first in history),
        float(shift),
    )
    return result


def carry_prior(map_index: MapIndex, prior: Prior, motions: Sequence[tuple[float, float, float]],
                track_options: TrackOptions | None = None) -> Prior:
    """A GPS fix carried along by odometry, as the prior of a later frame.

    The fix moves as :func:`localize_sequence` moves its own: by each motion
    ``(dx, dy, dyaw)`` (metres forward, metres left, radians counter-clockwise,
    in the vehicle frame before it), its uncertainty propagated through the
    motion with the odometry noise of ``track_options``. A heading error
    carried along moves the fix across the direction driven, so the result's
    ``position_ellipse`` grows across the road and hardly along it.

    Raises
    ------
    LocalizationInputError
        For a malformed prior or motion.
    """
    if not isinstance(map_index, MapIndex):
        raise LocalizationInputError("map_index: expected a localizer.MapIndex")
    _check_prior(prior)
    topt = track_options or TrackOptions()
    t = _gps_track(map_index.frame, prior, 0.0)
    for k, m in enumerate(motions):
        t = _predict(t, _motion(m, f"motions[{k}]"), topt, floor=False)
    return _prior_of(t, map_index.frame)


def _state_sigmas(t: _Track) -> tuple[float, float]:
    return (float(min(max(t.sigma_m, _MIN_STATE_SIGMA), MAX_SIGMA_M)),
            float(min(max(t.sigma_yaw, _MIN_STATE_SIGMA), MAX_SIGMA_YAW)))


def _step(map_index: MapIndex, tracks: list[_Track], gps: _Track, obs, motion, options: Options,
          topt: TrackOptions, frame_geo, history: list,
          shift: float) -> tuple[list[_Track], _Track, float, float]:
    """One frame after the first: every track predicted by the odometry and updated by the frame.

    ``history``: the frames before it that a new pose is retrodicted on
    (:func:`_retrodicted`), ``shift``: the weight ``max_lead`` has taken off
    the tracks so far. Returns the tracks, the GPS fix, the share of this
    frame's evidence a track gained, and the weight ``max_lead`` took off now.
    """
    null = options.null_score
    view = _view_depth(options)
    # The share of new ground this frame sees: its evidence counts in that
    # proportion (times evidence_scale), see the module docstring.
    weight = min(1.0, topt.evidence_scale
                 * (math.hypot(motion[0], motion[1]) / view[0] + abs(motion[2]) / view[1]))
    children: list[_Track] = []
    for t in tracks:
        parent = _predict(t, motion, topt)
        r = localize(map_index, obs, _prior_of(parent, frame_geo), options=options)
        # "All clutter" counts against a track as far as the map says the
        # camera should have seen something there: through a stretch without
        # markings the track goes on by the odometry, not fading.
        miss = -topt.unexplained_penalty * (1.0 - _p_nothing_seen(map_index, parent.pose, options))
        children.extend(_children(r, parent, parent.log_w, weight, frame_geo, miss))
    gps = _predict(gps, motion, topt, floor=False)
    prob = _posterior(tracks, null)
    if not tracks or prob[0] < options.ambiguity_probability:
        # No confident track: search around the GPS fix again, as the first
        # frame did. What it finds starts from "none of these" with this
        # frame's evidence in full (those poses explained nothing before).
        r = localize(map_index, obs, _prior_of(gps, frame_geo), options=options)
        found = _children(r, gps, null, 1.0, frame_geo)
        if history:
            for c in found:
                if any(_same_track(c, k, topt) for k in children):
                    continue
                before = _retrodicted(map_index, c.pose, motion, history, options, topt, frame_geo)
                if before is not None:
                    lp = _log_prior(c.pose, gps)
                    c.log_w = max(c.log_w, before - shift + weight * (c.log_w - null - lp) + lp)
        children.extend(found)
    tracks, excess = _prune(children, null, topt)
    return tracks, gps, weight, excess


def _same_track(a: _Track, b: _Track, topt: TrackOptions) -> bool:
    """Whether two tracks end within ``merge_distance_m`` and ``merge_heading_deg``: one hypothesis."""
    return (math.hypot(a.pose[0] - b.pose[0], a.pose[1] - b.pose[1]) <= topt.merge_distance_m
            and abs(wrap_angle(a.pose[2] - b.pose[2])) <= math.radians(topt.merge_heading_deg))


def _retrodicted(map_index: MapIndex, pose, motion, history: list, options: Options, topt: TrackOptions,
                 frame_geo) -> float | None:
    """The log weight a track at ``pose`` would hold had it been followed through ``history``.

    ``pose`` is this frame's, ``motion`` the odometry into it; ``history`` the
    frames before, oldest first, as ``(observations, motion into it, weight,
    first)``. The pose is moved back frame by frame and each frame localized
    with the moved pose as a track's prior; the hypothesis of that answer
    within 1 m and 3° of it gives the frame's evidence, as it would have to
    the track (none there: the frame counts as all clutter, as for a track).
    The earliest frame starts the track as the first frame of a drive does
    (from 0) or as the GPS search does (from "none of these"); the GPS prior
    term is left to the caller. None: no history.
    """
    if not history:
        return None
    poses = []
    back = _Track(pose, 0.0, 0.0, 0.0, False)
    into = motion
    for _, into_past, _, _ in reversed(history):
        back = _unpredict(back, into)
        poses.append(back.pose)
        into = into_past
    total = None
    sigma_m, sigma_yaw = topt.min_position_sigma_m, math.radians(topt.min_heading_sigma_deg)
    for (obs, _, weight, first), q in zip(history, reversed(poses)):
        pred = _Track(q, sigma_m, sigma_yaw, 0.0, False)
        r = localize(map_index, obs, _prior_of(pred, frame_geo), options=options)
        evidence = None
        if r.status != "failed" and r.log_score is not None:
            items = [((h.easting, h.northing, _grid_yaw(h, frame_geo)), h.log_score)
                     for h in r.hypotheses if h.log_score is not None]
            items = items or [((r.easting, r.northing, r.yaw_grid_rad), r.log_score)]
            for p, ls in items:
                if (math.hypot(p[0] - q[0], p[1] - q[1]) <= 1.0
                        and abs(wrap_angle(p[2] - q[2])) <= math.radians(3.0)):
                    evidence = ls - _log_prior(p, pred)
                    break
        if evidence is None:
            evidence = -topt.unexplained_penalty * (1.0 - _p_nothing_seen(map_index, q, options))
        if total is None:
            total = (0.0 if first else options.null_score) + evidence
        else:
            total += weight * evidence
    return total


def _p_nothing_seen(map_index: MapIndex, pose, options: Options) -> float:
    """Probability that the camera at ``pose`` reports none of the markings the map puts in its view.

    Each expected centroid in view (a point-like marking, or a cluster every
    few metres along a solid line; the view and misses of the negative
    evidence, ``Options.view_*`` and ``miss_probability``) is missed
    independently.
    """
    view = _camera_view(options)
    local = LocalMap(map_index, (pose[0], pose[1]), view[1] + 1.0)
    if len(local.expect_xy) == 0:
        return 1.0
    nowhere = np.array([[1e9, 1e9]])  # no observation explains anything
    points, solid = missed_counts(local, nowhere, [(0.0, 0.0, pose[2])], options, view)
    return float(options.miss_probability ** points[0] * options.solid_miss_probability ** solid[0])


def _camera_view(options: Options) -> tuple[float, float, float]:
    """The configured ground view: min range (m), max range (m), half angle (rad); defaults 4, 25 m and 30°."""
    lo = options.view_min_range_m if options.view_min_range_m is not None else 4.0
    hi = options.view_max_range_m if options.view_max_range_m is not None else 25.0
    fov = options.view_half_fov_deg if options.view_half_fov_deg is not None else 30.0
    return lo, hi, math.radians(fov)


def _view_depth(options: Options) -> tuple[float, float]:
    """Metres of road and radians of heading after which a frame sees all-new ground."""
    lo, hi, half = _camera_view(options)
    return max(hi - lo, 1.0), 2.0 * max(half, math.radians(1.0))


def _grid_pose(frame_geo, prior: Prior) -> tuple[float, float, float]:
    x, y = frame_geo.to_xy(prior.lon, prior.lat)
    return float(x), float(y), float(frame_geo.heading_to_grid_yaw(prior.heading_deg, prior.lon, prior.lat))


def _gps_track(frame_geo, prior: Prior, null: float) -> _Track:
    """The GPS fix as a track: searched around while no track is sure, never an answer itself."""
    cov = np.zeros((3, 3))
    cov[:2, :2] = position_covariance(prior, frame_geo)
    cov[2, 2] = math.radians(prior.heading_sigma_deg) ** 2
    return _with_cov(_Track(_grid_pose(frame_geo, prior), 0.0, 0.0, null, False), cov)


def _with_cov(t: _Track, cov: np.ndarray) -> _Track:
    """``t`` with covariance ``cov``, its scalar sigmas set from it (capped, see MAX_SIGMA_M)."""
    cov = 0.5 * (cov + cov.T)
    sigma_m = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
    if sigma_m > MAX_SIGMA_M:
        # shrink the position part (and its correlation with the heading) to the cap
        f = MAX_SIGMA_M / sigma_m
        cov = cov * np.array([[f * f, f * f, f], [f * f, f * f, f], [f, f, 1.0]])
        sigma_m = MAX_SIGMA_M
    sigma_yaw = math.sqrt(max(cov[2, 2], 0.0))
    if sigma_yaw > MAX_SIGMA_YAW:
        g = MAX_SIGMA_YAW / sigma_yaw
        cov = cov * np.array([[1.0, 1.0, g], [1.0, 1.0, g], [g, g, g * g]])
        sigma_yaw = MAX_SIGMA_YAW
    return replace(t, sigma_m=sigma_m, sigma_yaw=sigma_yaw, cov=cov)


def _ellipse(cov2: np.ndarray, frame_geo, lon: float, lat: float) -> ErrorEllipse:
    """The error ellipse of a 2x2 grid-axes covariance at (lon, lat), as a prior takes it."""
    val, vec = np.linalg.eigh(0.5 * (cov2 + cov2.T))
    yaw = math.atan2(vec[1, 1], vec[0, 1])  # the major axis, a grid direction
    major = float(np.clip(math.sqrt(max(val[1], 0.0)), 0.01, 1000.0))
    minor = float(np.clip(math.sqrt(max(val[0], 0.0)), 0.01, major))
    return ErrorEllipse(major, minor, float(frame_geo.grid_yaw_to_heading(yaw, lon, lat)) % 360.0)


def _prior_of(t: _Track, frame_geo) -> Prior:
    lon, lat = frame_geo.to_lonlat(t.pose[0], t.pose[1])
    return Prior(
        lat=float(lat), lon=float(lon),
        heading_deg=float(frame_geo.grid_yaw_to_heading(t.pose[2], lon, lat)) % 360.0,
        position_sigma_m=float(np.clip(t.sigma_m, 0.01, 1000.0)),
        heading_sigma_deg=float(np.clip(math.degrees(t.sigma_yaw), 0.01, 180.0)),
        position_ellipse=None if t.cov is None else _ellipse(t.cov[:2, :2], frame_geo, float(lon), float(lat)),
    )  # fmt: skip


def _predict(t: _Track, motion, topt: TrackOptions, floor: bool = True) -> _Track:
    """The track moved by the odometry, its uncertainty grown by the odometry's noise.

    A track with a covariance (the GPS fix) propagates it through the motion:
    an error in its heading moves it across the direction driven by the
    distance times that error, and it is the same error every frame, so the
    fix's uncertainty grows across the road, not along it.
    """
    dx, dy, dyaw = motion
    c, s = math.cos(t.pose[2]), math.sin(t.pose[2])
    pose = (t.pose[0] + c * dx - s * dy, t.pose[1] + s * dx + c * dy, float(wrap_angle(t.pose[2] + dyaw)))
    odo = topt.odometry_sigma_m + topt.odometry_sigma_ratio * math.hypot(dx, dy)
    if t.cov is not None:
        jac = np.array([[1.0, 0.0, -(s * dx + c * dy)], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
        noise = np.diag([odo**2, odo**2, math.radians(topt.odometry_sigma_yaw_deg) ** 2])
        return _with_cov(replace(t, pose=pose, answer=None), jac @ t.cov @ jac.T + noise)
    s_m = max(t.sigma_m, topt.min_position_sigma_m) if floor else t.sigma_m
    s_yaw = max(t.sigma_yaw, math.radians(topt.min_heading_sigma_deg)) if floor else t.sigma_yaw
    # Capped: the GPS fix's uncertainty grows frame after frame over a long drive.
    return replace(t, pose=pose, sigma_m=min(math.hypot(s_m, odo), MAX_SIGMA_M),
                   sigma_yaw=min(math.hypot(s_yaw, math.radians(topt.odometry_sigma_yaw_deg)), MAX_SIGMA_YAW),
                   answer=None)  # fmt: skip


def _unpredict(t: _Track, motion) -> _Track:
    """The pose from which ``motion`` leads to ``t``'s (its uncertainty unchanged)."""
    dx, dy, dyaw = motion
    yaw = float(wrap_angle(t.pose[2] - dyaw))
    c, s = math.cos(yaw), math.sin(yaw)
    return replace(t, pose=(t.pose[0] - c * dx + s * dy, t.pose[1] - s * dx - c * dy, yaw))


def _log_prior(pose, t: _Track) -> float:
    """The prior term :func:`localize` adds for ``pose`` under the prior ``_prior_of(t)``."""
    # a prior's position and heading are independent: the position's block alone
    pos_info = t.sigma_m if t.cov is None else np.linalg.inv(t.cov[:2, :2])
    return log_prior(pose, t.pose, pos_info, t.sigma_yaw)


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
        out.append(_Track(pose, s_m, s_yaw, base + weight * (ls - lp) + lp, True, r,
                          established=parent.established))
    return out + keep


def _grid_yaw(h: Hypothesis, frame_geo) -> float:
    return float(frame_geo.heading_to_grid_yaw(h.heading_deg, h.lon, h.lat))


def _prune(tracks: list[_Track], null: float, topt: TrackOptions) -> tuple[list[_Track], float]:
    """The tracks merged, the weakest dropped, and the lead capped: the tracks and the weight taken off each."""
    tracks = sorted(tracks, key=lambda t: -t.log_w)
    kept: list[_Track] = []
    for t in tracks:
        for k in kept:
            if _same_track(t, k, topt):
                k.log_w = float(np.logaddexp(k.log_w, t.log_w))
                k.matched = k.matched or t.matched
                k.established = k.established or t.established
                break
        else:
            kept.append(replace(t))
    prob = _posterior(kept, null)
    kept = [t for t, p in zip(kept, prob) if p >= topt.min_track_probability][: topt.max_tracks]
    excess = (kept[0].log_w - null - topt.max_lead) if kept else 0.0
    if excess <= 0:
        return kept, 0.0
    for t in kept:
        t.log_w -= excess
    return kept, float(excess)


def _posterior(tracks: list[_Track], null: float) -> np.ndarray:
    """Probabilities of the tracks; the rest is "none of these" (every observation clutter)."""
    w = np.array([t.log_w for t in tracks] + [null], float)
    w = np.exp(w - w.max())
    return w[:-1] / w.sum()


def _edge_hold(map_index: MapIndex, tracks: list[_Track], gps: _Track, obs: np.ndarray, null: float,
               options: Options, establish: bool = True) -> str | None:
    """Why the drive cannot trust its tracks at the map's edge (None: it can), establishing the best.

    While no track is established, the camera seeing beyond the map from the
    best one or from a pose within the GPS fix's reach along its heading (from
    the fix, carried by the odometry)
    (:func:`localizer.core.edge_reason` with the fix's position covariance:
    rivals were searched for around it) gives the reason, sure or not. Else
    a best track the drive is sure of becomes established (with ``establish``).
    A drive with an established track is followed as the filter follows any:
    once sure it searches for no new rival, and one that overtook its
    established track near an edge would owe it to the edge.
    """
    if not tracks or any(t.established for t in tracks):
        return None
    best = tracks[0]
    cov = gps.cov[:2, :2] if gps.cov is not None else np.eye(2) * gps.sigma_m**2
    reason = edge_reason(map_index, obs, best.pose, cov, options, centre=gps.pose[:2])
    if establish and reason is None and _posterior(tracks, null)[0] >= options.ambiguity_probability:
        best.established = True
    return reason


def _estimate(tracks, null, options: Options, frame_geo, crs) -> Pose:
    if not tracks:
        return Pose(status="failed", crs=crs, reason="no pose hypothesis is left: the frames matched nothing, "
                    "neither where the tracks were predicted nor around the GPS fix")
    best = tracks[0]
    prob = _posterior(tracks, null)
    status = "ok" if prob[0] >= options.ambiguity_probability else "ambiguous"
    out = _pose_at(best, status, frame_geo, crs)
    out.probability = float(prob[0])
    if status == "ambiguous":
        listed = []
        for t, p in zip(tracks[: options.max_hypotheses], prob):
            if p < options.min_hypothesis_probability:
                break
            h = _pose_at(t, "ok", frame_geo, crs)
            out.hypotheses.append(Hypothesis(h.lat, h.lon, h.heading_deg, h.easting, h.northing, float(p),
                                             log_score=t.log_w, covariance=h.covariance))
            listed.append(t.pose)
        out.mixture_covariance = mixture_covariance(
            best.pose, listed, [h.score for h in out.hypotheses], [h.covariance for h in out.hypotheses])
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

"""Input and result records of the localizer (explicit dataclasses)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .errors import LocalizationInputError

Status = Literal["ok", "ambiguous", "failed"]


@dataclass(frozen=True)
class ErrorEllipse:
    """A position's one-sigma error ellipse, as GNSS receivers report it (NMEA GST).

    Attributes
    ----------
    sigma_major_m, sigma_minor_m : float
        Standard deviations along the ellipse's major and minor axes, metres
        (``sigma_minor_m <= sigma_major_m``).
    orientation_deg : float
        Direction of the major axis, degrees clockwise from true north (an
        axis: 30 and 210 are the same ellipse).
    """

    sigma_major_m: float
    sigma_minor_m: float
    orientation_deg: float


@dataclass(frozen=True)
class Prior:
    """A coarse GPS fix.

    Attributes
    ----------
    lat, lon : float
        WGS84 latitude and longitude, degrees.
    heading_deg : float
        Heading, degrees clockwise from true north.
    position_sigma_m : float
        Standard deviation of each horizontal position component, metres.
    heading_sigma_deg : float
        Standard deviation of the heading, degrees.
    position_ellipse : ErrorEllipse, optional
        The position's error ellipse; when given it replaces
        ``position_sigma_m`` (a receiver in a street canyon, or a fix carried
        along by odometry with an uncertain heading, is far less sure across
        the road than along it, or the other way round).
    """

    lat: float
    lon: float
    heading_deg: float
    position_sigma_m: float = 5.0
    heading_sigma_deg: float = 10.0
    position_ellipse: ErrorEllipse | None = None


@dataclass(frozen=True)
class Hypothesis:
    """One candidate pose of an ambiguous result.

    ``score`` is the posterior probability of the candidate among all candidates found;
    ``log_score`` its unnormalised log posterior (see :attr:`Pose.log_score`);
    ``covariance`` the (3, 3) covariance of (easting m, northing m, yaw rad)
    of this candidate's pose, were it the right one (as :attr:`Pose.covariance`).
    """

    lat: float
    lon: float
    heading_deg: float
    easting: float
    northing: float
    score: float
    log_score: float | None = None
    covariance: np.ndarray | None = field(default=None, compare=False)

    def offset_from(self, pose: "Pose") -> tuple[float, float, float] | None:
        """Where this candidate lies as seen from ``pose`` (the answer it belongs to).

        Returns
        -------
        (x, y, heading) or None
            ``x`` forward and ``y`` left in ``pose``'s vehicle frame (ISO 8855),
            metres of the map CRS; ``heading`` this candidate's heading minus
            ``pose``'s, degrees clockwise, in [-180, 180). None when ``pose``
            has no position. Rivals only along ``x`` are repeating markings
            along the road (the lateral position and heading are sure); a
            ``y`` of a lane's width is a parallel lane.
        """
        if pose.easting is None or pose.northing is None or pose.yaw_grid_rad is None or pose.heading_deg is None:
            return None
        dx, dy = self.easting - pose.easting, self.northing - pose.northing
        c, s = math.cos(pose.yaw_grid_rad), math.sin(pose.yaw_grid_rad)
        turn = math.remainder(self.heading_deg - pose.heading_deg, 360.0)  # [-180, 180]; % can round to 360
        return (c * dx + s * dy, -s * dx + c * dy, -180.0 if turn >= 180.0 else turn)

    def to_dict(self, relative_to: "Pose | None" = None) -> dict[str, Any]:
        """JSON-safe dictionary; with ``relative_to``, its ``offset`` from that answer (:meth:`offset_from`)."""
        out = {
            "lat": float(self.lat),
            "lon": float(self.lon),
            "heading_deg": float(self.heading_deg),
            "easting": float(self.easting),
            "northing": float(self.northing),
            "score": float(self.score),
            "covariance": _matrix(self.covariance),
        }
        if relative_to is not None:
            off = self.offset_from(relative_to)
            out["offset"] = None if off is None else {
                "x_m": float(off[0]), "y_m": float(off[1]), "heading_deg": float(off[2])}
        return out


def _matrix(m) -> list[list[float | None]] | None:
    """A matrix as nested plain floats, non-finite entries as None (JSON has no NaN)."""
    if m is None:
        return None
    return [[float(v) if math.isfinite(v) else None for v in row] for row in np.asarray(m, float)]


@dataclass
class Pose:
    """Result of :func:`localizer.localize`.

    Attributes
    ----------
    status : {"ok", "ambiguous", "failed"}
        ``ambiguous``: several poses explain the observations about equally well
        (repeating dashes, parallel lanes); see ``hypotheses``. ``failed``: see ``reason``.
    lat, lon : float or None
        WGS84 position of the vehicle frame origin, degrees. When ambiguous, the
        pose fields describe the most probable hypothesis.
    heading_deg : float or None
        Degrees clockwise from true north.
    easting, northing : float or None
        Position in the map CRS, metres.
    crs : str
        The map CRS.
    yaw_enu_rad : float or None
        Heading as REP-103 yaw: radians counter-clockwise from (true) east.
    yaw_grid_rad : float or None
        Yaw in the map CRS: radians counter-clockwise from the grid's +x axis.
    covariance : (3, 3) ndarray or None
        Covariance of (easting m, northing m, yaw rad): of the returned pose,
        as the optimum it is (when ambiguous, were the best hypothesis right).
    mixture_covariance : (3, 3) ndarray or None
        When ambiguous: the expected outer product of the returned pose's
        error over the listed hypotheses, ``sum p_i (C_i + d_i d_i^T)`` with
        ``p_i`` their scores rescaled to sum to one, ``C_i`` their covariances
        and ``d_i`` their offsets from the returned pose (yaw wrapped). The
        returned pose's uncertainty with the ambiguity in it: between rivals
        along a road of repeating dashes it is long along the road and about
        as narrow across it as one hypothesis's. An answer the map's edge
        holds back (``Options.edge_share``) adds the prior's own uncertainty
        about it: its rivals there were scored down by what the map lacks
        and need not be listed (:func:`localizer.core.with_prior_uncertainty`). None when ``ok`` or
        ``failed``, when no hypothesis is listed (all below
        ``Options.min_hypothesis_probability``) or one has no covariance.
    iterations : int
        Refinement iterations of the returned pose.
    inliers : int
        Observations matched to the map at the returned pose.
    rms_m : float or None
        Root-mean-square distance of the matched observations, metres.
    probability : float or None
        Default method: posterior probability that the returned pose is the
        right one, among the hypotheses found and "none of these" (every
        observation clutter). ``ok`` means at least
        ``Options.ambiguity_probability`` (0.95); a client that needs more (or
        accepts less) can apply its own threshold. Calibrated on the benchmark
        (``benchmarks/localize_paper.py`` prints how often answers of each
        probability were right). None for ``pink2008`` (the paper's ICP has no
        posterior) and when ``failed``.
    hypotheses : list of Hypothesis
        Best first; filled when ``status == "ambiguous"``. Where each lies
        from the answer, in its vehicle frame: :meth:`Hypothesis.offset_from`
        (``to_dict`` writes it as ``offset``).
    reason : str or None
        Why the localization failed, or why a pose the posterior would call
        sure is ``ambiguous`` (the camera sees beyond the map's edge,
        ``Options.edge_share``).
    transformation : (3, 3) ndarray or None
        Homogeneous 2D transform taking vehicle coordinates to map CRS coordinates.
    trace : list of (easting, northing, yaw_grid_rad)
        Pose after each iteration (only when the options ask for it).
    diagnostics : dict
        Method internals, not part of the API: the default method's coarse
        candidates (``search``), how many observations its coarse search
        correlated (``search_observations``, fewer than given where it kept
        within its budget) and, when asked, the scored hypotheses.
    log_score : float or None
        Default method: the returned pose's unnormalised log posterior, the
        log-likelihood ratio of its matches against "every observation is
        clutter" (divided by ``Options.temperature``) plus the prior's
        log-density without its normalising constant. Comparable between calls
        on the same observations; :func:`localizer.track.localize_sequence`
        chains it over frames. Not part of the API.
    """

    status: Status
    crs: str
    lat: float | None = None
    lon: float | None = None
    heading_deg: float | None = None
    easting: float | None = None
    northing: float | None = None
    yaw_enu_rad: float | None = None
    yaw_grid_rad: float | None = None
    covariance: np.ndarray | None = None
    mixture_covariance: np.ndarray | None = None
    iterations: int = 0
    inliers: int = 0
    rms_m: float | None = None
    probability: float | None = None
    hypotheses: list[Hypothesis] = field(default_factory=list)
    reason: str | None = None
    transformation: np.ndarray | None = None
    trace: list[tuple[float, float, float]] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    log_score: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dictionary for the API (no NaN, plain floats and lists)."""

        def num(v):
            if v is None:
                return None
            v = float(v)
            return v if math.isfinite(v) else None

        return {
            "status": self.status,
            "lat": num(self.lat),
            "lon": num(self.lon),
            "heading_deg": num(self.heading_deg),
            "easting": num(self.easting),
            "northing": num(self.northing),
            "crs": self.crs,
            "yaw_enu_rad": num(self.yaw_enu_rad),
            "covariance": _matrix(self.covariance),
            "mixture_covariance": _matrix(self.mixture_covariance),
            "iterations": int(self.iterations),
            "inliers": int(self.inliers),
            "rms_m": num(self.rms_m),
            "probability": num(self.probability),
            "hypotheses": [h.to_dict(self) for h in self.hypotheses],
            "reason": self.reason,
        }


@dataclass(frozen=True)
class Options:
    """Tuning of both methods; the defaults are the ones benchmarked.

    Paper method (``pink2008``)
    ---------------------------
    max_pair_distance_m : float
        Pairs farther apart than this are dropped (ICP's maximum tolerable distance;
        the paper gives no value, 3 m was best of 1-8 m on the benchmark).
    epsilon_m : float
        ε of the mixed l1/l2 weight ``w = 1 / max(d, ε)`` (0.01-0.2 m perform alike).
    max_iterations : int
        Iteration cap.
    tolerance_m, tolerance_rad : float
        Stop when one iteration moves the pose by less than both.

    Default method
    --------------
    search_sigmas : float
        The global search covers ±``search_sigmas`` prior standard deviations.
    max_search_radius_m, min_search_radius_m : float
        Clamp of the translation search radius, metres.
    search_cell_m : float or None
        Translation step of the coarse search; None: a thirtieth of the search
        radius, between 0.5 and 0.75 m.
    max_search_observations : int
        The coarse search uses at most this many observations (highest weight first).
    max_refine_work : int
        Observations × candidates one refinement pass takes at most: beyond it
        the pass (the first ``candidates``, then the ``extra_candidates``)
        refines only the best coarse candidates, never fewer than four. With
        20 a pass this bites from 121 observations on (the coarse search's own
        ``max_search_observations``); a frame of 500 observations that nothing
        explains, under a fix of any heading, then costs about half the CPU
        (on the Karlsruhe map 0.50 s instead of 0.95 s).
    max_search_cells, max_search_work : int
        The coarse search's budget: the most cells of its heading × translation
        volume (float32, 4 bytes each), and the most cells × observations it
        sums. A far observation needs a fine heading step: a request within
        the API's limits (any heading, the 45 m radius, 500 observations out to
        148 m) would need 18 million cells and 2·10⁹ sums, about 1 s of CPU
        and 120–160 MiB. Beyond the first budget the farthest observations are
        left out of the coarse search, beyond the second those of lowest
        weight; the nearest or best eight always stay, and every observation
        still counts in the refinement and the scores. (Only a
        ``search_cell_m`` finer than the default's can make the translation
        grid alone, at the coarsest heading step of 3°, exceed the first.)
        The defaults leave every scene of the benchmarks untouched: the
        widest, 20 m / ±30°, needs under a million cells and 4·10⁷ sums.
    candidates : int
        Coarse optima that are refined (at most).
    extra_candidates, extra_search_probability : int, float
        When the best hypothesis from the first ``candidates`` holds less than
        ``extra_search_probability`` of the posterior, up to
        ``extra_candidates`` further coarse optima are refined too (where
        clutter or a wide prior crowded the truth out of the first ones; an
        answer beyond doubt costs nothing more). 0 disables it.
    coarse_pool : int
        This many of the best coarse optima (at least ``candidates`` +
        ``extra_candidates``) are charged their negative evidence (see
        ``miss_probability``) before the best ``candidates`` +
        ``extra_candidates`` of them are refined. The correlation rewards
        every match, clutter's too, and knows nothing of markings a pose puts
        in view that nobody saw; on the benchmark's 20 m / ±30° scenes the
        truth's optimum was often ranked below the 40th. 0 disables it (the
        correlation's own ranking).
    neighbour_starts : sequence of (along_m, across_m, turn_deg)
        Once the hypotheses are ranked, the best one's pose is refined again
        (fine scales only) from each of these offsets: metres along and across
        its heading, degrees turned counter-clockwise. A coarse cell is about
        as wide as the basin of a pose's optimum, so the best candidate can
        settle in a basin next to the truth's while no coarse candidate lay in
        the truth's; a restart from beside it finds that basin, which then
        wins or, as a rival, makes the answer ambiguous instead of
        confidently wrong. Empty: no restarts.
    candidate_margin : float
        Beyond the best four, coarse optima scoring more than this below the best
        (log units) are not refined. Under heavy clutter the coarse correlation
        rewards chance matches, and the truth's optimum was found 11–14 below the
        best in scenes that a margin of 10 left confidently wrong.
    heading_restarts : int
        The best this many coarse optima more than 3 m from the best
        hypothesis (beside it, ``neighbour_starts`` search) are refined again
        at its heading where theirs differs from it by more than 1.5°.
        The coarse grid's headings lie several degrees apart; a coarse optimum
        next to the truth's position but turned by one step can be refined to
        a nearby wrong heading, and the truth is then missing from the
        hypotheses. Rivals along a lane share its heading, so the best
        hypothesis's is the one to try. Only under a prior whose position
        sigma is at least 3 m (where a pose 3 m away is no more than a sigma
        off): under a GPS-like prior they found nothing on the benchmark and
        cost a fifth of a request's CPU. 0: no such restarts.
    anneal_m : tuple of float
        Robust (Geman-McClure) scales of the refinement, coarse to fine, metres.
    iterations_per_scale : int
        Most iterations of the refinement at each scale (fewer where every
        candidate has stopped moving). 4 takes 15-30 % less CPU per request,
        for a few more confidently wrong answers on maps built from imagery
        (``benchmarks/RESULTS-localizer.md``).
    noise_m, noise_range_coeff : float
        Observation noise model ``sigma(r) = noise_m + noise_range_coeff * r**2``
        (flat-ground camera: range error grows with range²).
    bearing_noise_rad : float or None
        Across the viewing ray the noise is ``noise_m + bearing_noise_rad * r``:
        a camera measures the direction to a marking far better than its range,
        so a pose that puts far observations beside their markings is penalised
        more than one that puts them short or long. Hypothesis scores and the
        last refinement scale use this anisotropic model; None: the range model
        in every direction.
    crowd_radius_m : float or None
        Observations within about this distance of each other share their
        weight (a Gaussian count of neighbours; the frame's total weight is
        kept): a preceding vehicle's or a curb's clusters, or a marking split
        in several, are not independent evidence. Measured on
        ``benchmarks/localize_paper.py`` (1.0, 1.5, 2 and 3 m tried). None: every
        observation keeps its own weight. Not used by ``pink2008``.
    edge_share : float or None
        An answer is at most ``ambiguous`` when more than this share of the
        observations' weight lies beyond the map's extent (the ground between
        its markings, :attr:`MapIndex.extent`, by more than 1 m) at its pose,
        or at its pose moved along its heading to where the prior's position
        lies along it and from there, either way, by three of the prior's
        position sigmas along that heading (the poses the prior admits, which
        an answer at the side of its region may be farther from). At a map's edge the
        camera sees markings the map does not hold; a pose one dash period
        away matches them to the map's own dashes and wins, surely and
        wrongly (from 8-10 m with the map ending 5-25 m ahead: 15-22 % of
        answers ``ok`` and more than 1 m off, ``benchmarks/localize_edge.py``).
        Such an answer, sure or not, carries a ``reason`` and a
        ``mixture_covariance`` with the prior's uncertainty in it: the truth
        may be a pose the map's missing markings scored down. None: no such
        check.
    edge_rival_m : float
        ``edge_share`` applies only when those three sigmas reach at least
        this far (metres): half the 9 m dash period, below which no rival a
        period away is within the prior's reach.
    edge_reach_m : float
        The farthest the pose is moved from the prior's position for
        ``edge_share``, metres: rivals lie
        one or two dash periods away (of the answers more than 1 m off at a
        map's edge, 8-10 m prior, nearly all lay within 20 m of the truth).
    outlier_density : float
        Relative density of outliers in the per-observation likelihood.
    clutter_reference : float
        When the best pose leaves more than this many observations unexplained,
        the outlier density used to score hypotheses grows in proportion (the
        clutter rate of the frame: under heavy clutter a chance match is likelier,
        so each match is weaker evidence).
    miss_probability : float
        Probability that the camera misses a marking in its view; each map marking
        predicted in view but not explained by an observation within
        ``explain_distance_m`` costs ``log(1 / miss_probability)``.
    solid_miss_probability : float
        The same for each expected cluster of a solid line (one every 3 m).
    explain_distance_m : float
        See ``miss_probability``, metres.
    solid_explain_along_m, solid_explain_across_m : float
        An expected cluster of a solid line is also explained by an observation
        within this distance along its line and this distance across it,
        metres: the camera clusters a line at its own phase, so near a line's
        end its first cluster can lie up to a clustering period (3 m) from the
        expected one.
    view_min_range_m, view_max_range_m, view_half_fov_deg : float or None
        The camera's ground view (a forward camera seeing the ground 4-25 m ahead
        within ±30° by default), widened to cover every observation; None: taken
        from the extent of the observations alone.
    view_margin_m, view_margin_deg : float
        Expected markings this close to the edge of the view are not held against a
        pose (a marking just outside may be seen, one just inside missed).
    temperature : float
        Scores are divided by this before turning them into probabilities;
        > 1 would discount observations whose errors are correlated. 1 since
        the crowd weights (``crowd_radius_m``) share the weight of clustered
        observations: re-fitted then by the log-loss of the answers'
        probability (``benchmarks/localize_calibrate.py``; 1.35 before).
    ambiguity_probability : float
        ``ok`` needs the best hypothesis to hold at least this posterior probability.
    null_score : float
        Log score of "none of the hypotheses found": all observations clutter
        (data log-likelihood ratio 0) at the prior's mean, less a little for a
        search that found nothing (calibrated); it takes its share of
        the posterior, so a best hypothesis must explain clearly more than
        clutter would to be ``ok``. ``-inf`` disables it.
    max_hypotheses, min_hypothesis_probability : int, float
        An ambiguous result lists at most this many hypotheses, each at least this probable.
    min_inliers : int
        Poses matching fewer observations do not compete while any pose
        matches this many.
    fallback_min_inliers : int
        When no pose matches ``min_inliers`` observations, poses matching this
        many compete instead (two point markings fix a pose; their answer is
        ``ok`` only if its posterior is as clear as any other's); fewer →
        ``failed``. Taken as ``min_inliers`` where it is larger.
    inlier_distance_m : float
        An observation within this distance of the map, or three noise sigmas if that
        is more, is an inlier at the final pose.
    camera_height_m, pitch_sigma_deg : float
        Camera height over the ground and the uncertainty of its pitch (ground-plane
        estimate); a pitch error scales all ranges together, a correlated error
        the covariance includes explicitly.
    estimate_pitch : bool
        Refine the chosen pose jointly with the camera's pitch error (prior
        ``pitch_sigma_deg``; :func:`localizer.robust.refine_with_pitch`). The far
        markings then no longer drag the pose along the road when the ground
        plane is tilted; the covariance keeps the pitch's remaining uncertainty.
    covariance_inflation : float
        Scale of the estimated covariance (calibrated on the benchmark).
    max_observations : int
        More observations than this are rejected as bad input.
    max_observation_range_m : float
        Observations farther from the vehicle are rejected as bad input.
    record_trace : bool
        Keep the pose after every iteration in ``Pose.trace``.
    record_candidates : bool
        Keep every scored hypothesis with the parts of its score (positive
        evidence, missed markings, prior) in ``Pose.diagnostics["candidates"]``
        (for calibration; costs a few milliseconds).
    """

    max_pair_distance_m: float = 3.0
    epsilon_m: float = 0.05
    max_iterations: int = 30
    tolerance_m: float = 1e-3
    tolerance_rad: float = 1e-4

    search_sigmas: float = 3.0
    max_search_radius_m: float = 45.0
    min_search_radius_m: float = 3.0
    search_cell_m: float | None = None
    max_search_observations: int = 120
    max_refine_work: int = 2_400
    max_search_cells: int = 4_000_000
    max_search_work: int = 200_000_000
    candidates: int = 20
    extra_candidates: int = 20
    extra_search_probability: float = 0.999
    coarse_pool: int = 100
    candidate_margin: float = 15.0
    heading_restarts: int = 4
    anneal_m: tuple[float, ...] = (0.8, 0.4, 0.2, 0.15)
    iterations_per_scale: int = 6
    noise_m: float = 0.05
    noise_range_coeff: float = 5e-4
    bearing_noise_rad: float | None = 0.003
    crowd_radius_m: float | None = 1.5
    edge_share: float | None = 0.2
    edge_rival_m: float = 4.5
    edge_reach_m: float = 20.0
    outlier_density: float = 0.05
    clutter_reference: float = 8.0
    miss_probability: float = 0.3
    solid_miss_probability: float = 0.3
    explain_distance_m: float = 1.5
    solid_explain_along_m: float = 3.0
    solid_explain_across_m: float = 0.75
    view_min_range_m: float | None = 4.0
    view_max_range_m: float | None = 25.0
    view_half_fov_deg: float | None = 30.0
    view_margin_m: float = 1.0
    view_margin_deg: float = 2.0
    temperature: float = 1.0
    ambiguity_probability: float = 0.95
    null_score: float = -1.0
    max_hypotheses: int = 8
    min_hypothesis_probability: float = 0.002
    min_inliers: int = 3
    fallback_min_inliers: int = 2
    inlier_distance_m: float = 0.75
    camera_height_m: float = 1.3
    pitch_sigma_deg: float = 0.05
    estimate_pitch: bool = True
    covariance_inflation: float = 1.0
    max_observations: int = 500
    max_observation_range_m: float = 150.0
    neighbour_starts: tuple[tuple[float, float, float], ...] = (
        (-1.5, 0.0, 0.0), (-0.75, 0.0, 0.0), (0.75, 0.0, 0.0), (1.5, 0.0, 0.0),
        (0.0, -0.75, 0.0), (0.0, 0.75, 0.0), (0.0, 0.0, -2.0), (0.0, 0.0, 2.0),
    )
    record_trace: bool = False
    record_candidates: bool = False

    def __post_init__(self) -> None:
        """Reject values no scene could make sense of (the message names the field)."""
        for name, lo, lo_open, hi, hi_open in _OPTION_RANGES:
            _check_range(name, getattr(self, name), lo, lo_open, hi, hi_open)
        for name, least in _OPTION_COUNTS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
                raise LocalizationInputError(f"options.{name}: must be a whole number >= {least}, got {v!r}")
        for name, lo, lo_open, hi, hi_open in _OPTIONAL_RANGES:
            if getattr(self, name) is not None:
                _check_range(name, getattr(self, name), lo, lo_open, hi, hi_open)
        if not isinstance(self.null_score, (int, float, np.floating)) or math.isnan(self.null_score) \
                or self.null_score == math.inf:
            raise LocalizationInputError(f"options.null_score: must be a number or -inf, got {self.null_score!r}")
        starts = self.neighbour_starts
        if not isinstance(starts, (tuple, list)) or not all(
            isinstance(t, (tuple, list)) and len(t) == 3
            and all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                    and math.isfinite(v) for v in t)
            for t in starts
        ):
            raise LocalizationInputError(
                "options.neighbour_starts: must be a sequence of (along_m, across_m, turn_deg) "
                f"triples of finite numbers, got {starts!r}"
            )
        anneal = self.anneal_m
        if not isinstance(anneal, (tuple, list)) or not anneal:
            raise LocalizationInputError("options.anneal_m: must be a non-empty sequence of scales in metres")
        for v in anneal:
            _check_range("anneal_m", v, 0.0, True, math.inf, True)
        # Lists are accepted and kept as tuples: Options are compared and hashed
        # (the localizer caches options derived from them).
        object.__setattr__(self, "anneal_m", tuple(float(v) for v in anneal))
        object.__setattr__(self, "neighbour_starts", tuple(tuple(float(v) for v in t) for t in starts))
        if self.min_search_radius_m > self.max_search_radius_m:
            raise LocalizationInputError(
                f"options.min_search_radius_m: {self.min_search_radius_m!r} exceeds "
                f"max_search_radius_m {self.max_search_radius_m!r}"
            )
        if (self.view_min_range_m is not None and self.view_max_range_m is not None
                and self.view_min_range_m >= self.view_max_range_m):
            raise LocalizationInputError(
                f"options.view_min_range_m: {self.view_min_range_m!r} is not below "
                f"view_max_range_m {self.view_max_range_m!r}"
            )
        if self.estimate_pitch and self.pitch_sigma_deg <= 0:
            raise LocalizationInputError(
                "options.pitch_sigma_deg: must be > 0 to estimate the pitch (or set estimate_pitch=False)"
            )


#: ``(field, low, low excluded, high, high excluded)`` of every numeric option.
_OPTION_RANGES = (
    ("max_pair_distance_m", 0.0, True, math.inf, True),
    ("epsilon_m", 0.0, True, math.inf, True),
    ("tolerance_m", 0.0, False, math.inf, True),
    ("tolerance_rad", 0.0, False, math.inf, True),
    ("search_sigmas", 0.0, True, math.inf, True),
    ("max_search_radius_m", 0.0, True, math.inf, True),
    ("min_search_radius_m", 0.0, True, math.inf, True),
    ("candidate_margin", 0.0, False, math.inf, False),
    ("noise_m", 0.0, True, math.inf, True),
    ("noise_range_coeff", 0.0, False, math.inf, True),
    ("outlier_density", 0.0, True, math.inf, True),
    ("clutter_reference", 0.0, True, math.inf, True),
    ("miss_probability", 0.0, True, 1.0, False),
    ("solid_miss_probability", 0.0, True, 1.0, False),
    ("explain_distance_m", 0.0, True, math.inf, True),
    ("solid_explain_along_m", 0.0, False, math.inf, True),
    ("solid_explain_across_m", 0.0, False, math.inf, True),
    ("view_margin_m", 0.0, False, math.inf, True),
    ("view_margin_deg", 0.0, False, 180.0, False),
    ("temperature", 0.0, True, math.inf, True),
    ("ambiguity_probability", 0.0, True, 1.0, False),
    ("extra_search_probability", 0.0, False, 1.0, False),
    ("min_hypothesis_probability", 0.0, False, 1.0, False),
    ("inlier_distance_m", 0.0, True, math.inf, True),
    ("camera_height_m", 0.0, True, math.inf, True),
    ("pitch_sigma_deg", 0.0, False, 90.0, True),
    ("covariance_inflation", 0.0, True, math.inf, True),
    ("max_observation_range_m", 0.0, True, math.inf, True),
    ("edge_rival_m", 0.0, False, math.inf, True),
    ("edge_reach_m", 0.0, False, math.inf, True),
)

#: The same for the options that may be None.
_OPTIONAL_RANGES = (
    ("search_cell_m", 0.0, True, math.inf, True),
    ("bearing_noise_rad", 0.0, False, math.inf, True),
    ("crowd_radius_m", 0.0, True, math.inf, True),
    ("edge_share", 0.0, False, 1.0, False),
    ("view_min_range_m", 0.0, False, math.inf, True),
    ("view_max_range_m", 0.0, True, math.inf, True),
    ("view_half_fov_deg", 0.0, True, 180.0, False),
)

#: ``(field, least)`` of the options that count something.
_OPTION_COUNTS = (("max_iterations", 1), ("iterations_per_scale", 1),
                  ("max_search_observations", 1), ("max_search_cells", 1), ("max_search_work", 1),
                  ("max_refine_work", 1),
                  ("candidates", 1),
                  ("extra_candidates", 0), ("coarse_pool", 0), ("heading_restarts", 0),
                  ("max_hypotheses", 1), ("min_inliers", 1),
                  ("fallback_min_inliers", 1), ("max_observations", 1))


def _check_range(name: str, v, lo: float, lo_open: bool, hi: float, hi_open: bool) -> None:
    ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and not math.isnan(v)
    if ok:
        ok = (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ok:
        span = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise LocalizationInputError(f"options.{name}: must be a number in {span}, got {v!r}")

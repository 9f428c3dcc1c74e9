"""Localize a vehicle against a lane-marking map (pure numerics: numpy, scipy, numba, pyproj).

A vehicle's camera sees lane-marking centroids ahead of it (vehicle frame: x
forward, y left, metres; each with a weight γ, the pixel count of its
cluster). Given a map of marking centroids in a projected metric CRS and a
coarse GPS prior, :func:`localize` returns the vehicle's pose.

Methods
-------
``pink2008``
    The matching of O. Pink, *Visual map matching and localization using a
    global feature map* (2008), section 4: nearest-neighbour pairing within a
    maximum distance, iteratively reweighted least squares with the mixed
    l1/l2 weight ``γ / max(d, ε)`` and a closed-form weighted 2D rigid fit,
    iterated from the GPS prior until the pose stops moving. Local: it
    converges to the nearest optimum.
``default``
    0. Each observation weighs its pixel count relative to the frame's median
       (capped at 1.5), shared with the observations within about 1.5 m
       (``Options.crowd_radius_m``): a preceding vehicle's clusters or a
       marking split in several are one piece of evidence, not several.
    1. A global correlative search over heading × translation covering ±3σ of
       the prior (radius clamped to 3-45 m): per heading, the observations are
       correlated with a likelihood raster of the map around the prior (per
       observation, the log-likelihood ratio of "marking" versus "clutter";
       built per request from the KD-tree neighbourhood, so no global field is
       precomputed), the GPS prior is added as a Gaussian log-density, and the
       best local maxima of the volume become candidates. The prior's position
       term is isotropic (``Prior.position_sigma_m``) or an error ellipse
       (``Prior.position_ellipse``); the search covers ±3σ of its major axis. The best 100 of them
       (``Options.coarse_pool``) are first charged their negative evidence
       (step 3's missed markings): the correlation rewards clutter's matches
       too and knows nothing of markings a pose puts in view unseen.
    2. Each candidate is refined by IRLS with a Geman-McClure kernel whose
       scale is annealed from 0.8 m to 0.15 m (observation noise grows with
       range², so each observation's kernel is widened by its own noise); a
       fine-only run from the same start guards against clutter dragging the
       coarse scales off. Pieces of solid lines (given ``bearing_deg`` and
       ``length_m``) are matched point-to-segment: a camera clusters a solid
       line at its own phase. At the last scale each step is Gauss-Newton with
       the camera's anisotropic noise: a residual along the viewing ray counts
       with the range noise, across it with the far smaller bearing noise
       (``Options.bearing_noise_rad``).
    3. Refined candidates are scored by a likelihood: per observation the
       log-likelihood ratio of matched versus clutter (with the same
       anisotropic kernel; a match on a segment counts less; the outlier
       density grows with the frame's clutter), and
       *negative evidence*: every place where the map says the camera should
       report a centroid (a point-like marking, or a point every 3 m along a
       solid line, precomputed per map) that the pose puts inside the camera's
       view (4-25 m, ±30° by default; ``Options.view_*``) with no observation
       near it (on a solid line: none on the line within a clustering period
       along it either) costs ``log(1/p_miss)``. A pose one dash period off explains the
       observed dashes as well, but near the end of a dashed line, a stop line
       or a change of line type it predicts markings nobody saw. Scores may
       be divided by a temperature (``Options.temperature``, 1: the shared
       weights of step 0 already keep correlated clusters from counting
       twice) and the GPS prior is added; poses matching fewer than
       ``min_inliers`` (3) observations do
       not compete while any pose matches that many (else poses matching
       ``fallback_min_inliers``, 2, compete), and a "none of these"
       hypothesis (all clutter) takes its share.
       The posterior probabilities decide ``ok`` versus ``ambiguous``
       (repeating 9 m dashes, parallel lanes 3.5 m apart): ``ok`` needs 95 %;
       the answer carries its own (``Pose.probability``). Where the camera
       sees past the map's edge from the answer, or from a pose within the
       prior's reach along the road, no answer is ``ok`` (``Options.edge_share``):
       a pose a dash period away matches the markings the map lacks. The
       edge is that of the index's extent: its markings' convex hull, or
       with ``MapIndex.from_arrays(..., extent="markings")`` the ground
       between them (a route, parts of a city). When the best of
       the first 20 candidates holds less than 99.9 %, the next 20 coarse
       optima are refined and scored too (``Options.extra_candidates``): a
       truth crowded out of the first ones, or a rival that makes a
       confident answer ambiguous. The best four coarse optima more than
       3 m from the best pose are refined again at its heading where theirs
       is more than 1.5° off (``Options.heading_restarts``): the coarse
       grid's headings lie degrees apart, and the truth's optimum one step
       turned can settle at a wrong heading while a pose one dash period
       along wins. Then the best pose is refined again from
       a few starts beside it (1.5 m and 0.75 m along, 0.75 m across, 2°
       turned; ``Options.neighbour_starts``): the coarse grid can hand over
       a candidate that settles in the basin next to the truth's, and a
       neighbouring optimum found this way wins or competes.
    4. The chosen pose is refined jointly with the camera's pitch error (a
       tilted ground plane stretches all ranges together, which a rigid fit
       would absorb by sliding along the road; ``Options.estimate_pitch``).
       The covariance of (easting, northing, yaw) averages the model-based and
       sandwich estimates of the weighted fit, adds the propagated effect of
       the pitch's remaining uncertainty, and lets the prior's information
       fill directions the map leaves open (along a solid line).
    5. Fewer than 2 observations within 0.75 m (or 3σ) of the map → ``failed``
       (``pink2008``: fewer than 3).

    Over a drive, :func:`localize_sequence` (``localizer/track.py``) follows
    every hypothesis through consecutive frames with the vehicle's odometry (a
    multi-hypothesis filter, the paper's future work): rivals one dash period
    apart stop explaining the camera's view as the road changes. A drive can
    be streamed a few frames at a time: each call returns a
    :class:`TrackState` that the next one continues from.

    Temperature, weight cap and thresholds were calibrated with
    ``benchmarks/localize_calibrate.py``; figures in ``benchmarks/RESULTS-localizer.md``.

Conventions
-----------
* Map coordinates: easting/northing in the map CRS (metres).
* ``heading_deg``: degrees clockwise from **true** north. The map grid's north
  differs by the meridian convergence ``c`` (pyproj):
  ``true_bearing = grid_bearing + c`` (about -0.43° at Karlsruhe in UTM 32N).
* ``yaw_enu_rad``: REP-103 yaw, radians counter-clockwise from true east.
* ``Pose.transformation``: 3x3 homogeneous matrix mapping vehicle coordinates
  to map CRS coordinates (grid yaw).
* Covariance: (easting m, northing m, yaw rad), map CRS axes.

Example
-------
>>> index = MapIndex.from_arrays(x, y, weight, "EPSG:25832")      # once per map
>>> pose = localize(index, obs, Prior(lat=49.0, lon=8.4, heading_deg=90.0))
>>> pose.to_dict()["status"]
'ok'
"""

from .core import METHODS, localize, parse_observations, warm_up
from .errors import LocalizationInputError
from .frames import GeoFrame, bearing_to_yaw, shared_frame, wrap_angle, yaw_to_bearing
from .index import EXTENT_RULES, MapExtent, MapIndex
from .track import (
    Frame,
    SequenceResult,
    TrackOptions,
    TrackState,
    carry_prior,
    iter_sequence,
    localize_sequence,
)
from .types import ErrorEllipse, Hypothesis, Options, Pose, Prior

__all__ = [
    "EXTENT_RULES",
    "METHODS",
    "ErrorEllipse",
    "GeoFrame",
    "shared_frame",
    "Hypothesis",
    "LocalizationInputError",
    "MapExtent",
    "MapIndex",
    "Options",
    "Frame",
    "Pose",
    "Prior",
    "SequenceResult",
    "TrackOptions",
    "TrackState",
    "bearing_to_yaw",
    "carry_prior",
    "localize",
    "iter_sequence",
    "localize_sequence",
    "parse_observations",
    "warm_up",
    "wrap_angle",
    "yaw_to_bearing",
]

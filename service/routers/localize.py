"""``POST /collections/{mapId}/localize`` and ``POST /localize``: a vehicle's pose from the markings its camera sees."""

from __future__ import annotations

import functools
import logging
import math
import time
from typing import Literal

import anyio
import numpy as np
from fastapi import APIRouter, Depends
from fastapi import Path as PathParam
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from localizer import Options

from .. import metrics, request_id
from ..deps import Context, get_ctx, require_read
from ..index_cache import IndexedMap, IndexPending
from ..map_index import MIN_PROBABILITY_RANGE, coverage_feature, localize_options
from ..problems import Problem

log = logging.getLogger(__name__)

router = APIRouter(tags=["Localization"], dependencies=[Depends(require_read)])

#: Largest |x|, |y| of an observation, metres (a camera sees tens of metres).
MAX_RANGE_M = 1000.0
#: Localizations computed at once per server process. They are CPU-bound Python:
#: more threads only share the GIL, and starve the event loop that parses
#: requests and sends answers (measured: answers took seconds at 64 clients).
#: Cores are used by running several server processes (``--workers``).
LOCALIZE_THREADS = 1

_DEFAULTS = Options()
_DEFAULT_OK = _DEFAULTS.ambiguity_probability
_MIN_PROBABILITY = Field(
    None, ge=MIN_PROBABILITY_RANGE[0], le=MIN_PROBABILITY_RANGE[1],
    description="Posterior probability the answer needs to be ok (default method); below it the answer is "
                "ambiguous with its hypotheses. Default: the localizer's (see PoseOut.probability). Higher: "
                "fewer ok answers and fewer of them wrong. An answer whose camera sees beyond the map's edge "
                "stays ambiguous at any threshold (see PoseOut.reason).")  # fmt: skip


#: The examples /docs offers: docs/examples/frame.json and the first two frames
#: of docs/examples/drive.json, which answer ok on the demo map (a test keeps them so).
_EXAMPLE_GPS = {"lat": 49.0051049, "lon": 8.4152842, "heading_deg": 102.87, "position_sigma_m": 3.0,
                "heading_sigma_deg": 8.0}
_EXAMPLE_FRAME = [
    {"x": 22.679, "y": 4.6, "weight": 23.0}, {"x": 21.946, "y": -2.618, "weight": 26.0},
    {"x": 23.712, "y": 0.182, "weight": 21.0}, {"x": 20.993, "y": 6.636, "weight": 29.0},
    {"x": 23.478, "y": -5.065, "weight": 18.0}, {"x": 17.028, "y": 9.653, "weight": 41.0},
    {"x": 12.963, "y": -5.572, "weight": 53.0}, {"x": 10.183, "y": -3.485, "weight": 28.0},
    {"x": 21.089, "y": 3.591, "weight": 19.0}, {"x": 6.8, "y": 3.7, "weight": 51.0},
    {"x": 22.387, "y": 9.052, "weight": 26.0}, {"x": 14.938, "y": -8.253, "weight": 31.0},
    {"x": 12.081, "y": 5.616, "weight": 57.0}, {"x": 20.886, "y": 0.495, "weight": 27.0},
    {"x": 12.123, "y": 2.595, "weight": 43.0},
]


class EllipseIn(BaseModel):
    """A one-sigma position error ellipse, as a GNSS receiver reports it (NMEA GST)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    sigma_major_m: float = Field(..., ge=0.01, le=1000, description="Sigma along the major axis, metres")
    sigma_minor_m: float = Field(..., ge=0.01, le=1000, description="Sigma along the minor axis, metres")
    orientation_deg: float = Field(..., ge=-360, le=720,
                                   description="Direction of the major axis, degrees clockwise from true north")

    @model_validator(mode="after")
    def _minor_not_above_major(self):
        if self.sigma_minor_m > self.sigma_major_m:
            raise ValueError("sigma_minor_m must not exceed sigma_major_m")
        return self


class GpsIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    lat: float = Field(..., ge=-90, le=90, description="WGS84 latitude, degrees")
    lon: float = Field(..., ge=-180, le=180, description="WGS84 longitude, degrees")
    heading_deg: float = Field(..., ge=-360, le=720, description="Degrees clockwise from true north")
    position_sigma_m: float | None = Field(None, ge=0.01, le=1000, description="Per-axis position sigma, metres")
    position_ellipse: EllipseIn | None = Field(
        None, description="The fix's error ellipse instead of `position_sigma_m` (not both)")
    heading_sigma_deg: float | None = Field(None, ge=0.01, le=180, description="Heading sigma, degrees")

    @model_validator(mode="after")
    def _one_position_sigma(self):
        if self.position_sigma_m is not None and self.position_ellipse is not None:
            raise ValueError("send position_sigma_m or position_ellipse, not both")
        return self


class ObservationIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    x: float = Field(..., ge=-MAX_RANGE_M, le=MAX_RANGE_M, description="Forward, metres")
    y: float = Field(..., ge=-MAX_RANGE_M, le=MAX_RANGE_M, description="Left, metres")
    weight: float = Field(1.0, gt=0, le=1e9, description="Pixel count of the marking's cluster")


class LocalizeIn(BaseModel):
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "example": {"gps": _EXAMPLE_GPS, "observations": _EXAMPLE_FRAME, "method": "default"}
        },
    )  # fmt: skip
    gps: GpsIn
    observations: list[ObservationIn] = Field(..., max_length=10_000)
    method: Literal["default", "pink2008"] = "default"
    min_probability: float | None = _MIN_PROBABILITY


class MotionIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    dx: float = Field(..., ge=-100, le=100, description="Metres forward since the previous frame (vehicle frame)")
    dy: float = Field(..., ge=-100, le=100, description="Metres to the left since the previous frame")
    dyaw_deg: float = Field(0.0, ge=-180, le=180,
                            description="Turn since the previous frame, degrees counter-clockwise (left positive)")


class FrameIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    observations: list[ObservationIn] = Field(..., max_length=10_000)
    motion: MotionIn | None = Field(
        None, description="Odometry from the previous frame (with `state`: from the previous answer's last "
                          "frame); required but for a drive's first frame")


class DriveTrack(BaseModel):
    """One hypothesis a drive's filter follows (map CRS, grid yaw)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    easting: float = Field(..., description="Metres in the map's CRS")
    northing: float = Field(..., description="Metres in the map's CRS")
    yaw_grid_rad: float = Field(..., description="Radians counter-clockwise from the CRS's +x axis")
    sigma_m: float = Field(..., gt=0, le=1000, description="Position sigma, metres")
    sigma_yaw_rad: float = Field(..., gt=0, le=math.pi, description="Heading sigma, radians")
    log_weight: float = Field(..., description="Unnormalised log posterior of the hypothesis")
    matched: bool = Field(..., description="Whether any frame matched along it")
    established: bool = Field(False, description="Whether the drive was sure of it once with no map edge within "
                                                 "the GPS fix's reach (false in older states)")


class DriveGps(BaseModel):
    """The drive's GPS fix carried along by the odometry (map CRS, grid yaw)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    easting: float
    northing: float
    yaw_grid_rad: float
    sigma_m: float = Field(..., gt=0, le=1000, description="Major axis of the position's error ellipse, metres")
    sigma_yaw_rad: float = Field(..., gt=0, le=math.pi)
    covariance: list[list[float]] | None = Field(
        None, min_length=3, max_length=3,
        description="3x3 covariance of (easting, northing, yaw_grid_rad): the fix's uncertainty grows across the "
                    "road as the odometry carries its heading error along (absent in older states)")


class DriveFrame(BaseModel):
    """One of a drive's last frames, kept to score a newly found pose on them (map-independent)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    observations: list[list[float]] = Field(..., max_length=10_000,
                                            description="`[x, y, weight]` per observation, as sent")
    motion: list[float] = Field(..., min_length=3, max_length=3,
                                description="Odometry into that frame: metres forward, metres left, radians")
    weight: float = Field(..., ge=0, le=1, description="Share of that frame's evidence a track gained "
                                                        "(0: the vehicle stood still)")
    first: bool = Field(..., description="Whether it was the drive's first frame")


class DriveState(BaseModel):
    """Where a drive's filter stands after its last frame (``SequenceOut.state``): send it back unchanged."""

    model_config = ConfigDict(extra="forbid")
    crs: str = Field(..., min_length=1, max_length=200, description="The map CRS of the poses")
    frames: int = Field(..., ge=1, le=2**53, description="Frames the drive has had so far")
    tracks: list[DriveTrack] = Field(..., max_length=64,
                                     description="The hypotheses followed, most probable first")
    gps: DriveGps = Field(..., description="The GPS fix carried along by the odometry")
    history: list[DriveFrame] | None = Field(
        None, max_length=50, description="The drive's last frames (absent in older states)")
    shift: float = Field(0.0, ge=0, allow_inf_nan=False,
                         description="Log weight the lead cap has taken off every track so far")
    map: str | None = Field(None, max_length=64,
                            description="The map the drive is localized on, when `POST /localize/sequence` "
                                        "picked it: the drive goes on there")


class SequenceIn(BaseModel):
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "example": {
                "gps": _EXAMPLE_GPS,
                "frames": [
                    {"observations": _EXAMPLE_FRAME},
                    {"observations": [
                        {"x": 19.702, "y": 1.059, "weight": 32.0}, {"x": 18.939, "y": -1.992, "weight": 26.0},
                        {"x": 21.999, "y": -2.596, "weight": 39.0}, {"x": 14.356, "y": 0.028, "weight": 282.0},
                        {"x": 16.511, "y": -0.343, "weight": 164.0}, {"x": 21.089, "y": -3.779, "weight": 37.0},
                        {"x": 10.952, "y": 4.104, "weight": 52.0}, {"x": 21.623, "y": 6.165, "weight": 33.0},
                        {"x": 15.439, "y": -0.307, "weight": 183.0}, {"x": 21.653, "y": 1.833, "weight": 27.0},
                        {"x": 10.843, "y": 1.188, "weight": 46.0}, {"x": 19.672, "y": 3.874, "weight": 20.0},
                        {"x": 20.981, "y": -0.966, "weight": 139.0},
                    ], "motion": {"dx": 1.499, "dy": 0.015, "dyaw_deg": 7.308}},
                ],
            }
        },
    )  # fmt: skip
    gps: GpsIn | None = Field(None, description="GPS fix at the first frame; required unless `state` is sent "
                                                 "(then a newer fix, optional)")
    frames: list[FrameIn] = Field(..., min_length=1, max_length=50, description="Consecutive frames, oldest first")
    state: DriveState | None = Field(
        None, description="The `state` of the drive's previous answer: continue the drive (the first "
                          "frame's `motion` is then the odometry since the previous answer's last frame). "
                          "The poses are those one request with all the frames would have given.")
    min_probability: float | None = _MIN_PROBABILITY


class HypothesisOffset(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x_m: float = Field(..., description="Metres ahead of the answer (its vehicle frame, ISO 8855: x forward)")
    y_m: float = Field(..., description="Metres to the answer's left (y left)")
    heading_deg: float = Field(..., ge=-180, lt=180,
                               description="This hypothesis's heading minus the answer's, degrees clockwise")


class HypothesisOut(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lat: float = Field(..., description="WGS84 latitude, degrees")
    lon: float = Field(..., description="WGS84 longitude, degrees")
    heading_deg: float = Field(..., description="Degrees clockwise from true north")
    easting: float = Field(..., description="Metres in the map's CRS")
    northing: float = Field(..., description="Metres in the map's CRS")
    score: float = Field(..., ge=0, le=1, description="Posterior probability of this hypothesis")
    covariance: list[list[float | None]] | None = Field(
        None, description="3x3 covariance of (easting m, northing m, yaw rad) of this hypothesis, were it right")
    offset: HypothesisOffset | None = Field(
        None, description="Where this hypothesis lies seen from the answer (the first hypothesis: at zero). "
                          "Rivals only ahead and behind are repeating markings along the road, the lateral "
                          "position and heading sure; a y of a lane's width is a parallel lane")


class PoseOut(BaseModel):
    """A localization answer (the pose fields are null when ``failed``)."""

    # Closed, so that a field the localizer adds without documenting it here
    # fails the schema test instead of going unnoticed.
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "example": {
                "status": "ok", "lat": 49.0051096, "lon": 8.4152576, "heading_deg": 107.846,
                "easting": 457234.940, "northing": 5428188.496, "crs": "EPSG:25832", "yaw_enu_rad": -0.31147,
                "covariance": [[0.01205, -0.00213, 0.0000866], [-0.00213, 0.00833, -0.000505],
                               [0.0000866, -0.000505, 0.0000330]],
                "mixture_covariance": None, "iterations": 6, "inliers": 8, "rms_m": 0.089, "probability": 0.99992,
                "hypotheses": [],
            }
        },
    )  # fmt: skip
    status: Literal["ok", "ambiguous", "failed"] = Field(
        ..., description="ambiguous: several poses explain the observations (see hypotheses); failed: see reason")
    crs: str = Field(..., description="The map's storage CRS")
    lat: float | None = Field(None, description="WGS84 latitude, degrees (the best hypothesis when ambiguous)")
    lon: float | None = Field(None, description="WGS84 longitude, degrees")
    heading_deg: float | None = Field(None, description="Degrees clockwise from true north")
    easting: float | None = Field(None, description="Metres in the map's CRS")
    northing: float | None = Field(None, description="Metres in the map's CRS")
    yaw_enu_rad: float | None = Field(None, description="REP-103 yaw: radians counter-clockwise from true east")
    covariance: list[list[float | None]] | None = Field(
        None, description="3x3 covariance of (easting m, northing m, yaw rad) of the pose as the optimum it is "
                          "(when ambiguous: were the best hypothesis right)")
    mixture_covariance: list[list[float | None]] | None = Field(
        None, description="When ambiguous: 3x3 expected outer product of the pose's error over the listed "
                          "hypotheses, sum p_i (C_i + d_i d_i^T) with p_i their scores rescaled to sum to one, "
                          "C_i their covariances, d_i their offsets from the pose; null otherwise")
    iterations: int | None = Field(None, description="Refinement iterations of the answer")
    inliers: int | None = Field(None, description="Observations matched to the map")
    rms_m: float | None = Field(None, description="RMS distance of the matched observations, metres")
    probability: float | None = Field(
        None, ge=0, le=1,
        description="Posterior probability that the answer is right (default method; ok needs the "
                    f"request's min_probability, by default {_DEFAULT_OK}; null for pink2008 and failed)")  # fmt: skip
    hypotheses: list[HypothesisOut] = Field(..., description="Best first; filled when ambiguous")
    reason: str | None = Field(None, description="Why the localization failed; that a drive's frame "
                                                  "matched nothing and the pose is the odometry's prediction; or "
                                                  "why a pose the posterior holds sure is ambiguous: the camera "
                                                  "sees beyond the map's edge")
    map: str | None = Field(None, description="The map the pose was found on: only in the answers of "
                                              "`POST /localize`, which picks the map by the GPS fix")


class SequenceOut(BaseModel):
    model_config = ConfigDict(extra="forbid")
    poses: list[PoseOut] = Field(..., description="The answer at every frame, from the frames up to it")
    tracks: int = Field(..., ge=0, description="Hypotheses still followed after the last frame")
    state: DriveState | None = Field(
        None, description="Send it with the next frames to continue the drive; null when the frames could "
                          "not be localized")
    map: str | None = Field(None, description="The map the drive was localized on: only in the answers of "
                                              "`POST /localize/sequence`, which picks it by the first GPS fix")


#: The answer's header naming the revision of the map it was localized against.
REVISION_HEADER = "X-Map-Revision"
#: How the OpenAPI document describes it on the localization answers.
_REVISION_DOC = {REVISION_HEADER: {
    "description": "The revision of the map the answer was localized against: while the index of a large "
                   "map's newest revision is built, its previous one answers (LANEMAP_INDEX_BACKGROUND_FROM)",
    "schema": {"type": "string", "pattern": "^[0-9]+$"}}}


#: How often a request waits for its map's index to be built before it is refused: more
#: than once only while the map is deleted and made anew meanwhile.
_INDEX_TRIES = 3


async def _on_index(ctx: Context, fn, map_id: str, *args):
    """``fn(indexed, t0, t1, *args)`` on the localization thread, with the map's index to answer
    from (:class:`~service.index_cache.IndexedMap`) and when looking it up began and ended.

    Where the map has no index yet (or its coverage changed) the build is awaited
    here, off the localization thread, so that other maps' requests go on meanwhile;
    the wait counts as looking up the index.
    """
    waited, accept_stale = 0.0, False
    for _ in range(_INDEX_TRIES):
        try:
            return await _turn(ctx, _with_index, ctx, fn, map_id, accept_stale, waited, *args)
        except IndexPending as pending:
            t = time.perf_counter()
            await pending.wait()
            waited += time.perf_counter() - t
            accept_stale = True
    raise Problem(503, f"map {map_id!r} changed while its index was built; retry shortly", "busy",
                  headers={"Retry-After": "1"})  # fmt: skip


def _with_index(ctx: Context, fn, map_id: str, accept_stale: bool, waited: float, *args):
    t0 = time.perf_counter()
    indexed, stale = ctx.indexes.lookup(map_id, accept_stale)
    if stale:
        metrics.stale_localizations.labels(map_id).inc()
    return fn(indexed, t0 - waited, time.perf_counter(), *args)


@router.get("/collections/{mapId}/coverage", summary="The ground the map speaks for, as localization draws it",
            responses={200: {"content": {"application/geo+json": {}},
                             "description": "A GeoJSON Feature in WGS84: where the map holds every marking painted, "
                                            "by its coverage; past it an answer whose camera sees there is held "
                                            "back (its geometry null for a map without area)"}})
async def map_coverage(mapId: str = PathParam(..., max_length=64), ctx: Context = Depends(get_ctx)):
    return await anyio.to_thread.run_sync(_coverage, ctx, mapId)


def _coverage(ctx: Context, map_id: str) -> JSONResponse:
    have, _ = ctx.indexes.get(map_id)
    return JSONResponse(coverage_feature(have.index, map_id, have.coverage, have.revision),
                        media_type="application/geo+json", headers={REVISION_HEADER: str(have.revision)})


@router.post("/collections/{mapId}/localize", summary="Localize a vehicle against the map",
             responses={200: {"model": PoseOut, "description": "The pose, or why there is none",
                              "headers": _REVISION_DOC}})
async def localize_vehicle(
    body: LocalizeIn,
    mapId: str = PathParam(..., max_length=64),
    ctx: Context = Depends(get_ctx),
):
    _check_frame(ctx, body)
    return await _admit(ctx, _run_frame, mapId, body)


@router.post("/localize", summary="Localize a vehicle against the map where its GPS fix is",
             responses={200: {"model": PoseOut, "description": "The pose, and the map it was found on",
                              "headers": _REVISION_DOC},
                        404: {"description": "No map has markings near the GPS fix"}})  # fmt: skip
async def localize_anywhere(body: LocalizeIn, ctx: Context = Depends(get_ctx)):
    """As `POST /collections/{mapId}/localize`, on the map with the most markings the localizer
    uses (accepted and unreviewed) within the fix's reach: three of its position sigmas (the
    ellipse's major one, 5 m by default) plus 30 m of camera view; of maps with as many, the
    first by id. A fleet whose vehicles cross
    from one map to the next need not know the maps' ids: the answer's `map` names the one used."""
    _check_frame(ctx, body)
    map_id = await anyio.to_thread.run_sync(_map_at, ctx, body.gps)
    return await _admit(ctx, functools.partial(_run_frame, name_map=True), map_id, body)


#: Camera view added to a fix's reach when a map is picked by it, metres.
_VIEW_REACH_M = 30.0


def _map_at(ctx: Context, g: "GpsIn") -> str:
    """The id of the map with the most markings within a GPS fix's reach (see ``localize_anywhere``)."""
    prior = _prior(g)
    sigma = prior.position_sigma_m if prior.position_ellipse is None else prior.position_ellipse.sigma_major_m
    reach = 3.0 * sigma + _VIEW_REACH_M
    near = _maps_near(ctx, g.lon, g.lat, reach)
    if not near:
        raise Problem(404, f"no map has markings within {reach:.0f} m of the GPS fix ({g.lat:.6f}, {g.lon:.6f})",
                      "no-map-here")  # fmt: skip
    return near[0][1]


def _maps_near(ctx: Context, lon: float, lat: float, reach: float,
               unless_only: str | None = None) -> list[tuple[int, str, str]]:  # fmt: skip
    """``(markings, map id, CRS)`` of every map with markings the localizer uses (accepted and
    unreviewed) within ``reach`` metres (a square) of lon/lat: the most first, ties by id.

    With ``unless_only``, an empty list without counting when that map's extent is the only one
    the square touches.
    """
    from mapbuilder.crs import from_wgs84

    touched = []
    for map_id, crs, bounds in ctx.store.map_extents():
        if crs is None or bounds is None:
            continue
        x, y = from_wgs84(crs).transform(lon, lat)
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if x < bounds[0] - reach or x > bounds[2] + reach or y < bounds[1] - reach or y > bounds[3] + reach:
            continue
        touched.append((map_id, crs, x, y))
    if unless_only is not None and [t[0] for t in touched] == [unless_only]:
        return []
    found = []
    for map_id, crs, x, y in touched:
        n = ctx.store.count_bbox(map_id, x - reach, y - reach, x + reach, y + reach, statuses=("accepted", "unreviewed"))
        if n:
            found.append((n, map_id, crs))
    found.sort(key=lambda t: -t[0])  # stable: maps_extents lists them by id
    return found


#: The centre of the localizer's default camera view ahead of the vehicle, and the half side of a
#: square around it that holds the view (4-25 m ahead within ±30°), metres.
_VIEW_AHEAD_M = 0.5 * (_DEFAULTS.view_min_range_m + _DEFAULTS.view_max_range_m)
_VIEW_HALF_M = max(0.5 * (_DEFAULTS.view_max_range_m - _DEFAULTS.view_min_range_m),
                   _DEFAULTS.view_max_range_m * math.sin(math.radians(_DEFAULTS.view_half_fov_deg)))

#: A drive moves to another map once that map has this many times the markings of its own
#: where the camera looks: maps that overlap do not take a drive back and forth.
HANDOVER_RATIO = 1.5


def _drive_map(ctx: Context, state: "DriveState") -> tuple[str, "DriveState"]:
    """The map a drive streamed through ``POST /localize/sequence`` goes on on, and its state there.

    A drive stays on its map while that map has markings where the camera looks
    (the view ahead of the most probable track, or of the carried GPS fix while
    no track is followed, widened by three of its sigmas). When another map has
    :data:`HANDOVER_RATIO` times as many there (or the drive's map is gone), the
    drive is handed to it: its state is moved into that map's CRS
    (:meth:`localizer.TrackState.to_crs`) and its hypotheses go on there.
    """
    from localizer import TrackState, shared_frame

    if state.tracks:
        t = state.tracks[0]
        e, n, yaw, sigma = t.easting, t.northing, t.yaw_grid_rad, t.sigma_m
    else:
        g = state.gps
        e, n, yaw, sigma = g.easting, g.northing, g.yaw_grid_rad, g.sigma_m
    lon, lat = shared_frame(state.crs).to_lonlat(e + _VIEW_AHEAD_M * math.cos(yaw), n + _VIEW_AHEAD_M * math.sin(yaw))
    if not (math.isfinite(lon) and math.isfinite(lat)):
        raise Problem(422, f"state: its pose lies outside the domain of {state.crs}", "invalid-localization-input")
    near = _maps_near(ctx, lon, lat, _VIEW_HALF_M + 3.0 * sigma, unless_only=state.map)
    own = next((count for count, map_id, _ in near if map_id == state.map), 0)
    rival = next((m for m in near if m[1] != state.map), None)
    if rival is None or (own and rival[0] < HANDOVER_RATIO * own):
        return state.map, state
    n_rival, map_id, crs = rival
    moved = TrackState.from_dict(state.model_dump(exclude={"map"})).to_crs(crs)
    log.info("drive handed from map %s (%d markings in view) to map %s (%d)", state.map, own, map_id, n_rival)
    metrics.drive_handovers.labels(state.map, map_id).inc()
    return map_id, DriveState(**moved.to_dict(), map=map_id)


@router.post("/collections/{mapId}/localize/sequence", summary="Localize a vehicle over a drive of frames",
             responses={200: {"model": SequenceOut, "description": "The pose at every frame",
                              "headers": _REVISION_DOC}})
async def localize_drive(
    body: SequenceIn,
    mapId: str = PathParam(..., max_length=64),
    ctx: Context = Depends(get_ctx),
):
    """The pose at every frame of a drive, following every hypothesis with the odometry.

    A single frame on a straight road with repeating dashes is often
    ``ambiguous``; over a drive the rivals stop explaining what the camera sees.
    A drive can be streamed: send the answer's ``state`` back with the next
    frames, and the poses are those of one request with all the frames. One
    request carries at most ``LANEMAP_MAX_DRIVE_OBSERVATIONS`` observations
    over all its frames (5,000 by default); a longer drive is streamed.
    """
    _check_drive(ctx, body)
    if body.state is not None and body.state.map is not None and body.state.map != mapId:
        raise Problem(409, f"state: the drive is localized on map {body.state.map!r}, not {mapId!r}; send it "
                      "to POST /localize/sequence, or start the drive anew", "state-of-another-map")  # fmt: skip
    return await _admit(ctx, _run_drive, mapId, body)


@router.post("/localize/sequence", summary="Localize a vehicle over a drive, on the map where its GPS fix is",
             responses={200: {"model": SequenceOut, "description": "The pose at every frame, and the map",
                              "headers": _REVISION_DOC},
                        404: {"description": "No map has markings near the GPS fix, or the state's map is gone "
                                               "and none has markings where the drive is"}})  # fmt: skip
async def localize_drive_anywhere(body: SequenceIn, ctx: Context = Depends(get_ctx)):
    """As `POST /collections/{mapId}/localize/sequence`, on the map that `POST /localize` would pick
    for the drive's first GPS fix. The answer's `map` and its `state` name it; a drive streamed with
    that state goes on there until another map has 1.5 times its markings where the camera looks
    next (or its map is deleted): the drive is then handed to that map, its state moved into that
    map's CRS, and the answer names it."""
    _check_drive(ctx, body)
    if body.state is not None:
        if body.state.map is None:
            raise Problem(422, "state.map: this state comes from a map's own drive endpoint; continue it there",
                          "missing-map")  # fmt: skip
        map_id, state = await anyio.to_thread.run_sync(_drive_map, ctx, body.state)
        if state is not body.state:
            body = body.model_copy(update={"state": state})
    else:
        map_id = await anyio.to_thread.run_sync(_map_at, ctx, body.gps)
    return await _admit(ctx, functools.partial(_run_drive, name_map=True), map_id, body)


def _check_drive(ctx: Context, body: SequenceIn) -> None:
    """What a drive's request must hold beyond its schema."""
    for k, f in enumerate(body.frames):
        _check_count(ctx, len(f.observations), f"frames[{k}].observations")
        if (k or body.state is not None) and f.motion is None:
            raise Problem(422, f"frames[{k}].motion: the odometry since the previous frame is required",
                          "missing-motion")  # fmt: skip
    total, cap = sum(len(f.observations) for f in body.frames), ctx.settings.max_drive_observations
    if total > cap:
        raise Problem(422, f"frames: {total} observations over {len(body.frames)} frames, at most {cap} accepted "
                      "per drive request; send the drive in smaller pieces with its state", "too-many-observations")
    if body.gps is None and body.state is None:
        raise Problem(422, "gps: a GPS fix is needed to start a drive (or the previous answer's state to "
                      "continue one)", "missing-gps")  # fmt: skip


def _check_frame(ctx: Context, body: LocalizeIn) -> None:
    """What a single frame's request must hold beyond its schema."""
    _check_count(ctx, len(body.observations), "observations")
    if body.min_probability is not None and body.method != "default":
        raise Problem(422, "min_probability: the pink2008 method has no posterior probability",
                      "min-probability-needs-default-method")  # fmt: skip


def _check_count(ctx: Context, n: int, field: str) -> None:
    limit = ctx.settings.max_observations
    if n > limit:
        raise Problem(422, f"{field}: {n} given, at most {limit} accepted", "too-many-observations")


async def _admit(ctx: Context, run, map_id: str, body):
    """Run a localization on the localization thread, or shed it when too many are pending."""
    # Admission runs on the event loop, so it counts the requests still waiting
    # for a worker thread as well as the running ones.
    cap = ctx.settings.localize_max_pending
    if cap and ctx.localize_pending >= cap:
        metrics.shed.inc()
        raise Problem(503, f"the server is busy: {ctx.localize_pending} localizations are pending; "
                      "retry shortly", "busy", headers={"Retry-After": "1"})  # fmt: skip
    if ctx.localize_limiter is None:
        ctx.localize_limiter = anyio.CapacityLimiter(LOCALIZE_THREADS)
    ctx.localize_pending += 1
    try:
        return await run(ctx, map_id, body, time.perf_counter())
    finally:
        ctx.localize_pending -= 1


def _turn(ctx: Context, fn, *args):
    """``fn(*args)`` on the localization thread, after the requests already waiting for it."""
    return anyio.to_thread.run_sync(fn, *args, limiter=ctx.localize_limiter)


async def _run_frame(ctx: Context, map_id: str, body: LocalizeIn, admitted: float,
                     name_map: bool = False) -> JSONResponse:  # fmt: skip
    return await _on_index(ctx, _localize, map_id, map_id, body, admitted, name_map)


def _localize(indexed: IndexedMap, t0: float, t1: float, map_id: str, body: LocalizeIn, admitted: float,
              name_map: bool = False) -> JSONResponse:  # fmt: skip
    """The CPU-bound part of a localization, run in a worker thread."""
    from localizer import localize

    index, revision = indexed.index, indexed.revision
    obs = _observations(body.observations)
    pose, failure = None, None
    try:
        pose = localize(index, obs, _prior(body.gps), method=body.method,
                        options=localize_options(body.min_probability))  # fmt: skip
    except (ArithmeticError, np.linalg.LinAlgError) as exc:
        log.warning("localization on %s failed numerically: %r", map_id, exc)
        failure = {"status": "failed", "crs": index.crs, "hypotheses": [],
                   "reason": f"numerical failure ({exc.__class__.__name__})"}  # fmt: skip
    _count(map_id, "frame", body.method, [pose.status if pose else "failed"], time.perf_counter() - t1)
    headers = {**_server_timing(admitted, t0, t1), REVISION_HEADER: str(revision)}
    answer = failure or _pose_json(pose)
    if name_map:
        answer["map"] = map_id
    return JSONResponse(answer, headers=headers)


async def _run_drive(ctx: Context, map_id: str, body: SequenceIn, admitted: float,
                     name_map: bool = False) -> JSONResponse:  # fmt: skip
    """A drive a frame per turn at the localization thread.

    The frames of a drive could hold the thread for seconds (50 of them, or
    ten of 500 observations that nothing explains); in turns, the single
    frames that arrive meanwhile wait for one of its frames, not for all of
    them. The poses are those of one call (the filter goes on from where the
    last turn left it).
    """
    (index, revision, steps), t0, t1 = await _on_index(ctx, _drive_steps, map_id, body)
    frames = body.frames
    busy = 0.0
    try:
        while True:
            done, dt = await _turn(ctx, _advance, steps, map_id if name_map else None)
            busy += dt
            if done is not None:
                statuses, answer = done
                break
    except (ArithmeticError, np.linalg.LinAlgError) as exc:
        log.warning("drive localization on %s failed numerically: %r", map_id, exc)
        failed = {"status": "failed", "crs": index.crs, "hypotheses": [],
                  "reason": f"numerical failure ({exc.__class__.__name__})"}  # fmt: skip
        statuses = ["failed"] * len(frames)
        answer = JSONResponse({"poses": [failed] * len(frames), "tracks": 0, "state": None,
                               **({"map": map_id} if name_map else {})})  # fmt: skip
    _count(map_id, "drive", "default", statuses, busy)
    answer.headers.update({**_server_timing(admitted, t0, t1, busy), REVISION_HEADER: str(revision)})
    return answer


def _drive_steps(indexed: IndexedMap, t0: float, t1: float, body: SequenceIn):
    """The map's index and revision, and the drive's frames as a generator of their poses
    (:func:`localizer.iter_sequence`); ``t0`` and ``t1``."""
    from localizer import Frame, TrackState, iter_sequence

    index, revision = indexed.index, indexed.revision
    frames = [
        Frame(_observations(f.observations),
              (0.0, 0.0, 0.0) if f.motion is None else (f.motion.dx, f.motion.dy, math.radians(f.motion.dyaw_deg)))
        for f in body.frames
    ]  # fmt: skip
    state = TrackState.from_dict(body.state.model_dump(exclude={"map"})) if body.state is not None else None
    steps = iter_sequence(index, frames, _prior(body.gps) if body.gps is not None else None,
                          options=localize_options(body.min_probability), state=state)
    return (index, revision, steps), t0, t1


def _advance(steps, map_id: str | None = None) -> tuple[tuple[list[str], JSONResponse] | None, float]:
    """One frame of a drive and the seconds it took: ``None`` while frames are left, then the
    poses' statuses and the answer (rendered here, off the event loop; naming ``map_id``, in
    the answer and its state, when given)."""
    t = time.perf_counter()
    try:
        next(steps)
    except StopIteration as end:
        dt = time.perf_counter() - t
        result = end.value
        out = {"poses": [_pose_json(p) for p in result.poses], "tracks": result.tracks,
               "state": result.state.to_dict()}
        if map_id is not None:
            out["map"] = out["state"]["map"] = map_id
        return ([p.status for p in result.poses], JSONResponse(out)), dt
    return None, time.perf_counter() - t


def _count(map_id: str, endpoint: str, method: str, statuses: list[str], seconds: float) -> None:
    """Count a request's answers by map and status, and the ``seconds`` its localizer took."""
    metrics.localizer_seconds.labels(endpoint).observe(seconds)
    token = request_id.client()
    for status in statuses:
        metrics.localizations.labels(map_id, endpoint, method, status, token).inc()


def _prior(g: GpsIn):
    from localizer import ErrorEllipse, Prior

    kw = {"lat": g.lat, "lon": g.lon, "heading_deg": g.heading_deg % 360.0}
    if g.position_sigma_m is not None:
        kw["position_sigma_m"] = g.position_sigma_m
    if g.position_ellipse is not None:
        e = g.position_ellipse
        kw["position_ellipse"] = ErrorEllipse(e.sigma_major_m, e.sigma_minor_m, e.orientation_deg % 360.0)
    if g.heading_sigma_deg is not None:
        kw["heading_sigma_deg"] = g.heading_sigma_deg
    return Prior(**kw)


def _observations(items: list[ObservationIn]) -> np.ndarray:
    return np.array([[o.x, o.y, o.weight] for o in items], dtype=float).reshape(-1, 3)


def _pose_json(pose) -> dict:
    out = pose.to_dict()
    if out.get("reason") is None:
        out.pop("reason", None)
    for k, v in out.items():
        if isinstance(v, float) and not math.isfinite(v):
            out[k] = None
    return out


def _server_timing(admitted: float, t0: float, t1: float, busy: float | None = None) -> dict[str, str]:
    """``Server-Timing`` (W3C), milliseconds: waiting for a worker thread, the map index, the localizer.

    Load tests and operators read from it how much of a request the
    localization itself takes, apart from HTTP, JSON and queueing. A drive's
    localizer time is ``busy``, its frames' own; its waits between them count
    as queueing.
    """
    t2 = time.perf_counter()
    localize = t2 - t1 if busy is None else busy
    queue = (t0 - admitted) + (t2 - t1 - localize)
    return {"Server-Timing": f"queue;dur={queue * 1e3:.2f}, index;dur={(t1 - t0) * 1e3:.2f}, "
                             f"localize;dur={localize * 1e3:.2f}"}  # fmt: skip

"""Camera scenes simulated on real map geometry, for tests and benchmarks.

Everything here takes arrays (marking centroids, solid-line polylines, curb
polylines, lanelet centrelines); loading a Lanelet2 map happens in the tests
and benchmarks. All randomness comes from the ``numpy.random.Generator``
passed in, so scenes are reproducible from a seed.

The camera model is a forward camera over a flat ground plane:

* it sees the ground ``min_range_m``–``max_range_m`` ahead within ±``half_fov_deg``;
* a small pitch error per frame stretches or shrinks all ranges (the range of a
  ground point at depression angle α is ``h / tan α``), and each centroid gets
  range noise growing with range² and a small bearing noise;
* dashes and stop lines are seen as their map centroids; a solid line is
  clustered at the camera's own phase, so its observed centroids lie anywhere
  along the line;
* markings are missed with some probability;
* outliers as in the paper: curb edges, a preceding vehicle (edges above the
  ground project far away, with many edge pixels) and random clutter;
* weights γ mimic edge-pixel counts: the image extent of a marking falls with
  range (lateral extent ∝ 1/r, longitudinal extent ∝ h/r²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .geometry import apply, weighted_rigid_fit


@dataclass(frozen=True)
class SceneMap:
    """Map geometry the simulator draws from (all in one metric CRS, metres).

    Attributes
    ----------
    marking_xy : (M, 2) ndarray
        Centroids of the map's point-like markings (dashes, stop lines).
    marking_kind : (M,) ndarray of str
        ``dash`` or ``stop_line`` (decides the image shape of the marking).
    solid_lines : list of (K, 2) ndarray
        Solid-line polylines; the camera clusters them at its own phase.
    curbs : list of (K, 2) ndarray
        Curb polylines: edges the camera mistakes for markings.
    centerlines : list of (K, 2) ndarray
        Lanelet centrelines, in driving direction, for vehicle poses.
    """

    marking_xy: np.ndarray
    marking_kind: np.ndarray
    solid_lines: list = field(default_factory=list)
    curbs: list = field(default_factory=list)
    centerlines: list = field(default_factory=list)


@dataclass(frozen=True)
class Camera:
    """Flat-ground forward camera (see the module docstring)."""

    min_range_m: float = 4.0
    max_range_m: float = 25.0
    half_fov_deg: float = 30.0
    height_m: float = 1.3
    focal_px: float = 800.0
    pitch_sigma_deg: float = 0.03
    range_noise_m: float = 0.03
    range_noise_coeff: float = 3e-4
    bearing_noise_rad: float = 0.002
    miss_probability: float = 0.1
    solid_piece_m: float = 3.0


@dataclass(frozen=True)
class Clutter:
    """Outlier levels. ``Clutter()`` is paper-like; :data:`HEAVY` is worse."""

    curb_probability: float = 0.25
    vehicle_probability: float = 0.3
    vehicle_clusters: tuple[int, int] = (3, 7)
    clutter_mean: float = 1.5


HEAVY = Clutter(curb_probability=0.6, vehicle_probability=0.8, vehicle_clusters=(5, 12),
                clutter_mean=6.0)
NONE = Clutter(curb_probability=0.0, vehicle_probability=0.0, clutter_mean=0.0)


@dataclass
class Scene:
    """One simulated camera frame.

    Attributes
    ----------
    pose : (x, y, yaw)
        True vehicle pose in the map CRS (grid yaw, radians).
    observations : (N, 3) ndarray
        Observed centroids (x forward, y left, metres) and weights γ.
    true_xy : (N, 2) ndarray
        True map position of each inlier observation; NaN for outliers.
    label : (N,) ndarray of str
        ``dash``, ``stop_line``, ``solid``, ``curb``, ``vehicle``, ``clutter``.
    true_dir : (N, 2) ndarray
        Unit direction of the line under a solid-line observation; zeros otherwise.
    """

    pose: tuple[float, float, float]
    observations: np.ndarray
    true_xy: np.ndarray
    label: np.ndarray
    true_dir: np.ndarray | None = None

    @property
    def inlier(self) -> np.ndarray:
        return np.isfinite(self.true_xy[:, 0])


def _to_vehicle(pose, pts: np.ndarray) -> np.ndarray:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    d = pts - np.array([x, y])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def _in_view(v: np.ndarray, cam: Camera) -> np.ndarray:
    r = np.hypot(v[:, 0], v[:, 1])
    b = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    return (r >= cam.min_range_m) & (r <= cam.max_range_m) & (np.abs(b) <= cam.half_fov_deg)


def _pieces(line: np.ndarray, piece: float, phase: float, with_direction: bool = False):
    """Centroids of consecutive pieces of ``line`` starting at arc length ``phase``.

    With ``with_direction`` also the unit tangent of the line at each centroid.
    """
    seg = np.hypot(*np.diff(line, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    starts = np.arange(phase, s[-1] - 0.5, piece)
    if starts.size == 0:
        return (np.zeros((0, 2)), np.zeros((0, 2))) if with_direction else np.zeros((0, 2))
    mids = np.minimum(starts + piece / 2, (starts + np.minimum(starts + piece, s[-1])) / 2)
    c = np.column_stack([np.interp(mids, s, line[:, 0]), np.interp(mids, s, line[:, 1])])
    if not with_direction:
        return c
    k = np.clip(np.searchsorted(s, mids) - 1, 0, len(seg) - 1)
    d = np.diff(line, axis=0)[k] / np.maximum(seg[k], 1e-12)[:, None]
    return c, d


def _gamma(r: np.ndarray, lateral_m, longitudinal_m, cam: Camera, rng) -> np.ndarray:
    px = 2.0 * cam.focal_px * (lateral_m / r + cam.height_m * longitudinal_m / r**2)
    return np.maximum(np.rint(px * rng.lognormal(0.0, 0.25, r.size)), 3.0)


def visible_markings(scene_map: SceneMap, pose, cam: Camera = Camera()) -> int:
    """Number of point-like map markings whose centroid the camera would see at ``pose``."""
    if len(scene_map.marking_xy) == 0:
        return 0
    return int(_in_view(_to_vehicle(pose, scene_map.marking_xy), cam).sum())


def _distance_to_polyline(line: np.ndarray, p) -> float:
    a = line[:-1]
    d = line[1:] - a
    t = np.clip(np.einsum("nd,nd->n", np.asarray(p) - a, d) / np.maximum(np.einsum("nd,nd->n", d, d), 1e-12), 0, 1)
    return float(np.min(np.hypot(*(a + t[:, None] * d - np.asarray(p)).T)))


def _local_lines(lines, pose, reach: float):
    return [ln for ln in lines if len(ln) >= 2 and _distance_to_polyline(ln, pose[:2]) <= reach]


def simulate_scene(
    scene_map: SceneMap,
    pose,
    rng: np.random.Generator,
    camera: Camera = Camera(),
    clutter: Clutter = Clutter(),
) -> Scene:
    """Simulate what the camera sees at ``pose`` = (x, y, grid yaw).

    Returns
    -------
    Scene
        Observations in random order with their ground truth.
    """
    cam = camera
    pose = tuple(float(v) for v in pose)
    obs_true: list[np.ndarray] = []  # vehicle-frame true positions
    world: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    shapes: list[np.ndarray] = []  # (lateral, longitudinal) extent in metres
    dirs: list[np.ndarray] = []  # line direction of solid pieces (zeros otherwise)

    if len(scene_map.marking_xy):
        v = _to_vehicle(pose, scene_map.marking_xy)
        m = _in_view(v, cam) & (rng.random(len(v)) >= cam.miss_probability)
        kinds = np.asarray(scene_map.marking_kind)[m]
        obs_true.append(v[m])
        world.append(scene_map.marking_xy[m])
        dirs.append(np.zeros((int(m.sum()), 2)))
        labels.append(kinds.astype(object))
        shp = np.where((kinds == "stop_line")[:, None], [3.0, 0.5], [0.15, 3.0])
        shapes.append(np.asarray(shp, float).reshape(-1, 2))
    reach = cam.max_range_m + 50.0
    for line in _local_lines(scene_map.solid_lines, pose, reach):
        c, u = _pieces(line, cam.solid_piece_m, rng.uniform(0, cam.solid_piece_m), True)
        if not len(c):
            continue
        v = _to_vehicle(pose, c)
        m = _in_view(v, cam) & (rng.random(len(v)) >= cam.miss_probability)
        obs_true.append(v[m])
        world.append(c[m])
        dirs.append(u[m])
        labels.append(np.full(m.sum(), "solid", object))
        shapes.append(np.tile([0.15, cam.solid_piece_m], (m.sum(), 1)))

    # Outliers: true positions are NaN in world coordinates.
    for line in _local_lines(scene_map.curbs, pose, reach):
        c = _pieces(line, rng.uniform(2.0, 4.0), rng.uniform(0, 2.0))
        if not len(c):
            continue
        v = _to_vehicle(pose, c)
        m = _in_view(v, cam) & (rng.random(len(v)) < clutter.curb_probability)
        v = v[m] + rng.normal(0, 0.1, (m.sum(), 2))
        obs_true.append(v)
        world.append(np.full((len(v), 2), np.nan))
        dirs.append(np.zeros((len(v), 2)))
        labels.append(np.full(len(v), "curb", object))
        shapes.append(np.tile([0.2, 2.0], (len(v), 1)))
    if rng.random() < clutter.vehicle_probability:
        k = int(rng.integers(clutter.vehicle_clusters[0], clutter.vehicle_clusters[1] + 1))
        dist = rng.uniform(7.0, 20.0)
        y0 = rng.normal(0.0, 0.4)
        z = rng.uniform(0.0, 0.9 * cam.height_m, k)  # edge heights above the ground
        stretch = cam.height_m / (cam.height_m - z)
        v = np.column_stack(
            [(dist + rng.uniform(0, 0.5, k)) * stretch, (y0 + rng.uniform(-0.9, 0.9, k)) * stretch]
        )
        v = v[_in_view(v, cam)]
        obs_true.append(v)
        world.append(np.full((len(v), 2), np.nan))
        dirs.append(np.zeros((len(v), 2)))
        labels.append(np.full(len(v), "vehicle", object))
        shapes.append(np.tile([1.5, 0.3], (len(v), 1)))
    nc = int(rng.poisson(clutter.clutter_mean))
    if nc:
        r = np.sqrt(rng.uniform(cam.min_range_m**2, cam.max_range_m**2, nc))
        b = np.radians(rng.uniform(-cam.half_fov_deg, cam.half_fov_deg, nc))
        obs_true.append(np.column_stack([r * np.cos(b), r * np.sin(b)]))
        world.append(np.full((nc, 2), np.nan))
        dirs.append(np.zeros((nc, 2)))
        labels.append(np.full(nc, "clutter", object))
        shapes.append(np.tile([0.3, 0.5], (nc, 1)) * rng.uniform(0.5, 2.0, (nc, 1)))

    if obs_true:
        v = np.concatenate(obs_true)
        w = np.concatenate(world)
        lab = np.concatenate(labels)
        shp = np.concatenate(shapes)
        tdir = np.concatenate(dirs)
    else:
        v, w, lab, shp = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, object), np.zeros((0, 2))
        tdir = np.zeros((0, 2))

    # Camera measurement: pitch bias (shared), range and bearing noise (per centroid).
    r = np.hypot(v[:, 0], v[:, 1])
    b = np.arctan2(v[:, 1], v[:, 0])
    dpitch = math.radians(rng.normal(0.0, cam.pitch_sigma_deg))
    alpha = np.arctan2(cam.height_m, np.maximum(r, 1e-6))
    r_meas = cam.height_m / np.tan(np.maximum(alpha + dpitch, 1e-3))
    r_meas = r_meas + rng.normal(0.0, 1.0, r.size) * (cam.range_noise_m + cam.range_noise_coeff * r**2)
    b_meas = b + rng.normal(0.0, cam.bearing_noise_rad, r.size)
    ob = np.column_stack([r_meas * np.cos(b_meas), r_meas * np.sin(b_meas)])
    gamma = _gamma(np.maximum(r, 1.0), shp[:, 0], shp[:, 1], cam, rng)
    order = rng.permutation(len(ob))
    return Scene(
        pose=pose,
        observations=np.column_stack([ob, gamma])[order],
        true_xy=w[order],
        label=lab[order],
        true_dir=tdir[order],
    )


def _centrelines(scene_map: SceneMap) -> tuple[list[np.ndarray], np.ndarray]:
    """The map's centrelines of two points or more, and their lengths (m)."""
    lines = [c for c in scene_map.centerlines if len(c) >= 2]
    if not lines:
        raise ValueError("scene_map has no centrelines")
    return lines, np.array([np.sum(np.hypot(*np.diff(c, axis=0).T)) for c in lines])


def sample_poses(
    scene_map: SceneMap,
    n: int,
    rng: np.random.Generator,
    camera: Camera = Camera(),
    min_visible: int = 0,
    lateral_sigma_m: float = 0.2,
    heading_sigma_deg: float = 2.0,
    max_tries: int = 100_000,
) -> np.ndarray:
    """Vehicle poses along lanelet centrelines, ``(n, 3)`` of (x, y, grid yaw).

    A pose is kept when at least ``min_visible`` point-like map markings are in view.
    """
    lines, lengths = _centrelines(scene_map)
    p = lengths / lengths.sum()
    out = []
    for _ in range(max_tries):
        c = lines[int(rng.choice(len(lines), p=p))]
        k = int(rng.integers(0, len(c) - 1))
        a = rng.random()
        pt = c[k] + a * (c[k + 1] - c[k])
        d = c[k + 1] - c[k]
        yaw = math.atan2(d[1], d[0]) + math.radians(rng.normal(0, heading_sigma_deg))
        lat = rng.normal(0, lateral_sigma_m)
        pose = (pt[0] - lat * math.sin(yaw), pt[1] + lat * math.cos(yaw), yaw)
        if visible_markings(scene_map, pose, camera) >= min_visible:
            out.append(pose)
            if len(out) == n:
                break
    return np.array(out, float).reshape(-1, 3)


def _drive(lines: list[np.ndarray], starts: np.ndarray, li: int, s0: float, length: float) -> np.ndarray | None:
    """Polyline of ``length`` metres from arc length ``s0`` of centreline ``li``, continuing into
    the centreline that starts where one ends (within 0.5 m, turning less than 30°); None at a dead end."""
    pts, line, s = [], lines[li], s0
    left = length
    while True:
        seg = np.hypot(*np.diff(line, axis=0).T)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        stop = min(cum[-1], s + left)
        inner = line[(cum > s) & (cum < stop)]
        at = [np.array([np.interp(v, cum, line[:, 0]), np.interp(v, cum, line[:, 1])]) for v in (s, stop)]
        pts.extend([at[0], *inner, at[1]])
        left -= stop - s
        if left <= 1e-6:
            return np.array(pts)
        end_dir = line[-1] - line[-2]
        near = np.flatnonzero(np.hypot(*(starts - line[-1]).T) < 0.5)
        nxt = [k for k in near if len(lines[k]) >= 2 and abs(math.remainder(
            math.atan2(*(lines[k][1] - lines[k][0])[::-1]) - math.atan2(end_dir[1], end_dir[0]), 2 * math.pi))
            < math.radians(30)]
        if not nxt:
            return None
        line, s = lines[nxt[0]], 0.0


def sample_trajectories(
    scene_map: SceneMap,
    n: int,
    frames: int,
    step_m: float,
    rng: np.random.Generator,
    camera: Camera = Camera(),
    min_visible: int = 0,
    max_tries: int = 100_000,
) -> np.ndarray:
    """Drives along lanelet centrelines: ``(n, frames, 3)`` poses (x, y, grid yaw), ``step_m`` apart.

    A drive follows one centreline into the next where one ends; it is kept when
    the first frame sees at least ``min_visible`` point-like map markings.
    """
    lines, lengths = _centrelines(scene_map)
    starts = np.array([c[0] for c in lines])
    p = lengths / lengths.sum()
    length = step_m * (frames - 1)
    out = []
    for _ in range(max_tries):
        li = int(rng.choice(len(lines), p=p))
        path = _drive(lines, starts, li, float(rng.uniform(0, lengths[li])), length + 0.5)
        if path is None:
            continue
        seg = np.hypot(*np.diff(path, axis=0).T)
        keep = seg > 1e-9
        path = np.vstack([path[:1], path[1:][keep]])
        cum = np.concatenate([[0.0], np.cumsum(seg[keep])])
        at = np.arange(frames) * step_m
        x, y = np.interp(at, cum, path[:, 0]), np.interp(at, cum, path[:, 1])
        ahead = np.minimum(at + 0.5, cum[-1])
        yaw = np.arctan2(np.interp(ahead, cum, path[:, 1]) - y, np.interp(ahead, cum, path[:, 0]) - x)
        poses = np.column_stack([x, y, yaw])
        if visible_markings(scene_map, poses[0], camera) >= min_visible:
            out.append(poses)
            if len(out) == n:
                break
    return np.array(out, float).reshape(-1, frames, 3)


def odometry(a, b) -> tuple[float, float, float]:
    """Motion from pose ``a`` to pose ``b`` in ``a``'s vehicle frame: (forward m, left m, dyaw rad)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (float(c * dx + s * dy), float(-s * dx + c * dy), math.remainder(float(b[2] - a[2]), 2 * math.pi))


def oracle_pose(
    scene: Scene, sigma_m: np.ndarray | None = None, line_aware: bool = True
) -> tuple[float, float, float] | None:
    """Weighted least squares on the true inliers with their true positions (noise floor).

    ``sigma_m`` (N,) is the per-observation noise; weights are ``1 / sigma²``.
    With ``line_aware`` an observation of a solid line constrains only the
    distance across the line: where along the line a camera's cluster of it
    lies is arbitrary, so its along-line position carries no information (the
    simulator draws it at random, and no method can know it). Returns None with
    fewer than two inliers.
    """
    m = scene.inlier
    if m.sum() < 2:
        return None
    obs = scene.observations[m, :2]
    tgt = scene.true_xy[m] - np.asarray(scene.pose[:2])
    w = np.ones(m.sum()) if sigma_m is None else 1.0 / np.asarray(sigma_m)[m] ** 2
    theta, t = weighted_rigid_fit(obs, tgt, w)
    pose = np.array([t[0], t[1], theta])
    if line_aware and scene.true_dir is not None and np.any(scene.true_dir[m]):
        u = scene.true_dir[m]
        normal = np.column_stack([-u[:, 1], u[:, 0]])
        line = np.any(u != 0, axis=1)
        for _ in range(10):  # Gauss-Newton; point rows for points, normal rows for lines
            c, s = math.cos(pose[2]), math.sin(pose[2])
            q = np.column_stack([c * obs[:, 0] - s * obs[:, 1], s * obs[:, 0] + c * obs[:, 1]])
            r = q + pose[:2] - tgt
            H = np.zeros((3, 3))
            g = np.zeros(3)
            for j in range(len(obs)):
                J = np.array([[1.0, 0.0, -q[j, 1]], [0.0, 1.0, q[j, 0]]])
                rj = r[j]
                if line[j]:
                    J = normal[j][None] @ J
                    rj = np.array([normal[j] @ r[j]])
                H += w[j] * J.T @ J
                g += w[j] * J.T @ rj
            try:
                step = np.linalg.solve(H, -g)
            except np.linalg.LinAlgError:
                break
            pose += step
            if np.abs(step).max() < 1e-9:
                break
    return (float(pose[0] + scene.pose[0]), float(pose[1] + scene.pose[1]), float(pose[2]))


def perturb(pose, distance_m: float, heading_deg: float, rng: np.random.Generator):
    """``pose`` moved by ``distance_m`` in a random direction and turned by ``heading_deg``."""
    a = rng.uniform(0, 2 * math.pi)
    return (
        pose[0] + distance_m * math.cos(a),
        pose[1] + distance_m * math.sin(a),
        pose[2] + math.radians(heading_deg),
    )


def transform_points(pose, pts: np.ndarray) -> np.ndarray:
    """Vehicle-frame points to map coordinates (re-exported for convenience)."""
    return apply(pose, pts)

"""Behaviour of localizer.localize: recovery, ambiguity, failure, covariance, inputs."""

from __future__ import annotations

import json
import math
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from localizer import ErrorEllipse, Hypothesis, LocalizationInputError, MapIndex, Options, Pose, Prior, localize
from localizer.geometry import LocalMap, apply, weighted_rigid_fit
from localizer.pink2008 import pink2008_icp
from localizer.robust import crowd_weights
from localizer.simulate import NONE, Camera, Clutter, SceneMap, perturb, sample_poses, simulate_scene

from ._localizer_helpers import karlsruhe

CRS = "EPSG:25832"
ORIGIN = np.array([458000.0, 5428000.0])  # Karlsruhe, UTM 32N
EXACT = Camera(pitch_sigma_deg=0.0, range_noise_m=0.0, range_noise_coeff=0.0,
               bearing_noise_rad=0.0, miss_probability=0.0)


def random_map(rng, n=4000, half=120.0):
    """Markings scattered without pattern around ORIGIN: one unambiguous optimum."""
    xy = ORIGIN + rng.uniform(-half, half, (n, 2))
    return xy, rng.uniform(20, 200, n)


def prior_at(index, pose, sigma_m=5.0, sigma_deg=10.0) -> Prior:
    lon, lat = index.frame.to_lonlat(pose[0], pose[1])
    heading = float(index.frame.grid_yaw_to_heading(pose[2], lon, lat))
    return Prior(lat=lat, lon=lon, heading_deg=heading, position_sigma_m=sigma_m,
                 heading_sigma_deg=sigma_deg)


def errors(result, pose):
    e = math.hypot(result.easting - pose[0], result.northing - pose[1])
    h = abs(math.degrees((result.yaw_grid_rad - pose[2] + math.pi) % (2 * math.pi) - math.pi))
    return e, h


def benchmark_scene(name: str):
    """A benchmark frame kept in ``tests/data``: the Karlsruhe index, true pose, prior, observations, labels."""
    data = json.loads((Path(__file__).parent / "data" / name).read_text())
    index, _ = karlsruhe()
    assert index.crs == data["crs"]
    return index, data["true_pose"], Prior(**data["prior"]), np.array(data["observations"]), data.get("labels", [])


def observe(xy, pose, cam=EXACT, rng=None, clutter=NONE):
    smap = SceneMap(marking_xy=xy, marking_kind=np.full(len(xy), "dash", object))
    return simulate_scene(smap, pose, rng or np.random.default_rng(0), cam, clutter)


# ---------------------------------------------------------------- numerics


def _closest_reference(local: LocalMap, p: np.ndarray, max_dist: float):
    """LocalMap.closest spelled out: of the three nearest centroids closer than
    ``max_dist`` plus the longest half length, the nearest point or segment."""
    from scipy.spatial import cKDTree

    tree = cKDTree(local.xy)
    d0, ii = tree.query(p, k=3, distance_upper_bound=max_dist + local.max_half)
    dist = np.full(len(p), np.inf)
    target = np.zeros((len(p), 2))
    which = np.full(len(p), -1)
    for r in range(len(p)):
        for d_c, i in zip(d0[r], ii[r]):
            if not np.isfinite(d_c):
                continue
            u, h = local.axis[i], local.half[i]
            a = float(np.clip((p[r] - local.xy[i]) @ u, -h, h))
            q = local.xy[i] + a * u
            d = float(np.hypot(*(p[r] - q)))
            if d < dist[r]:
                dist[r], target[r], which[r] = d, q, i
    far = dist > max_dist
    dist[far], which[far] = np.inf, -1
    return dist, target, which


def _karlsruhe_scenes(seed: int, n: int):
    """``(true pose, scene, its neighbourhood)`` of ``n`` simulated Karlsruhe frames with paper-like clutter."""
    index, smap = karlsruhe()
    rng = np.random.default_rng(seed)
    for pose in sample_poses(smap, n, rng, Camera(), min_visible=4):
        yield pose, simulate_scene(smap, pose, rng, Camera(), Clutter()), LocalMap(index, pose[:2], 60.0)


def test_nearest_marking_queries_match_the_plain_definition():
    index, _ = karlsruhe()
    rng = np.random.default_rng(3)
    for k in range(5):
        local = LocalMap(index, index.xy[rng.integers(len(index))], 45.0)
        assert local.max_half > 0
        p = np.concatenate([local.xy[rng.integers(len(local), size=150)] + rng.normal(0, 1.0, (150, 2)),
                            rng.uniform(-50, 50, (50, 2))])  # fmt: skip
        for max_dist in (0.5, 2.4, 4.0):
            d, tgt, normal, which = local.closest(p, max_dist, return_index=True)
            rd, rtgt, rwhich = _closest_reference(local, p, max_dist)
            ok = np.isfinite(rd)
            assert np.array_equal(np.isfinite(d), ok)
            assert np.allclose(d[ok], rd[ok], atol=1e-9) and np.allclose(tgt[ok], rtgt[ok], atol=1e-9)
            assert np.array_equal(which, rwhich)
            seg = local.half[np.maximum(which, 0)] > 0
            # unit normals across matched segments, none for points
            assert np.allclose(np.hypot(*normal[ok & seg].T), 1.0)
            assert not normal[ok & ~seg].any() and not normal[~ok].any()


def test_nearest_marking_queries_on_tiny_and_point_only_maps():
    """The bucket grid's edges: one or two markings, points far outside the grid, no segments."""
    rng = np.random.default_rng(5)
    for n, bearing in [(1, 90.0), (2, 30.0), (2, None), (7, None)]:
        xy = rng.uniform(-3, 3, (n, 2)) + ORIGIN
        extra = {} if bearing is None else dict(bearing_deg=np.full(n, bearing), length_m=np.full(n, 3.0),
                                                 kind=np.full(n, "solid"))
        index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], np.ones(n), "EPSG:25832", **extra)
        local = LocalMap(index, ORIGIN, 20.0)
        assert len(local) == n and (local.max_half > 0) == (bearing is not None)
        p = np.concatenate([rng.uniform(-6, 6, (100, 2)), rng.uniform(-400, 400, (20, 2))])
        for max_dist in (0.3, 2.0, 300.0):
            d, tgt, _, which = local.closest(p, max_dist, return_index=True)
            rd, rtgt, rwhich = _closest_reference(local, p, max_dist)
            ok = np.isfinite(rd)
            assert np.array_equal(np.isfinite(d), ok) and np.array_equal(which, rwhich)
            assert np.allclose(d[ok], rd[ok], atol=1e-9) and np.allclose(tgt[ok], rtgt[ok], atol=1e-9)
    # Points no cell holds (NaN, absurdly far) match nothing.
    d, _, _, which = local.closest(np.array([[np.nan, 0.0], [1e15, -1e15]]), 10.0, return_index=True)
    assert np.isinf(d).all() and (which == -1).all()
    empty = LocalMap(MapIndex.from_arrays([0.0], [0.0], [1.0], "EPSG:25832"), ORIGIN, 5.0)
    d, _, _, which = empty.closest(np.zeros((3, 2)), 10.0, return_index=True)
    assert len(empty) == 0 and np.isinf(d).all() and (which == -1).all()


def test_a_batch_refines_each_pose_as_alone():
    """robust_refine's poses do not interact: refined together or one by one, the same answers."""
    from localizer.robust import noise_sigma, robust_refine

    pose, scene, local = next(_karlsruhe_scenes(11, 1))
    rng = np.random.default_rng(11)
    obs = scene.observations[:, :2]
    o = Options()
    # Coarse-to-fine from up to a metre off, fine-only (from the third scale) from a few centimetres.
    starts = [(dx, dy, pose[2] + dyaw) for dx, dy, dyaw in rng.normal(0, [0.7, 0.7, 0.03], (3, 3))]
    starts += [(dx, dy, pose[2] + dyaw) for dx, dy, dyaw in rng.normal(0, [0.05, 0.05, 0.003], (3, 3))]
    together = robust_refine(local, obs, scene.observations[:, 2] / 50, noise_sigma(obs, o), starts, o,
                             start_scale=[0, 0, 0, 2, 2, 2], record=True)
    for k, s in enumerate(starts):
        alone = robust_refine(local, obs, scene.observations[:, 2] / 50, noise_sigma(obs, o), [s], o,
                              start_scale=[[0, 0, 0, 2, 2, 2][k]], record=True)[0]
        assert alone.pose == together[k].pose and alone.iterations == together[k].iterations
        if k == 0:
            assert alone.trace == together[0].trace and len(alone.trace) == alone.iterations + 1
    # Each pose moved (none was left as it started).
    assert all(r.iterations > 0 for r in together), [r.iterations for r in together]


def _missed_reference(local: LocalMap, obs: np.ndarray, pose, o: Options, view):
    """missed_counts spelled out for one pose: expected centroids in the shrunk view
    that no observation explains within explain_distance_m, nor (on a solid line)
    one of the four nearest within solid_explain_along_m, lying along the line."""
    from scipy.spatial import cKDTree

    rmin, rmax = view[0] + o.view_margin_m, view[1] - o.view_margin_m
    half = view[2] - math.radians(o.view_margin_deg)
    v = (local.expect_xy - np.asarray(pose[:2])) @ np.array([[math.cos(pose[2]), -math.sin(pose[2])],
                                                             [math.sin(pose[2]), math.cos(pose[2])]])
    tree = cKDTree(obs)
    points = lines = 0
    for e, (vx, vy) in enumerate(v):
        r = math.hypot(vx, vy)
        if not (rmin <= r <= rmax and vx > 0 and abs(vy) <= math.tan(half) * vx):
            continue
        if tree.query((vx, vy), distance_upper_bound=o.explain_distance_m)[0] < math.inf:
            continue
        if not local.expect_solid[e]:
            points += 1
            continue
        ax = local.expect_axis[e]
        u = np.array([math.cos(pose[2]) * ax[0] + math.sin(pose[2]) * ax[1],
                      -math.sin(pose[2]) * ax[0] + math.cos(pose[2]) * ax[1]])  # fmt: skip
        d, i = tree.query((vx, vy), k=min(4, len(obs)), distance_upper_bound=o.solid_explain_along_m)
        near = [obs[j] - (vx, vy) for dj, j in zip(np.atleast_1d(d), np.atleast_1d(i)) if dj < math.inf]
        if not any(abs(w @ u) <= o.solid_explain_along_m and abs(w[1] * u[0] - w[0] * u[1])
                   <= o.solid_explain_across_m for w in near):  # fmt: skip
            lines += 1
    return points, lines


def test_negative_evidence_counts_match_the_plain_definition():
    from localizer.robust import missed_counts, view_of

    rng = np.random.default_rng(8)
    o = Options()
    seen_points = seen_lines = 0
    for pose, scene, local in _karlsruhe_scenes(8, 12):
        obs = scene.observations[:, :2]
        view = view_of(obs, o)
        jitter = rng.normal(0, [3.0, 3.0, 0.2], (5, 3)) + [0, 0, pose[2]]
        poses = [(0.0, 0.0, pose[2])] + [tuple(t) for t in jitter]
        pts, lines = missed_counts(local, obs, poses, o, view)
        for k, q in enumerate(poses):
            assert (pts[k], lines[k]) == _missed_reference(local, obs, q, o, view)
        seen_points += pts.sum()
        seen_lines += lines.sum()
    assert seen_points > 20 and seen_lines > 20  # both kinds of misses were counted


def test_positive_evidence_matches_the_plain_definition():
    """data_scores less its negative evidence: per observation w log(1 + k / outlier density), k the
    anisotropic Gaussian of the residual to the closest marking, discounted on segments."""
    from localizer.robust import SCORE_FLOOR_M, bearing_sigma, data_scores, miss_costs, noise_sigma, view_of

    rng = np.random.default_rng(9)
    for bearing_noise in (Options().bearing_noise_rad, None):
        o = Options(bearing_noise_rad=bearing_noise)
        for pose, scene, local in _karlsruhe_scenes(9, 6):
            obs, w = scene.observations[:, :2], scene.observations[:, 2] / 40.0
            sig = noise_sigma(obs, o)
            view = view_of(obs, o)
            jitter = rng.normal(0, [0.3, 0.3, 0.01], (3, 3)) + [0, 0, pose[2]]
            poses = [(0.0, 0.0, pose[2])] + [tuple(t) for t in jitter]
            got = data_scores(local, obs, w, sig, poses, o, view) + miss_costs(local, obs, poses, o, view)
            s = np.sqrt(SCORE_FLOOR_M**2 + sig**2)
            st = np.sqrt(SCORE_FLOOR_M**2 + bearing_sigma(obs, o) ** 2) if bearing_noise is not None else s
            for q, g in zip(poses, got):
                p = apply(q, obs)
                d, tgt, _, which = local.closest(p, 4.0 * s.max(), return_index=True)
                want = 0.0
                for j in np.flatnonzero(np.isfinite(d)):
                    b = q[2] + math.atan2(obs[j, 1], obs[j, 0])
                    ray, across = np.array([math.cos(b), math.sin(b)]), np.array([-math.sin(b), math.cos(b)])
                    e = p[j] - tgt[j]
                    k = math.exp(-0.5 * ((e @ ray / s[j]) ** 2 + (e @ across / st[j]) ** 2))
                    if local.half[which[j]] > 0:
                        k *= min(1.0, math.sqrt(2 * math.pi) * s[j] / (2 * local.half[which[j]]))
                    want += w[j] * math.log1p(k / o.outlier_density)
                assert g == pytest.approx(want, rel=1e-9, abs=1e-9) and want > 0


def test_fit_sums_match_the_jacobian_rows_spelled_out():
    """fit_statistics' compiled sums: H, G, B, chi² and dof from the Jacobian rows of each pair
    (x and y rows for a point, the normal's row for a segment), as numpy matrix products."""
    from localizer.robust import _fit_sums, noise_sigma, pitch_lever

    o = Options()
    n_seg = n_pt = 0
    for pose, scene, local in _karlsruhe_scenes(12, 8):
        obs, w_obs = scene.observations[:, :2], scene.observations[:, 2] / 40.0
        sig = noise_sigma(obs, o)
        q_pose = (0.05, -0.03, pose[2] + 0.002)
        gate = np.maximum(o.inlier_distance_m, 3.0 * sig)
        p = apply(q_pose, obs)
        d, tgt, normal = local.closest(p, float(gate.max()))
        m = np.isfinite(d) & (d <= gate)
        q = apply((0.0, 0.0, q_pose[2]), obs)[m]
        r, w, nv = p[m] - tgt[m], w_obs[m] / sig[m] ** 2, normal[m]
        rng_j = np.hypot(obs[m, 0], obs[m, 1])
        shift = q / rng_j[:, None] * pitch_lever(rng_j, o)[:, None]
        seg = nv.any(axis=1)
        jx = np.column_stack([np.ones(m.sum()), np.zeros(m.sum()), -q[:, 1]])
        jy = np.column_stack([np.zeros(m.sum()), np.ones(m.sum()), q[:, 0]])
        J1 = np.where(seg[:, None], nv[:, :1] * jx + nv[:, 1:] * jy, jx)
        J2 = np.where(seg[:, None], 0.0, jy)
        r1 = np.where(seg, (nv * r).sum(1), r[:, 0])
        r2 = np.where(seg, 0.0, r[:, 1])
        s1 = np.where(seg, (nv * shift).sum(1), shift[:, 0])
        s2 = np.where(seg, 0.0, shift[:, 1])
        g = (J1 * r1[:, None] + J2 * r2[:, None]) * w[:, None]
        got = _fit_sums(np.array(q_pose), obs, w_obs, sig, gate, float(gate.max()),
                        pitch_lever(np.hypot(obs[:, 0], obs[:, 1]), o), local.tables)  # fmt: skip
        assert np.array_equal(got[0], m)
        assert got[1] == pytest.approx(float((d[m] ** 2).sum()), rel=1e-12)
        assert np.allclose(got[2], (J1 * w[:, None]).T @ J1 + (J2 * w[:, None]).T @ J2, rtol=1e-10, atol=1e-9)
        assert np.allclose(got[3], (w * s1) @ J1 + (w * s2) @ J2, rtol=1e-10, atol=1e-9)
        assert np.allclose(got[4], g.T @ g, rtol=1e-10, atol=1e-9)
        assert got[5] == pytest.approx(float(np.sum(w * (r1 * r1 + r2 * r2))), rel=1e-10)
        assert got[6] == float(np.sum(np.where(seg, 1.0, 2.0)))
        n_seg += int(seg.sum())
        n_pt += int((~seg).sum())
    assert n_seg > 10 and n_pt > 10  # both kinds of pairs were exercised


def _pitch_iterations_reference(pose, pairs, opts: Options, iterations: int = 5):
    """refine_with_pitch's Gauss-Newton iterations as numpy on all pairs at once."""
    from localizer.geometry import rotation
    from localizer.robust import PITCH_FIT_DAMPING, pitch_corrected

    obs, ray, lever, var_r, var_t, tgt, normal = pairs
    seg = normal.any(axis=1)
    info_pitch = 1.0 / math.radians(opts.pitch_sigma_deg) ** 2
    pose = np.array(pose, float)
    start, delta, var = pose.copy(), 0.0, 1.0 / info_pitch
    for _ in range(iterations):
        o = pitch_corrected(obs, delta, opts)
        R = rotation(pose[2])
        q, u = o @ R.T, ray @ R.T
        v = np.column_stack([-u[:, 1], u[:, 0]])
        e = q + pose[:2] - tgt
        e[seg] = (e[seg] * normal[seg]).sum(1, keepdims=True) * normal[seg]
        gm = 1.0 / (1.0 + (e * e).sum(1) / var_r) ** 2
        info = gm[:, None, None] * (np.einsum("ni,nj->nij", u, u) / var_r[:, None, None]
                                    + np.einsum("ni,nj->nij", v, v) / var_t[:, None, None])
        nv = normal[seg]
        var_n = (nv * u[seg]).sum(1) ** 2 * var_r[seg] + (nv * v[seg]).sum(1) ** 2 * var_t[seg]
        info[seg] = gm[seg, None, None] * np.einsum("ni,nj->nij", nv, nv) / var_n[:, None, None]
        J = np.zeros((len(e), 2, 4))
        J[:, 0, 0] = J[:, 1, 1] = 1.0
        J[:, 0, 2], J[:, 1, 2] = -q[:, 1], q[:, 0]
        J[:, :, 3] = u * lever[:, None]
        JtI = np.einsum("nki,nkl->nil", J, info)
        H = np.einsum("nil,nlj->ij", JtI, J) + np.eye(4) * 1e-9
        b = -np.einsum("nil,nl->i", JtI, e)
        H[3, 3] += info_pitch
        b[3] -= info_pitch * delta
        H[:3, :3] += PITCH_FIT_DAMPING
        b[:3] -= PITCH_FIT_DAMPING @ (pose - start)
        Hinv = np.linalg.inv(H)
        step = Hinv @ b
        var = float(Hinv[3, 3])
        pose += step[:3]
        delta += step[3]
        if np.hypot(step[0], step[1]) < opts.tolerance_m and abs(step[2]) < opts.tolerance_rad:
            break
    return tuple(pose), delta, var


def test_the_joint_pitch_fit_matches_its_numpy_form():
    from localizer.robust import noise_sigma, pitch_pairs, refine_with_pitch

    o = Options()
    moved = n_seg = 0
    for pose, scene, local in _karlsruhe_scenes(13, 10):
        obs = scene.observations[:, :2]
        start = (0.1, -0.1, pose[2] + 0.003)
        got = refine_with_pitch(local, obs, noise_sigma(obs, o), start, o)
        pairs = pitch_pairs(local, obs, noise_sigma(obs, o), start, o)
        want = _pitch_iterations_reference(start, pairs, o)
        assert np.allclose(got[0], want[0], rtol=0, atol=1e-9)
        assert got[1] == pytest.approx(want[1], abs=1e-12) and got[2] == pytest.approx(want[2], rel=1e-9)
        moved += math.hypot(got[0][0] - start[0], got[0][1] - start[1]) > 0.01
        n_seg += int(pairs[-1].any(axis=1).sum())
    assert moved >= 5 and n_seg > 10  # the fits moved the poses, segment pairs among them


def test_warm_up_compiles_what_requests_run():
    """After localizer.warm_up(), varied requests compile nothing more (no request waits for numba)."""
    from localizer import Frame, geometry, localize_sequence, robust, search, warm_up

    warm_up()
    kernels = [geometry.closest_points, robust._refine_batch, robust._positive_scores, robust._missed_batch,
               robust._fit_sums, robust._pitch_fit, search._stamp_max, search._separated]  # fmt: skip
    compiled = [len(k.signatures) for k in kernels]
    assert all(n >= 1 for n in compiled)
    index, smap = karlsruhe()
    for pose, scene, _ in _karlsruhe_scenes(21, 3):
        lon, lat = index.frame.to_lonlat(pose[0] + 1.0, pose[1] - 1.0)
        heading = float(index.frame.grid_yaw_to_heading(pose[2], lon, lat))
        # A tight prior's small search volume takes its own path (_maximum_filter).
        for prior in (Prior(lat, lon, heading, 3.0, 8.0), Prior(lat, lon, heading, 1.5, 2.0)):
            for options in (Options(), Options(bearing_noise_rad=None, record_trace=True, record_candidates=True)):
                for method in ("default", "pink2008"):
                    localize(index, scene.observations, prior, method=method, options=options)
            localize_sequence(index, [Frame(scene.observations, (0.0, 0.0, 0.0))] * 2, prior)
    assert [len(k.signatures) for k in kernels] == compiled


def test_likelihood_raster_is_the_best_kernel_within_its_window():
    """Each cell holds the largest amplitude-scaled Gaussian of the points within 3 sigma (in cells)."""
    from localizer.search import likelihood_raster

    rng = np.random.default_rng(3)
    # Points inside and around a 23 x 31 raster: stamps clipped at every edge.
    pts = rng.uniform([-3.0, -3.0], [18.0, 14.0], size=(60, 2))
    amp = rng.uniform(0.1, 1.0, 60)
    x0, y0, cell, sigma, dens = 0.5, -0.25, 0.5, 0.4, 0.05
    got = likelihood_raster(pts, x0, y0, (23, 31), cell, sigma, dens, amp)
    r = int(np.ceil(3 * sigma / cell))
    ii, jj = np.mgrid[0:23, 0:31]
    want = np.zeros((23, 31))
    for (px, py), a in zip(pts, amp):
        ci, cj = np.rint((py - y0) / cell), np.rint((px - x0) / cell)
        inside = (np.abs(ii - ci) <= r) & (np.abs(jj - cj) <= r)
        d2 = (x0 + jj * cell - px) ** 2 + (y0 + ii * cell - py) ** 2
        want = np.maximum(want, np.where(inside, a * np.exp(-0.5 * d2 / sigma**2), 0.0))
    assert got.shape == (23, 31) and (want > 0).mean() > 0.5
    assert np.allclose(got, np.log1p(want / dens), rtol=1e-6, atol=1e-7)
    assert not likelihood_raster(pts[:0], x0, y0, (4, 5), cell, sigma, dens).any()


def test_small_volume_maximum_filter_is_scipys():
    from scipy.ndimage import maximum_filter

    from localizer.search import _maximum_filter

    rng = np.random.default_rng(0)
    for shape in [(17, 19, 19), (1, 19, 19), (3, 5, 7), (2, 1, 4)]:
        v = rng.normal(size=shape).astype(np.float32)
        v[v < -1] = -np.inf
        for half in (1, 2, 3):
            assert np.array_equal(_maximum_filter(v, half), maximum_filter(v, size=2 * half + 1, mode="nearest"))



def test_local_maxima_of_a_large_volume_are_the_best_cells_that_no_neighbour_beats():
    """A wide prior's volume: the local maxima (scipy's filter) among its ``top_k`` best finite cells."""
    from scipy.ndimage import maximum_filter

    from localizer.search import _local_maxima

    rng = np.random.default_rng(1)
    for shape, top_k in [((40, 61, 61), 4000), ((9, 121, 121), 500), ((60, 25, 25), 40)]:
        # Smooth enough to have few maxima per neighbourhood, as a score volume.
        v = np.cumsum(np.cumsum(rng.normal(size=shape), 1), 2).astype(np.float32)
        v[:, :5, :5] = -np.inf  # outside the search disc
        for half in (1, 2):
            assert v.size > 3 * top_k
            got = set(zip(*(a.tolist() for a in _local_maxima(v, half, top_k))))
            peak = maximum_filter(v, size=2 * half + 1, mode="nearest")
            best = np.sort(v.ravel())[::-1][top_k - 1]  # the top_k-th largest value
            want = set(zip(*(a.tolist() for a in np.nonzero((v == peak) & np.isfinite(v) & (v >= best)))))
            assert got == want and want


def test_wide_search_scores_the_same_volume_either_way(monkeypatch):
    """A wide prior's volume summed per observation equals the one-matmul sum."""
    import localizer.search as search

    rng = np.random.default_rng(5)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    local = LocalMap(index, ORIGIN, 80.0)
    scene = observe(xy, (ORIGIN[0] + 3.0, ORIGIN[1] - 4.0, 0.7), Camera(), rng)
    args = (local, scene.observations[:, :2], np.ones(len(scene.observations)), (0.0, 0.0, 0.6),
            40.0, math.radians(45), 14.0, math.radians(17), 0.75, 0.05, 20, 1.5)
    n = 2 * math.ceil(40.0 / 0.75) + 1
    assert n * n >= search.LARGE_WINDOW_CELLS  # the per-observation path
    per_observation = search.correlative_search(*args)
    monkeypatch.setattr(search, "LARGE_WINDOW_CELLS", 10**9)
    one_matmul = search.correlative_search(*args)
    assert len(per_observation) == len(one_matmul) == 20
    for a, b in zip(per_observation, one_matmul):
        assert (a.x, a.y, a.yaw) == (b.x, b.y, b.yaw)
        assert a.score == pytest.approx(b.score, abs=1e-3)


def test_the_coarse_search_keeps_far_observations_and_its_sums_within_budget():
    from localizer.search import heading_step, search_observations

    rng = np.random.default_rng(2)
    r, b = rng.uniform(4.0, 148.0, 500), rng.uniform(-1.0, 1.0, 500)
    obs = np.column_stack([r * np.cos(b), r * np.sin(b)])
    order = rng.permutation(500)[:120]
    n2 = (2 * math.ceil(45.0 / 0.75) + 1) ** 2

    def cells(kept):
        step = heading_step(0.75, float(r[kept].max()))
        return (2 * math.ceil(math.pi / step) + 1) * n2

    assert cells(order) > 15_000_000  # any heading, 45 m: the unbounded volume
    kept = search_observations(obs, order, 45.0, math.pi, 0.75, 4_000_000, 10**12)
    assert cells(kept) <= 4_000_000 and len(kept) >= 8
    # The farthest are left out, in the order given.
    assert r[kept].max() < r[np.setdiff1d(order, kept)].min()
    assert kept.tolist() == [k for k in order.tolist() if k in set(kept.tolist())]
    # Beyond the sums' budget the first of the order (the highest weights) stay.
    few = search_observations(obs, order, 45.0, math.pi, 0.75, 4_000_000, 20 * cells(kept))
    assert few.tolist() == kept[:20].tolist()
    assert len(search_observations(obs, order, 45.0, math.pi, 0.75, 4_000_000, 1)) == 8
    # The benchmarks' widest prior (14 m / 17°: 42 m, ±51°), 40 observations to 25 m: untouched.
    near = np.flatnonzero(r <= 25.0)[:40]
    assert search_observations(obs, near, 42.0, math.radians(51), 0.75, 4_000_000, 200_000_000).tolist() \
        == near.tolist()


def test_a_request_at_the_api_limits_is_answered_within_the_search_budget():
    # Any heading, a 1 km position sigma, 500 observations out to 148 m of a
    # wide camera: the coarse search leaves the far ones out, the answer uses all.
    rng = np.random.default_rng(21)
    xy, w = random_map(rng, n=3_600, half=200.0)  # about 500 markings in view
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0] + 6.0, ORIGIN[1] - 3.0, 1.1)
    wide = Camera(min_range_m=4.0, max_range_m=148.0, half_fov_deg=60.0, pitch_sigma_deg=0.0,
                  range_noise_m=0.02, range_noise_coeff=0.0, bearing_noise_rad=0.0, miss_probability=0.0)
    obs = observe(xy, pose, wide, rng).observations
    obs = obs[rng.permutation(len(obs))[:500]]
    assert len(obs) == 500 and np.hypot(obs[:, 0], obs[:, 1]).max() > 140.0
    r = localize(index, obs, prior_at(index, (ORIGIN[0], ORIGIN[1], 0.0), 1000.0, 180.0))
    assert r.status == "ok"
    e, h = errors(r, pose)
    assert e < 0.1 and h < 0.1
    assert r.inliers > 400  # the far observations count in the answer
    assert 8 <= r.diagnostics["search_observations"] < 120  # the coarse search kept within its budget


def test_weighted_rigid_fit_recovers_transform_and_ignores_zero_weights():
    rng = np.random.default_rng(1)
    src = rng.normal(0, 10, (20, 2))
    dst = apply((3.0, -2.0, 0.4), src)
    dst[0] += 100.0  # an outlier with zero weight
    w = np.ones(20)
    w[0] = 0.0
    theta, t = weighted_rigid_fit(src, dst, w)
    assert theta == pytest.approx(0.4, abs=1e-12)
    assert t == pytest.approx([3.0, -2.0], abs=1e-9)


def test_pink2008_converges_exactly_on_noise_free_scene():
    rng = np.random.default_rng(2)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0] + 3.0, ORIGIN[1] - 4.0, 0.8)
    scene = observe(xy, pose)
    assert len(scene.observations) >= 15
    local = LocalMap(index, ORIGIN, 100.0)
    init = (pose[0] - ORIGIN[0] + 0.8, pose[1] - ORIGIN[1] - 0.6, pose[2] + math.radians(4))
    res = pink2008_icp(local, scene.observations[:, :2], scene.observations[:, 2], init)
    assert res.converged
    assert res.iterations <= 30
    assert math.hypot(res.pose[0] + ORIGIN[0] - pose[0], res.pose[1] + ORIGIN[1] - pose[1]) < 1e-3
    assert abs(res.pose[2] - pose[2]) < 1e-5
    # The trace starts at the initial pose and its error falls overall.
    err = [math.hypot(t[0] + ORIGIN[0] - pose[0], t[1] + ORIGIN[1] - pose[1]) for t in res.trace]
    assert err[0] == pytest.approx(1.0) and err[-1] < 1e-3


def test_pink2008_is_robust_to_a_gross_outlier_but_local():
    rng = np.random.default_rng(3)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], -1.2)
    scene = observe(xy, pose)
    obs = np.vstack([scene.observations, [12.0, 1.0, 400.0]])  # heavy clutter off the map
    r = localize(index, obs, prior_at(index, perturb(pose, 0.7, 3.0, rng)), method="pink2008")
    assert r.status == "ok"
    e, h = errors(r, pose)
    assert e < 0.05 and h < 0.2


@pytest.mark.parametrize("dist, turn, sigma_m, sigma_deg", [(1.5, 12.0, 2.0, 10.0), (9.0, -10.0, 6.0, 10.0),
                                                           (20.0, 25.0, 12.0, 20.0)])
def test_default_recovers_known_pose_on_synthetic_map(dist, turn, sigma_m, sigma_deg):
    rng = np.random.default_rng(4)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0] - 10.0, ORIGIN[1] + 5.0, 2.0)
    scene = observe(xy, pose, Camera(), rng)
    prior = prior_at(index, perturb(pose, dist, turn, rng), sigma_m, sigma_deg)
    r = localize(index, scene.observations, prior)
    assert r.status == "ok", r.reason
    e, h = errors(r, pose)
    assert e < 0.2 and h < 0.5
    assert r.inliers >= 0.8 * len(scene.observations)
    assert r.rms_m < 0.5


def test_default_recovers_karlsruhe_scenes():
    index, smap = karlsruhe()
    rng = np.random.default_rng(11)
    from localizer.simulate import Clutter, sample_poses

    poses = sample_poses(smap, 10, rng, min_visible=6)
    good = 0
    for pose in poses:
        scene = simulate_scene(smap, pose, rng, Camera(), Clutter())
        prior = prior_at(index, perturb(pose, rng.uniform(0.5, 2.0), rng.uniform(-15, 15), rng),
                         1.0, 9.0)
        r = localize(index, scene.observations, prior)
        assert r.status != "ok" or errors(r, pose)[0] < 1.0  # never confidently wrong
        if r.status == "ok":
            e, h = errors(r, pose)
            good += e < 0.3 and h < 1.0
    assert good >= 8


@pytest.mark.parametrize("shift", [1.5, -1.5])
def test_a_restart_beside_the_answer_finds_the_better_basin_next_to_it(shift):
    # Two rows of markings 1.5 m apart and three markings off the rows: a pose
    # one spacing along the road explains the rows but not those three. The
    # search is held to 0.3 m around a GPS fix one spacing off, so every coarse
    # candidate lies in the basin next to the truth's, as happens on real maps
    # where the coarse cells are as wide as a basin.
    xy = np.vstack([dash_rows(lateral=(0.0, 3.5), period=1.5, n=200),
                    ORIGIN + [[10.0, -1.0], [15.0, 2.5], [19.0, 4.5]]])
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 0.4, ORIGIN[1] + 1.7, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    prior = prior_at(index, (pose[0] + shift, pose[1], 0.0), 1.0, 2.0)
    narrow = {"min_search_radius_m": 0.3, "max_search_radius_m": 0.3}
    alone = localize(index, scene.observations, prior, options=Options(neighbour_starts=(), **narrow))
    assert all(math.hypot(x - pose[0], y - pose[1]) > 1.0 for x, y, _, _ in alone.diagnostics["search"])
    assert alone.status == "ok" and errors(alone, pose)[0] > 1.0  # confidently wrong without restarts
    r = localize(index, scene.observations, prior, options=Options(**narrow))
    e, h = errors(r, pose)
    assert r.status == "ok" and e < 0.2 and h < 0.5
    assert r.log_score > alone.log_score


def test_a_refinement_dragged_off_while_turning_is_restarted_at_its_heading(monkeypatch):
    # A benchmark scene (14 observations, 7 of them markings): the best coarse
    # candidate lies 0.2 m from the truth but 6° off; the coarse-to-fine
    # refinement from it finds the heading and is dragged 1.9 m along the road
    # by clutter, and the fine-only one from the same start keeps the wrong
    # heading. Restarting at the refined heading from the candidate's position
    # ends at the truth.
    import localizer.core

    index, pose, prior, obs, _ = benchmark_scene("dragged_refinement.json")
    # Shared crowd weights alone rescue this scene too, and so do the heading
    # restarts from the best coarse optima; the restart is tested without them.
    opts = Options(crowd_radius_m=None, heading_restarts=0)
    monkeypatch.setattr(localizer.core, "_RESTART_TURN_RAD", math.inf)
    without = localize(index, obs, prior, options=opts)
    assert without.status == "ok" and errors(without, pose)[0] > 1.0  # confidently wrong
    monkeypatch.undo()
    r = localize(index, obs, prior, options=opts)
    e, h = errors(r, pose)
    assert r.status == "ok" and e < 0.25 and h < 1.0
    assert r.log_score > without.log_score


@pytest.mark.parametrize("scene_file, dashes, without, wrong_m", [
    # From 8-10 m under heavy clutter: 22 observations, 7 of them dashes. The
    # clutter's chance matches give the coarse correlation a best optimum 13 m
    # off; the truth's coarse optimum (0.2 m, 0.7° off) scores 14 log units
    # below it. Skipped as hopeless by a margin of 10, the wrong pose was
    # answered `ok`; refined, the truth outscores it.
    pytest.param("truth_far_below_clutter.json", 7, {"candidate_margin": 10.0}, 10.0,
                 id="far-below-clutter"),
    # The first frame of a drive from 8-10 m: 10 observations, 4 of them
    # dashes among a preceding vehicle's clusters and a curb. The best coarse
    # optimum lies 0.9 m from the truth but 7° turned (the coarse grid holds
    # no heading closer), and refined from there it settles 10° off, matching
    # two observations. The answer was the pose one dash period (9 m) along
    # the lane, `ok`. Started again at that answer's heading, the truth's
    # coarse optimum reaches the truth, which outscores it.
    pytest.param("truth_turned_off_by_coarse_grid.json", 4, {"heading_restarts": 0}, 8.0,
                 id="turned-by-coarse-grid"),
])
def test_a_truth_the_coarse_search_misplaced_is_still_refined(scene_file, dashes, without, wrong_m):
    index, pose, prior, obs, labels = benchmark_scene(scene_file)
    assert labels.count("dash") == dashes
    before = localize(index, obs, prior, options=Options(**without))
    assert before.status == "ok" and errors(before, pose)[0] > wrong_m  # confidently wrong
    r = localize(index, obs, prior)
    e, h = errors(r, pose)
    assert e < 0.25 and h < 1.0
    assert r.probability > 0.5 and r.log_score > before.log_score
    # The wrong optimum is still a rival: the answer is not beyond doubt.
    assert r.status == "ambiguous"
    assert any(math.hypot(hy.easting - before.easting, hy.northing - before.northing) < 1.0
               for hy in r.hypotheses)


def test_hundreds_of_observations_get_fewer_candidates_refined():
    """The refinement's budget: a frame of 500 clutter observations refines the best four a pass."""
    index, smap = karlsruhe()
    x, y = smap.marking_xy[250]
    lon, lat = index.frame.to_lonlat(float(x), float(y))
    prior = Prior(lat, lon, 100.0, 1000.0, 180.0)  # any heading: many coarse optima
    rng = np.random.default_rng(22)
    r, b = np.sqrt(rng.uniform(4.0**2, 148.0**2, 500)), rng.uniform(-1.0, 1.0, 500)
    clutter = np.column_stack([r * np.cos(b), r * np.sin(b), rng.uniform(20, 200, 500)])
    unbounded = Options(max_refine_work=10**9)
    many = localize(index, clutter, prior, options=unbounded)
    few = localize(index, clutter, prior)
    assert len(many.diagnostics["search"]) > 12
    assert len(few.diagnostics["search"]) <= 8  # four, and four more when in doubt
    assert few.status != "ok"  # nothing explains clutter either way
    # A frame within the coarse search's 120 observations is refined as before.
    obs = clutter[:120]
    a, b_ = localize(index, obs, prior), localize(index, obs, prior, options=unbounded)
    assert a.diagnostics["search"] == b_.diagnostics["search"] and a.to_dict() == b_.to_dict()


def test_heading_restarts_run_only_under_priors_of_at_least_3_m(monkeypatch):
    """Under a GPS-like prior they found nothing on the benchmark and cost a fifth of a request."""
    import localizer.core

    calls = []
    real = localizer.core._heading_restarts
    monkeypatch.setattr(localizer.core, "_heading_restarts", lambda *a: calls.append(1) or real(*a))
    index, pose, prior, obs, _ = benchmark_scene("truth_turned_off_by_coarse_grid.json")
    runs = {}
    for name, p in [("2.9 m", replace(prior, position_sigma_m=2.9)),
                    ("3 m", replace(prior, position_sigma_m=3.0)),
                    ("ellipse 3 x 1 m", replace(prior, position_ellipse=ErrorEllipse(3.0, 1.0, 0.0))),
                    ("ellipse 2.9 x 1 m", replace(prior, position_ellipse=ErrorEllipse(2.9, 1.0, 0.0)))]:
        calls.clear()
        localize(index, obs, p)
        runs[name] = len(calls)
    assert runs == {"2.9 m": 0, "3 m": 1, "ellipse 3 x 1 m": 1, "ellipse 2.9 x 1 m": 0}


def test_a_pitch_fit_that_leaves_too_few_matches_answers_failed():
    # A benchmark scene from 0.5-2 m: 10 observations, 3 of them markings
    # among curbs and a preceding vehicle. The best-ranked pose matches three;
    # the joint fit with the camera's pitch, started there, leaves it two
    # within the inlier gate. The rigid optimum is 0.9 m off (the truth ranks
    # second): matches that a small change of the camera model loses are no
    # fix, and the answer is `failed`, not that pose.
    index, pose, prior, obs, labels = benchmark_scene("pitch_fit_loses_a_match.json")
    assert labels.count("dash") + labels.count("solid") == 3
    rigid = localize(index, obs, prior, options=Options(estimate_pitch=False))
    assert rigid.status != "failed" and rigid.inliers >= 3 and errors(rigid, pose)[0] > 0.5
    r = localize(index, obs, prior)
    assert r.status == "failed" and r.easting is None
    assert "only 2 of 10 observations match" in r.reason


def test_crowded_observations_share_their_weight():
    rng = np.random.default_rng(3)
    isolated = np.array([[5.0, -8.0], [20.0, 8.0]])
    crowd = np.array([12.0, 0.5]) + rng.normal(0.0, 0.25, (5, 2))  # a preceding vehicle's edges
    xy = np.vstack([isolated, crowd])
    w = np.ones(len(xy))
    shared = crowd_weights(xy, w, 1.5)
    assert math.isclose(shared.sum(), w.sum())
    # Five clusters within half a metre count about as much as one marking.
    assert shared[2:].sum() < 1.5 * shared[0]
    assert math.isclose(shared[0], shared[1], rel_tol=1e-6)
    # Far apart, nothing is shared; observations are not reordered.
    apart = np.column_stack([np.arange(7) * 20.0, np.zeros(7)])
    np.testing.assert_allclose(crowd_weights(apart, np.arange(1.0, 8.0), 1.5), np.arange(1.0, 8.0))
    assert crowd_weights(xy[:1], w[:1], 1.5).tolist() == [1.0]


def test_a_preceding_vehicle_does_not_outweigh_the_markings():
    # A benchmark scene of 13 observations: six dashes, two curb edges and five
    # clusters of a preceding vehicle carrying half the frame's pixel weight. A
    # rival turned 30° lays the vehicle's clusters on markings; with every
    # cluster counted as independent evidence, it keeps a real share of the
    # posterior (4.6 %; 7 % and the answer ambiguous under the temperature of
    # 1.35 the fixture was taken with).
    index, pose, prior, obs, labels = benchmark_scene("crowded_vehicle.json")
    assert labels.count("vehicle") == 5
    alone = localize(index, obs, prior, options=Options(crowd_radius_m=None))
    r = localize(index, obs, prior)
    e, h = errors(r, pose)
    assert r.status == "ok" and e < 0.25 and h < 1.0
    assert 1.0 - r.probability < (1.0 - alone.probability) / 5.0


def test_crowd_radius_is_validated():
    for bad in (0.0, -1.0, math.nan, "1"):
        with pytest.raises(LocalizationInputError, match="crowd_radius_m"):
            Options(crowd_radius_m=bad)


def test_pink2008_recovers_karlsruhe_scenes_from_small_errors():
    index, smap = karlsruhe()
    rng = np.random.default_rng(12)
    from localizer.simulate import sample_poses

    poses = sample_poses(smap, 10, rng, min_visible=6)
    good = 0
    for pose in poses:
        scene = simulate_scene(smap, pose, rng, Camera(), NONE)
        prior = prior_at(index, perturb(pose, 0.5, 3.0, rng))
        r = localize(index, scene.observations, prior, method="pink2008")
        if r.status == "ok":
            e, h = errors(r, pose)
            good += e < 0.5 and h < 1.0
    assert good >= 7


# ---------------------------------------------------------------- ambiguity and failure


def dash_rows(lateral=(0.0,), period=9.0, n=60):
    xs = np.concatenate([np.arange(-n, n) * period for _ in lateral])
    ys = np.concatenate([np.full(2 * n, y) for y in lateral])
    return ORIGIN + np.column_stack([xs, ys])


def test_periodic_dash_rows_are_ambiguous_with_hypotheses_a_period_apart():
    xy = dash_rows(lateral=(0.0, 3.5))  # a lane between two dashed lines
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 1.0, ORIGIN[1] + 1.7, 0.0)  # driving along the lane
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    prior = prior_at(index, (pose[0] + 4.5, pose[1], 0.0))  # half a period off
    r = localize(index, scene.observations, prior)
    assert r.status == "ambiguous"
    assert len(r.hypotheses) >= 2
    assert sum(h.score for h in r.hypotheses) <= 1.0 + 1e-9
    assert r.hypotheses[0].score < Options().ambiguity_probability
    # The answer's probability is the best hypothesis's.
    assert r.probability == pytest.approx(r.hypotheses[0].score)
    east = sorted(h.easting - pose[0] for h in r.hypotheses)
    assert min(abs(e) for e in east) < 0.3  # the truth is one of them
    gaps = np.diff(east)
    assert np.all(np.abs(gaps / 9.0 - np.round(gaps / 9.0)) < 0.05)
    # Seen from the answer (driving east: x east, y north) the rivals lie a
    # whole number of periods ahead or behind, in the same lane, at the same heading.
    offsets = [h.offset_from(r) for h in r.hypotheses]
    assert offsets[0] == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    for (x, y, turn), h in zip(offsets[1:], r.hypotheses[1:]):
        assert x == pytest.approx(h.easting - r.easting, abs=0.05) and abs(x) > 8.0
        assert abs(x / 9.0 - round(x / 9.0)) < 0.05 and abs(y) < 0.3 and abs(turn) < 1.0
    assert [h["offset"]["x_m"] for h in r.to_dict()["hypotheses"]] == pytest.approx([o[0] for o in offsets])
    # The paper's method just answers, wrong by a period or right by luck.
    p = localize(index, scene.observations, prior, method="pink2008")
    assert p.status in ("ok", "failed") and p.hypotheses == [] and p.probability is None


def test_an_ambiguous_answer_gives_each_hypothesis_its_covariance_and_their_mixture():
    """Rivals a dash period apart along the road: the mixture is long along it, narrow across."""
    from localizer.robust import mixture_covariance

    xy = dash_rows(lateral=(0.0, 3.5))
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 1.0, ORIGIN[1] + 1.7, 0.0)  # driving east along the lane
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    r = localize(index, scene.observations, prior_at(index, (pose[0] + 4.5, pose[1], 0.0)))
    assert r.status == "ambiguous" and len(r.hypotheses) >= 2
    for h in r.hypotheses:
        c = h.covariance
        assert c.shape == (3, 3) and np.allclose(c, c.T) and np.all(np.linalg.eigvalsh(c) > 0)
        assert math.sqrt(c[0, 0]) < 0.5 and math.sqrt(c[1, 1]) < 0.5  # each one is sure of itself
    assert np.array_equal(r.hypotheses[0].covariance, r.covariance)
    # sum p_i (C_i + d_i d_i^T), the scores rescaled, spelled out
    p = np.array([h.score for h in r.hypotheses])
    p /= p.sum()
    want = np.zeros((3, 3))
    for w, h in zip(p, r.hypotheses):
        yaw = index.frame.heading_to_grid_yaw(h.heading_deg, h.lon, h.lat)
        d = np.array([h.easting - r.easting, h.northing - r.northing,
                      math.remainder(yaw - r.yaw_grid_rad, 2 * math.pi)])
        want += w * (h.covariance + np.outer(d, d))
    m = r.mixture_covariance
    assert np.allclose(m, want, rtol=1e-6, atol=1e-9)  # yaw back from the heading: to 1e-9 rad
    # Along the road the rivals spread it over the period; across it and in
    # heading it stays about one hypothesis's.
    spread = math.sqrt(sum(w * (h.easting - r.easting) ** 2 for w, h in zip(p, r.hypotheses)))
    assert spread > 3.0 and math.sqrt(m[0, 0]) == pytest.approx(spread, rel=0.01)
    assert math.sqrt(m[1, 1]) < 0.3 and math.sqrt(m[2, 2]) < math.radians(1.0)
    # Driving east: along the heading is east, across it north.
    from localizer.robust import along_across_sigmas

    along, across = along_across_sigmas(m, r.yaw_grid_rad)
    assert along == pytest.approx(math.sqrt(m[0, 0]), rel=1e-3) and across == pytest.approx(math.sqrt(m[1, 1]), abs=0.01)
    # The truth lies inside its 95 % ellipse, whichever rival the answer is.
    dx = np.array([pose[0] - r.easting, pose[1] - r.northing])
    assert dx @ np.linalg.solve(m[:2, :2], dx) < 5.99
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert np.allclose(d["mixture_covariance"], m) and np.allclose(d["hypotheses"][1]["covariance"],
                                                                    r.hypotheses[1].covariance)
    # Without a hypothesis's covariance there is no mixture; yaw offsets wrap.
    assert mixture_covariance((0, 0, 0), [(0, 0, 0)], [1.0], [None]) is None
    got = mixture_covariance((0.0, 0.0, math.pi - 0.01), [(0.0, 0.0, -math.pi + 0.01)], [0.5], [np.zeros((3, 3))])
    assert got[2, 2] == pytest.approx(0.02**2)


def test_a_doubtful_answer_gets_more_candidates_refined():
    xy = dash_rows(lateral=(0.0, 3.5))
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 1.0, ORIGIN[1] + 1.7, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    prior = prior_at(index, (pose[0] + 4.5, pose[1], 0.0))
    first_only = localize(index, scene.observations, prior, options=Options(candidates=2, extra_candidates=0))
    more = localize(index, scene.observations, prior, options=Options(candidates=2, extra_candidates=12))
    assert first_only.status == more.status == "ambiguous"
    # The second pass refined more coarse optima and found the aliases two periods away.
    assert len(more.diagnostics["search"]) > len(first_only.diagnostics["search"]) + 5
    offsets = sorted(round((h.easting - pose[0]) / 9.0) for h in more.hypotheses)
    assert len(more.hypotheses) > len(first_only.hypotheses) and len(set(offsets)) >= 4
    assert more.probability < first_only.probability
    # An answer beyond doubt is not searched further.
    rng = np.random.default_rng(15)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 0.5)
    obs, prior = observe(xy, pose).observations, prior_at(index, pose)
    sure = localize(index, obs, prior, options=Options(candidates=3))
    assert sure.probability > Options().extra_search_probability
    assert sure.diagnostics["search"] == localize(index, obs, prior, options=Options(
        candidates=3, extra_candidates=0)).diagnostics["search"]


def test_parallel_lanes_are_ambiguous():
    xy = dash_rows(lateral=(-7.0, -3.5, 0.0, 3.5, 7.0), period=9.0)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0], ORIGIN[1] + 1.75, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(6))
    prior = prior_at(index, (pose[0], pose[1] + 1.75, 0.0), 3.0, 5.0)
    r = localize(index, scene.observations, prior)
    assert r.status == "ambiguous"
    north = [h.northing - pose[1] for h in r.hypotheses]
    assert any(abs(n) < 0.3 for n in north)
    assert any(abs(abs(n) - 3.5) < 0.3 for n in north)
    # a lane's width to the answer's left or right (driving east: y is north)
    assert any(abs(abs(h.offset_from(r)[1]) - 3.5) < 0.3 for h in r.hypotheses)


def test_a_hypothesis_offset_is_in_the_answers_vehicle_frame():
    """x forward, y left (ISO 8855) of the answer, and the heading difference clockwise, wrapped."""
    north = Pose(status="ambiguous", crs=CRS, lat=49.0, lon=8.4, easting=100.0, northing=200.0,
                 yaw_grid_rad=math.pi / 2, heading_deg=359.5)  # facing grid north
    ahead = Hypothesis(49.0, 8.4, 0.7, 100.0, 209.0, 0.4)  # 9 m north, turned 1.2° clockwise across north
    left = Hypothesis(49.0, 8.4, 358.0, 96.5, 200.0, 0.2)  # 3.5 m west, turned 1.5° anticlockwise
    assert ahead.offset_from(north) == pytest.approx((9.0, 0.0, 1.2), abs=1e-9)
    assert left.offset_from(north) == pytest.approx((0.0, 3.5, -1.5), abs=1e-9)
    east = replace(north, yaw_grid_rad=0.0, heading_deg=90.0)
    assert ahead.offset_from(east)[:2] == pytest.approx((0.0, 9.0))  # north is left of a car facing east
    assert ahead.offset_from(Pose(status="failed", crs=CRS)) is None
    d = Hypothesis(49.0, 8.4, 180.0, 100.0, 200.0, 1.0).to_dict(north)["offset"]
    assert d == {"x_m": 0.0, "y_m": 0.0, "heading_deg": pytest.approx(-179.5)}
    assert "offset" not in ahead.to_dict()
    # About half a turn stays inside [-180, 180), even where rounding the difference would give +180.
    for heading in (179.5 + 1e-13, 179.5, 179.5 - 1e-13, -1e-15):
        turn = Hypothesis(49.0, 8.4, heading, 100.0, 200.0, 1.0).offset_from(replace(north, heading_deg=heading + 180.0))[2]
        assert -180.0 <= turn < 180.0 and abs(turn) == pytest.approx(180.0)
    just_past = replace(north, heading_deg=math.nextafter(180.0, 360.0))  # (d + 180) % 360 rounds to 360 here
    assert -180.0 <= Hypothesis(49.0, 8.4, 0.0, 100.0, 200.0, 1.0).offset_from(just_past)[2] < 180.0


def test_an_error_ellipse_tight_across_the_road_picks_the_lane():
    """A GNSS fix sure of the lane but not of the distance along: its ellipse decides what a circle cannot."""
    xy = dash_rows(lateral=tuple(np.arange(-10, 11) * 3.5), period=9.0)  # a wide road of identical lanes
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0], ORIGIN[1] + 1.75, 0.0)  # driving east
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(6))
    centre = (pose[0] + 1.0, pose[1] + 0.4, 0.0)
    circle = prior_at(index, centre, 2.5, 5.0)
    lon, lat = index.frame.to_lonlat(*centre[:2])
    east = float(index.frame.grid_yaw_to_heading(0.0, lon, lat))  # the road's true bearing, about 90.4°

    def lanes(r):
        return sorted(round((h.northing - pose[1]) / 3.5) for h in r.hypotheses)

    wide = localize(index, scene.observations, circle)
    assert wide.status == "ambiguous" and {-1, 0, 1} <= set(lanes(wide))
    along = localize(index, scene.observations, replace(circle, position_ellipse=ErrorEllipse(2.5, 0.5, east)))
    assert along.status == "ok" and errors(along, pose)[0] < 0.3
    # The same ellipse turned across the road is no help: the orientation is read as a bearing.
    across = localize(index, scene.observations,
                      replace(circle, position_ellipse=ErrorEllipse(2.5, 0.5, east + 90.0)))
    assert across.status == "ambiguous" and 0 in lanes(across) and 1 in lanes(across)
    # A round ellipse is the circle, whatever its orientation.
    round_ = localize(index, scene.observations, replace(circle, position_ellipse=ErrorEllipse(2.5, 2.5, 33.0)))
    assert round_.status == wide.status and round_.probability == pytest.approx(wide.probability, abs=1e-9)
    assert (round_.easting, round_.northing) == pytest.approx((wide.easting, wide.northing), abs=1e-9)


def test_an_error_ellipse_is_oriented_by_true_bearing_where_grid_north_differs():
    from pyproj import Geod

    from localizer import GeoFrame
    from localizer.core import position_covariance

    frame = GeoFrame("EPSG:32632")
    lon, lat = 13.5, 60.0  # far east of the zone's central meridian: the convergence is about +3.9°
    assert frame.convergence_deg(lon, lat) > 3.0
    for bearing in (0.0, 30.0, 125.0):
        prior = Prior(lat=lat, lon=lon, heading_deg=0.0, position_ellipse=ErrorEllipse(4.0, 1.0, bearing))
        cov = position_covariance(prior, frame)
        val, vec = np.linalg.eigh(cov)
        assert val == pytest.approx([1.0, 16.0])
        # 100 m along the true bearing on the ellipsoid, in the grid: the major axis
        lon2, lat2, _ = Geod(ellps="WGS84").fwd(lon, lat, bearing, 100.0)
        d = np.subtract(frame.to_xy(lon2, lat2), frame.to_xy(lon, lat))
        cos = abs(float(vec[:, 1] @ d)) / np.hypot(*d)
        assert math.degrees(math.acos(min(cos, 1.0))) < 0.02


@pytest.mark.parametrize(
    "ellipse, message",
    [
        (ErrorEllipse(1.0, 2.0, 0.0), "larger than sigma_major_m"),
        (ErrorEllipse(float("nan"), 1.0, 0.0), "sigma_major_m: must be a finite number"),
        (ErrorEllipse(2.0, 1.0, float("inf")), "orientation_deg: must be a finite number"),
        (ErrorEllipse(2.0, 0.0, 10.0), "sigma_minor_m: 0.0 is outside"),
        (ErrorEllipse(5000.0, 1.0, 10.0), "sigma_major_m: 5000.0 is outside"),
        ((2.0, 1.0, 10.0), "expected a localizer.ErrorEllipse"),
    ],
)
def test_a_malformed_error_ellipse_is_an_input_error(ellipse, message):
    rng = np.random.default_rng(15)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 0.5)
    prior = replace(prior_at(index, pose), position_ellipse=ellipse)
    with pytest.raises(LocalizationInputError, match=message):
        localize(index, observe(xy, pose).observations, prior)


def test_a_distinct_marking_resolves_the_period():
    xy = np.vstack([dash_rows(lateral=(0.0, 3.5)), ORIGIN + [[12.0, -1.0], [21.0, 2.2]]])
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 1.0, ORIGIN[1] + 1.7, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    r = localize(index, scene.observations, prior_at(index, (pose[0] + 3.0, pose[1], 0.0)))
    assert r.status == "ok"
    assert errors(r, pose)[0] < 0.2


def ending_dash_rows(end_m=60.0):
    """Three dashed lines a lane apart that end ``end_m`` metres east of ORIGIN."""
    xy = dash_rows(lateral=(0.0, 3.5, 7.0))
    return xy[xy[:, 0] - ORIGIN[0] <= end_m]


def test_negative_evidence_resolves_the_period_where_a_dashed_line_ends():
    # The camera sees the last dashes of the lines and nothing beyond. A pose one
    # period back explains those as well (its dashes lie where the camera saw
    # dashes), but it also puts the last dash of each line in view, where nobody
    # saw one.
    xy = ending_dash_rows()
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 40.0, ORIGIN[1] + 1.7, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    assert len(scene.observations) == 5
    prior = prior_at(index, (pose[0] - 1.0, pose[1], 0.0))  # 1 m back, sigma 5 m

    def period_back(result):
        """Posterior probability of the pose one period back."""
        return sum(h.score for h in result.hypotheses
                   if abs(h.easting - pose[0] + 9.0) < 0.3 and abs(h.northing - pose[1]) < 0.3)

    r = localize(index, scene.observations, prior)
    assert errors(r, pose)[0] < 0.2  # the best pose is the truth
    assert r.status == "ok" or period_back(r) < 0.02
    # Without negative evidence the pose a period back is a serious rival.
    blind = Options(miss_probability=1.0, solid_miss_probability=1.0)
    r = localize(index, scene.observations, prior, options=blind)
    assert r.status == "ambiguous"
    assert period_back(r) > 0.1


def test_coarse_optima_are_charged_the_markings_they_put_in_view_unseen():
    # Refining a single coarse optimum: the correlation's best one, one period
    # back (nearest the prior), explains the observed dashes as well as the
    # truth and wins on the prior; but it puts the lines' last dashes in view,
    # where nobody saw one.
    xy = ending_dash_rows()
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS)
    pose = (ORIGIN[0] + 40.0, ORIGIN[1] + 1.7, 0.0)
    scene = observe(xy, pose, Camera(miss_probability=0.0), np.random.default_rng(5))
    prior = prior_at(index, (pose[0] - 9.0, pose[1], 0.0))
    one = Options(candidates=1, extra_candidates=0)

    def first_searched(result):
        return result.diagnostics["search"][0][0] - pose[0]

    blind = localize(index, scene.observations, prior, options=replace(one, coarse_pool=0))
    assert first_searched(blind) == pytest.approx(-9.0, abs=0.5)
    assert errors(blind, pose)[0] > 8.0  # only the period-back basin was refined
    charged = localize(index, scene.observations, prior, options=replace(one, coarse_pool=50))
    assert abs(first_searched(charged)) < 0.5
    assert errors(charged, pose)[0] < 0.2


def test_coarse_optima_are_separated_as_a_greedy_suppression():
    from localizer.search import _separated

    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 6, 400), rng.uniform(0, 6, 400)
    yaw = rng.uniform(-0.2, 0.2, 400)
    yaw[::2] += math.pi  # half of them near ±π, where headings wrap
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi

    def turn(a, b):
        return abs(math.remainder(a - b, 2 * math.pi))

    for limit in (1, 25, 400):
        want: list[int] = []
        for k in range(400):
            if len(want) < limit and not any(
                math.hypot(x[k] - x[m], y[k] - y[m]) < 1.0 and turn(yaw[k], yaw[m]) < math.radians(2.5)
                for m in want
            ):
                want.append(k)
        assert _separated(x, y, yaw, 1.0, math.radians(2.5), limit).tolist() == want
    assert len(want) > 25  # the limit was reached
    # Two optima a degree apart across ±π are one.
    assert _separated(np.zeros(2), np.zeros(2), np.array([math.pi - 0.01, -math.pi + 0.01]), 1.0,
                      math.radians(2.5), 10).tolist() == [0]


def test_a_solid_line_predicted_in_view_but_not_seen_counts_against_a_pose():
    from localizer.geometry import LocalMap
    from localizer.robust import missed_counts, view_of

    # A 30 m solid line cut in 3 m pieces, 1.75 m left of a vehicle driving along it.
    xs = np.arange(10) * 3.0 + 1.5
    xy = ORIGIN + np.column_stack([xs, np.zeros(10)])
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS,
                                 bearing_deg=np.full(10, 90.0), length_m=np.full(10, 3.0))
    assert np.all(index.half_length[1:-1] == 1.5)  # the end pieces stay point-like
    local = LocalMap(index, ORIGIN, 100.0)
    opts = Options()
    on_line = np.column_stack([np.arange(6, 26, 3.0), np.full(7, 1.75)])  # what the camera saw
    elsewhere = np.array([[8.0, -6.0], [12.0, -6.5], [20.0, -7.0]])
    for obs, expect_missed in ((on_line, False), (elsewhere, True)):
        pts, solid = missed_counts(local, obs, [(-2.0, -1.75, 0.0)], opts, view_of(obs, opts))
        assert pts[0] == 0
        assert (solid[0] >= 4) if expect_missed else (solid[0] == 0)


def test_detections_cut_short_or_run_long_get_slack_along_their_axis():
    from localizer.index import length_slack

    # Two dashed lines of 3 m dashes, 9 m apart, detected with unknown kind. A
    # tree hides two thirds of one dash (1 m detected, at its far end); another
    # touches a patch of paint (4.6 m); a stop line 6 m across the road.
    xy = dash_rows(lateral=(0.0, 3.5), n=8)
    n = len(xy)
    length = np.full(n, 3.0)
    bearing = np.full(n, 90.0)
    short, long_ = 5, 12
    xy[short, 0] += 1.0
    length[short], length[long_] = 1.0, 4.6
    xy = np.vstack([xy, ORIGIN + [[40.0, 1.75]]])
    length = np.append(length, 6.0)
    bearing = np.append(bearing, 0.0)
    measured = np.ones(n + 1, bool)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, bearing_deg=bearing, length_m=length,
                                 measured=measured)
    assert index.half_length[short] == pytest.approx(1.0)  # the painted centroid is within ±1 m
    assert index.half_length[long_] == pytest.approx(0.8)
    assert index.half_length[-1] == pytest.approx(1.5)  # across the road: along-road position kept
    assert np.allclose(index.axis[short], [1.0, 0.0])
    assert np.allclose(index.axis[-1], [0.0, 1.0], atol=1e-9)
    regular = np.ones(n + 1, bool)
    regular[[short, long_, n]] = False
    assert np.all(index.half_length[regular] == 0)
    # Kinds a map knows are taken as they are: a dash is a point.
    known = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, bearing_deg=bearing, length_m=length,
                                 kind=["dash"] * n + ["stop_line"], measured=measured)
    assert np.all(known.half_length == 0)
    # Nor is a surveyed map's geometry, kinds or not.
    exact = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, bearing_deg=bearing, length_m=length)
    assert np.all(exact.half_length == 0)
    # The service's index gives it to detections only, not to imported markings.
    from mapbuilder.store import MarkingArrays
    from service.map_index import index_from_markings

    source = np.full(n + 1, "detected", object)
    arrays = MarkingArrays(id=np.arange(n + 1), x=xy[:, 0], y=xy[:, 1], weight=np.ones(n + 1),
                           length_m=length, bearing_deg=bearing, kind=np.full(n + 1, None, object),
                           source=source)
    assert index_from_markings(arrays, CRS).half_length[short] == pytest.approx(1.0, abs=0.02)
    source[:] = "imported"
    assert np.all(index_from_markings(arrays, CRS).half_length == 0)
    # A detection without a length (a point from elsewhere) has no axis to slide along.
    pts = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, bearing_deg=bearing,
                               length_m=np.where(np.arange(n + 1) == short, 0.0, length), measured=measured)
    assert pts.half_length[short] == 0 and pts.half_length[long_] == pytest.approx(0.8)
    # Too few detections to tell what is typical: nothing changes.
    few = length_slack(xy[:5], length[:5], np.ones(5, bool))
    assert np.all(few == 0)


def test_a_cluster_along_the_line_explains_an_expected_cluster_of_its_end_piece():
    from localizer.robust import missed_counts, view_of

    # A line of two 3 m pieces 1.75 m left, from 10 to 16 m ahead: one expected
    # cluster per piece, at 11.5 and 14.5 m. The camera clustered the line at
    # its own phase and reported one centroid, 13.8 m ahead: 2.3 m from the
    # first expected cluster, beyond explain_distance_m, but on its line.
    xy = ORIGIN + np.array([[11.5, 1.75], [14.5, 1.75]])
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, bearing_deg=[90.0, 90.0],
                                 length_m=[3.0, 3.0], kind=["solid", "solid"])
    local = LocalMap(index, ORIGIN, 100.0)
    pose = [(0.0, 0.0, 0.0)]
    others = np.array([[8.0, -5.0], [20.0, -6.0], [22.0, 4.0]])  # point markings elsewhere
    # (centroid, missed expected clusters, missed by the 1.5 m rule alone):
    # on the line 2.3 m along; 1.1 m beside it; on it but 4.9 m from the second.
    for seen, missed, missed_isotropic in (([13.8, 1.75], 0, 1), ([13.8, 2.85], 1, 1), ([9.6, 1.75], 1, 2)):
        obs = np.vstack([others, seen])
        for opts, expect in ((Options(), missed), (Options(solid_explain_along_m=0.0), missed_isotropic)):
            view = view_of(obs, opts)
            assert missed_counts(local, obs, pose, opts, view)[1][0] == expect, (seen, opts.solid_explain_along_m)


def _points_ahead(rng, n=12):
    """Point markings 5-25 m ahead within ±29° of a vehicle at ORIGIN facing +x (vehicle frame)."""
    r = rng.uniform(5.0, 25.0, n)
    b = rng.uniform(-0.5, 0.5, n)
    v = np.column_stack([r * np.cos(b), r * np.sin(b)])
    index = MapIndex.from_arrays(v[:, 0] + ORIGIN[0], v[:, 1] + ORIGIN[1], None, CRS)
    return v, LocalMap(index, ORIGIN, 100.0)


def test_an_observation_beside_its_marking_counts_less_than_one_short_of_it():
    from localizer.robust import data_scores, noise_sigma

    # One marking 20 m ahead. A camera's range error there is several times
    # its bearing error, so 0.4 m across the ray is the less likely miss.
    index = MapIndex.from_arrays([ORIGIN[0] + 20.0], [ORIGIN[1]], None, CRS)
    local = LocalMap(index, ORIGIN, 100.0)
    short, beside = np.array([[19.6, 0.0]]), np.array([[20.0, 0.4]])

    def score(obs, opts):
        return data_scores(local, obs, np.ones(1), noise_sigma(obs, opts), [(0.0, 0.0, 0.0)], opts)[0]

    opts = Options()
    assert score(short, opts) > score(beside, opts) + 0.5
    iso = Options(bearing_noise_rad=None)
    assert score(short, iso) == pytest.approx(score(beside, iso), abs=0.1)  # sigma follows the range


def test_refinement_converges_exactly_and_trusts_bearings_more_than_ranges():
    from localizer.robust import noise_sigma, robust_refine

    rng = np.random.default_rng(3)
    v, local = _points_ahead(rng)
    opts = Options()
    start = [(0.4, -0.3, math.radians(1.5))]
    run = robust_refine(local, v, np.ones(len(v)), noise_sigma(v, opts), start, opts)[0]
    exact = run.pose
    assert math.hypot(exact[0], exact[1]) < 1e-3 and abs(exact[2]) < 1e-5
    # The iterations a scale may take are an option; one each is not enough here.
    once = robust_refine(local, v, np.ones(len(v)), noise_sigma(v, opts), start,
                         Options(iterations_per_scale=1))[0]
    assert once.iterations == len(opts.anneal_m) < run.iterations
    assert math.hypot(once.pose[0], once.pose[1]) > math.hypot(exact[0], exact[1])
    # Range errors only, as large as the noise model says: the anisotropic
    # last scale recovers the heading better than weighing both directions alike.
    heading = {True: [], False: []}
    for _ in range(30):
        v, local = _points_ahead(rng)
        r = np.hypot(v[:, 0], v[:, 1])
        obs = v * (1.0 + rng.normal(0.0, 1.0, len(r)) * (0.05 + 5e-4 * r**2) / r)[:, None]
        for aniso in (True, False):
            o = opts if aniso else Options(bearing_noise_rad=None)
            pose = robust_refine(local, obs, np.ones(len(obs)), noise_sigma(obs, o), start, o)[0].pose
            heading[aniso].append(abs(pose[2]))
    assert np.mean(heading[True]) < 0.85 * np.mean(heading[False])


def _pitched(v, pitch_rad, height_m=1.3):
    """What a flat-ground camera pitched down by ``pitch_rad`` reports for ground points ``v``."""
    r = np.hypot(v[:, 0], v[:, 1])
    r_meas = height_m / np.tan(np.arctan2(height_m, r) + pitch_rad)
    return v * (r_meas / r)[:, None]


def test_refinement_with_pitch_undoes_the_stretch_a_rigid_fit_absorbs():
    from localizer.robust import noise_sigma, pitch_corrected, refine_with_pitch, robust_refine

    rng = np.random.default_rng(5)
    v, local = _points_ahead(rng, n=15)
    opts = Options()
    pitch = math.radians(0.1)  # two prior sigmas: 0.3 m of range at 15 m
    obs = _pitched(v, pitch)
    np.testing.assert_allclose(pitch_corrected(obs, pitch, opts), v, atol=1e-9)
    sig = noise_sigma(obs, opts)
    rigid = robust_refine(local, obs, np.ones(len(obs)), sig, [(0.0, 0.0, 0.0)], opts)[0].pose
    assert abs(rigid[0]) > 0.15  # the rigid fit slides the vehicle to shorten the ranges
    pose, est, var = refine_with_pitch(local, obs, sig, rigid, opts)
    # The prior holds the estimate a little short of the truth (0.1° is two of its sigmas).
    assert math.hypot(pose[0], pose[1]) < 0.4 * abs(rigid[0]) and abs(pose[2]) < math.radians(0.1)
    assert est == pytest.approx(pitch, rel=0.3)
    assert 0 < var < math.radians(opts.pitch_sigma_deg) ** 2  # the data narrowed the prior
    # No pitch, no change: the exact pose stays where it is.
    pose0, est0, _ = refine_with_pitch(local, v, noise_sigma(v, opts), (0.0, 0.0, 0.0), opts)
    assert math.hypot(pose0[0], pose0[1]) < 1e-6 and abs(est0) < 1e-9


def test_refinement_with_pitch_stays_put_where_nothing_pins_the_pose_along_the_road():
    from localizer.robust import noise_sigma, refine_with_pitch

    # Two solid lines on a gentle curve (radius 300 m), cut into 3 m pieces, and
    # nothing else: sliding along the road (turning about the curve's centre)
    # changes no residual. Undamped, the step along it was noise amplified:
    # 5-20 m on these scenes. The fit must correct the pitch and stay put.
    radius = 300.0
    centre = ORIGIN + np.array([0.0, radius])
    a = np.arange(-0.02, 0.14, 3.0 / radius)
    pieces = np.vstack([
        np.column_stack([centre[0] + (radius - off) * np.sin(a), centre[1] - (radius - off) * np.cos(a)])
        for off in (-1.75, 1.75)
    ])
    bearing = np.tile((90.0 - np.degrees(a)) % 180.0, 2)
    index = MapIndex.from_arrays(pieces[:, 0], pieces[:, 1], None, CRS, bearing_deg=bearing,
                                 length_m=np.full(len(pieces), 3.0), kind=["solid"] * len(pieces))
    local = LocalMap(index, ORIGIN, 100.0)
    opts = Options()
    start = (0.1, 0.02, 0.002)  # where a rigid fit left it
    for seed in range(4):
        rng = np.random.default_rng(seed)
        # The camera's clusters on the lines, 5-25 m ahead, with a pitch error and range noise.
        b = rng.uniform(5.0, 25.0, (2, 6)) / radius
        v = np.vstack([np.column_stack([(radius - off) * np.sin(t), radius - (radius - off) * np.cos(t)])
                       for off, t in zip((-1.75, 1.75), b)])
        r = np.hypot(v[:, 0], v[:, 1])
        obs = _pitched(v, math.radians(0.05)) * (1 + rng.normal(0, 1, len(r)) * (0.03 + 3e-4 * r**2) / r)[:, None]
        pose, _, _ = refine_with_pitch(local, obs, noise_sigma(obs, opts), start, opts)
        assert math.hypot(pose[0] - start[0], pose[1] - start[1]) < 0.1, seed
        assert abs(pose[2] - start[2]) < math.radians(0.2), seed


def test_localize_estimates_the_pitch_unless_told_not_to():
    rng = np.random.default_rng(21)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0] + 3.0, ORIGIN[1] - 2.0, 0.4)
    scene = observe(xy, pose)
    obs = scene.observations.copy()
    obs[:, :2] = _pitched(obs[:, :2], math.radians(0.1))
    prior = prior_at(index, perturb(pose, 1.5, 5.0, rng), 2.0, 10.0)
    with_pitch = localize(index, obs, prior)
    rigid = localize(index, obs, prior, options=Options(estimate_pitch=False))
    assert with_pitch.status == rigid.status == "ok"
    assert errors(with_pitch, pose)[0] < 0.05 < errors(rigid, pose)[0]


def test_a_pose_that_explains_little_more_than_clutter_is_not_ok():
    # Two markings matched among a dozen random blobs: whatever the best pose, the
    # "none of these" hypothesis keeps it from being reported as certain.
    rng = np.random.default_rng(11)
    xy, w = random_map(rng, n=400)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 0.3)
    real = observe(xy, pose).observations
    real = real[np.argsort(real[:, 0])][:3]
    clutter = np.column_stack([rng.uniform(5, 24, 12), rng.uniform(-8, 8, 12), rng.uniform(20, 60, 12)])
    obs = np.vstack([real, clutter])
    r = localize(index, obs, prior_at(index, pose, 5.0, 10.0))
    assert r.status in ("ambiguous", "failed")


def test_failed_when_too_few_observations_match():
    rng = np.random.default_rng(7)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 0.3)
    obs = observe(xy, pose).observations
    # One match fixes no pose; the paper's method, ranking nothing, needs min_inliers.
    for method, seen, need in (("default", obs[:1], 2), ("pink2008", obs[:2], 3)):
        r = localize(index, seen, prior_at(index, pose), method=method)
        assert r.status == "failed"
        assert "match the map" in r.reason and f"need {need})" in r.reason
        assert r.lat is None and r.hypotheses == []


def test_two_matched_markings_fix_a_pose_when_nothing_matches_three():
    # A sparse map: about two markings in the camera's view. Where exactly two
    # are seen, they fix the pose; while another pose matches three, two-match
    # poses do not compete (covered by the benchmark's scenes).
    rng = np.random.default_rng(5)
    xy, w = random_map(rng, n=300)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    answered = 0
    while answered < 4:
        pose = (ORIGIN[0] + rng.uniform(-60, 60), ORIGIN[1] + rng.uniform(-60, 60), rng.uniform(-3, 3))
        obs = observe(xy, pose).observations
        if len(obs) != 2 or np.hypot(*(obs[0, :2] - obs[1, :2])) < 3.0:
            continue
        prior = prior_at(index, perturb(pose, 0.8, 3.0, rng), 1.0, 3.0)
        r = localize(index, obs, prior)
        assert r.status == "ok" and r.inliers == 2 and r.probability >= 0.95
        e, h = errors(r, pose)
        assert e < 0.05 and h < 0.1
        old = localize(index, obs, prior, options=Options(fallback_min_inliers=3))
        assert old.status == "failed" and "need 3)" in old.reason
        answered += 1


def test_failed_when_the_prior_is_far_from_the_map():
    rng = np.random.default_rng(8)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    obs = observe(xy, (ORIGIN[0], ORIGIN[1], 0.0)).observations
    far = prior_at(index, (ORIGIN[0] + 20_000.0, ORIGIN[1], 0.0))
    r = localize(index, obs, far)
    assert r.status == "failed" and "no map markings" in r.reason
    assert json.loads(json.dumps(r.to_dict(), allow_nan=False))["reason"] == r.reason
    # On the other side of the globe, where the UTM zone's meridian convergence
    # is undefined: the same answer, and no numpy warning on the way.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for method in ("default", "pink2008"):
            r = localize(index, obs, Prior(lat=0.0, lon=180.0, heading_deg=0.0), method=method)
            assert r.status == "failed" and "no map markings" in r.reason


def test_an_empty_map_fails_with_a_reason():
    index = MapIndex.from_arrays([], [], None, CRS)
    assert len(index) == 0
    r = localize(index, [[10.0, 0.0, 5.0]] * 4, prior_at(index, (ORIGIN[0], ORIGIN[1], 0.0)))
    assert r.status == "failed" and "no map markings" in r.reason


def test_empty_observations_fail_with_a_reason():
    index = MapIndex.from_arrays([ORIGIN[0]], [ORIGIN[1]], [1.0], CRS)
    r = localize(index, [], prior_at(index, (ORIGIN[0], ORIGIN[1], 0.0)))
    assert r.status == "failed" and r.reason == "no observations"


# ---------------------------------------------------------------- covariance and result


def test_covariance_is_honest_in_shape_and_degenerate_along_a_solid_line():
    # One straight solid line in 3 m pieces (segments) plus nothing else.
    s = np.arange(-200, 200, 3.0) + 1.5
    xy = ORIGIN + np.column_stack([s, np.zeros_like(s)])
    n = len(s)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS,
                                 bearing_deg=np.full(n, 90.0), length_m=np.full(n, 3.0))
    # Interior pieces are inferred to be a continuous line; the two end pieces are not.
    assert np.all(index.half_length[1:-1] == 1.5) and np.all(index.half_length[[0, -1]] == 0)
    pose = (ORIGIN[0] + 2.0, ORIGIN[1] - 1.8, 0.0)
    line = np.array([[ORIGIN[0] - 200, ORIGIN[1]], [ORIGIN[0] + 200, ORIGIN[1]]])
    smap = SceneMap(marking_xy=np.zeros((0, 2)), marking_kind=np.zeros(0, object), solid_lines=[line])
    scene = simulate_scene(smap, pose, np.random.default_rng(9), Camera(), NONE)
    r = localize(index, scene.observations, prior_at(index, (pose[0] + 1.0, pose[1] + 0.5, 0.02)))
    assert r.status in ("ok", "ambiguous")
    c = r.covariance
    assert c.shape == (3, 3) and np.allclose(c, c.T)
    assert np.all(np.linalg.eigvalsh(c) > 0)
    # Across the line (north) it is well determined, along it (east) only by the prior.
    assert abs(r.northing - pose[1]) < 0.1
    assert math.sqrt(c[1, 1]) < 0.1
    assert math.sqrt(c[0, 0]) > 2.0
    assert math.sqrt(c[0, 0]) > 20 * math.sqrt(c[1, 1])


def test_result_dict_is_json_safe_with_the_api_keys():
    rng = np.random.default_rng(10)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 1.0)
    scene = observe(xy, pose, Camera(), rng)
    r = localize(index, scene.observations, prior_at(index, pose))
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert set(d) == {"status", "lat", "lon", "heading_deg", "easting", "northing", "crs",
                      "yaw_enu_rad", "covariance", "mixture_covariance", "iterations", "inliers",
                      "rms_m", "probability", "hypotheses", "reason"}
    assert d["status"] == "ok" and d["crs"] == CRS and d["reason"] is None
    assert d["mixture_covariance"] is None and d["hypotheses"] == []
    assert Options().ambiguity_probability <= d["probability"] <= 1.0
    assert len(d["covariance"]) == 3 and all(len(row) == 3 for row in d["covariance"])
    assert 0 <= d["heading_deg"] < 360
    # ENU yaw and true heading agree; the transformation maps the vehicle origin.
    assert math.radians(90 - d["heading_deg"]) % (2 * math.pi) == pytest.approx(
        d["yaw_enu_rad"] % (2 * math.pi), abs=1e-9)
    assert r.transformation @ [0, 0, 1] == pytest.approx([r.easting, r.northing, 1])
    assert isinstance(d["iterations"], int) and d["inliers"] >= 3


def test_true_heading_reported_differs_from_grid_by_convergence():
    # Far from the central meridian (6.1°E, 60°N in UTM 32N) the convergence is ~-2.5°.
    crs = "EPSG:32632"
    from localizer import GeoFrame

    frame = GeoFrame(crs)
    cx, cy = frame.to_xy(6.1, 60.0)
    rng = np.random.default_rng(13)
    xy = np.array([cx, cy]) + rng.uniform(-100, 100, (500, 2))
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, crs)
    pose = (cx, cy, math.pi / 2)  # facing grid north
    scene = observe(xy, pose, Camera(), rng)
    lon, lat = frame.to_lonlat(cx, cy)
    prior = Prior(lat=lat, lon=lon, heading_deg=float(frame.convergence_deg(lon, lat)) + 3.0)
    r = localize(index, scene.observations, prior)
    assert r.status == "ok"
    conv = frame.convergence_deg(lon, lat)
    assert conv < -2.0
    assert ((r.heading_deg - conv + 180) % 360 - 180) == pytest.approx(0.0, abs=0.3)
    # arrays of positions, an empty one included (PROJ itself refuses it)
    assert frame.convergence_deg(np.array([lon, lon]), np.array([lat, lat])) == pytest.approx([conv, conv])
    assert frame.convergence_deg(np.zeros(0), np.zeros(0)).shape == (0,)


def test_shared_index_is_thread_safe():
    rng = np.random.default_rng(14)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    jobs = []
    for k in range(8):
        pose = (ORIGIN[0] + rng.uniform(-40, 40), ORIGIN[1] + rng.uniform(-40, 40), rng.uniform(-3, 3))
        scene = observe(xy, pose, Camera(), rng)
        jobs.append((scene.observations, prior_at(index, perturb(pose, 3.0, 5.0, rng))))
    serial = [localize(index, o, p).to_dict() for o, p in jobs]
    with ThreadPoolExecutor(4) as pool:
        parallel = list(pool.map(lambda a: localize(index, *a).to_dict(), jobs * 2))
    assert parallel == serial + serial


# ---------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def small():
    rng = np.random.default_rng(15)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0], ORIGIN[1], 0.5)
    return index, observe(xy, pose).observations, prior_at(index, pose)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda o: np.where(np.arange(o.size).reshape(o.shape) == 0, np.nan, o), "NaN"),
        (lambda o: np.where(np.arange(o.size).reshape(o.shape) == 4, np.inf, o), "infinite"),
        (lambda o: np.column_stack([o[:, :2], np.zeros(len(o))]), "positive"),
        (lambda o: np.column_stack([o[:, :2], -o[:, 2]]), "positive"),
        (lambda o: np.tile(o, (60, 1))[:501], "at most 500"),
        (lambda o: o[:, :1], "shape"),
        (lambda o: "garbage", "not an array"),
        (lambda o: [{"x": 1.0}], "needs keys"),
        (lambda o: [{"x": "a", "y": 1.0}], "numbers"),
        (lambda o: {"x": 1}, "mapping"),
        (lambda o: np.vstack([o, [5000.0, 0.0, 10.0]]), "farther than 150 m"),
    ],
)
def test_bad_observations_raise_a_clear_error(small, mutate, match):
    index, obs, prior = small
    with pytest.raises(LocalizationInputError, match=match):
        localize(index, mutate(obs), prior)


def test_observations_as_dicts_equal_array(small):
    index, obs, prior = small
    dicts = [{"x": x, "y": y, "weight": w} for x, y, w in obs]
    assert localize(index, dicts, prior).to_dict() == localize(index, obs, prior).to_dict()


@pytest.mark.parametrize(
    "kwargs, match",
    [({"lat": 95.0}, "prior.lat"), ({"lon": float("nan")}, "prior.lon"),
     ({"position_sigma_m": 0.0}, "position_sigma_m"), ({"heading_sigma_deg": -1.0}, "heading_sigma"),
     ({"position_sigma_m": -5.0}, "position_sigma_m"), ({"position_sigma_m": 1e-9}, "position_sigma_m"),
     ({"heading_sigma_deg": 1e-12}, "heading_sigma"), ({"heading_sigma_deg": 0.0}, "heading_sigma"),
     ({"position_sigma_m": 1e7}, "position_sigma_m"), ({"heading_sigma_deg": float("nan")}, "heading_sigma"),
     ({"heading_deg": float("inf")}, "heading_deg")],
)
def test_bad_prior_raises(small, kwargs, match):
    index, obs, prior = small
    fields = {**prior.__dict__, **kwargs}
    with pytest.raises(LocalizationInputError, match=match):
        localize(index, obs, Prior(**fields))


@pytest.mark.parametrize(
    "kwargs, match",
    [({"pitch_sigma_deg": 0.0}, "pitch_sigma_deg"), ({"temperature": 0.0}, "temperature"),
     ({"miss_probability": 1.5}, "miss_probability"), ({"noise_m": float("nan")}, "noise_m"),
     ({"anneal_m": ()}, "anneal_m"), ({"anneal_m": (0.8, -0.1)}, "anneal_m"),
     ({"candidates": 0}, "candidates"), ({"min_inliers": 2.5}, "min_inliers"),
     ({"max_iterations": True}, "max_iterations"), ({"search_cell_m": 0.0}, "search_cell_m"),
     ({"view_min_range_m": 30.0}, "view_min_range_m"), ({"ambiguity_probability": 0.0}, "ambiguity"),
     ({"min_search_radius_m": 50.0}, "min_search_radius_m"), ({"null_score": float("inf")}, "null_score"),
     ({"epsilon_m": "0.05"}, "epsilon_m"), ({"extra_candidates": -1}, "extra_candidates"),
     ({"heading_restarts": -1}, "heading_restarts"),
     ({"max_refine_work": 0}, "max_refine_work"),
     ({"heading_restarts": 1.5}, "heading_restarts"),
     ({"extra_search_probability": 1.5}, "extra_search_probability"),
     ({"fallback_min_inliers": 0}, "fallback_min_inliers"),
     ({"iterations_per_scale": 0}, "iterations_per_scale"),
     ({"solid_explain_across_m": -1.0}, "solid_explain_across_m"),
     ({"neighbour_starts": ((1.0, 0.0),)}, "neighbour_starts"),
     ({"neighbour_starts": ((1.0, float("nan"), 0.0),)}, "neighbour_starts")],
)
def test_bad_options_raise_a_clear_error(kwargs, match):
    with pytest.raises(LocalizationInputError, match=f"options.{match}"):
        Options(**kwargs)


def test_edge_options_are_accepted_and_used(small):
    index, obs, prior = small
    for opts in (Options(estimate_pitch=False, pitch_sigma_deg=0.0), Options(null_score=-math.inf),
                 Options(bearing_noise_rad=None, search_cell_m=None, view_half_fov_deg=None)):
        assert localize(index, obs, prior, options=opts).status == "ok"
    assert localize(index, obs, prior, options=Options(iterations_per_scale=1)).status == "ok"
    # Sequences may be lists; the options keep them as tuples (they are hashed).
    listed = Options(anneal_m=[0.8, 0.2, 0.15], neighbour_starts=[[1.5, 0, 0], [-1.5, 0, 0]])
    assert listed.anneal_m == (0.8, 0.2, 0.15) and listed.neighbour_starts == ((1.5, 0.0, 0.0), (-1.5, 0.0, 0.0))
    assert localize(index, obs, prior, options=listed).status == "ok"


def test_bad_method_and_map_inputs_raise(small):
    index, obs, prior = small
    with pytest.raises(LocalizationInputError, match="method"):
        localize(index, obs, prior, method="icp")
    with pytest.raises(LocalizationInputError, match="x"):
        MapIndex.from_arrays([1.0, np.nan], [2.0, 3.0], None, CRS)
    with pytest.raises(LocalizationInputError, match="y: 1 values"):
        MapIndex.from_arrays([1.0, 2.0], [2.0], None, CRS)
    with pytest.raises(LocalizationInputError, match="weight"):
        MapIndex.from_arrays([1.0], [2.0], [0.0], CRS)
    with pytest.raises(LocalizationInputError, match="crs"):
        MapIndex.from_arrays([1.0], [2.0], None, "EPSG:4326")


def test_solid_pieces_are_inferred_and_dashes_stay_points():
    # A solid line of five 3 m pieces continued by a dashed line (3 m dash, 6 m gap).
    solid = [(1.5 + 3 * k, 0.0) for k in range(5)]
    dashes = [(16.5 + 9 * k, 0.0) for k in range(4)]
    xy = ORIGIN + np.array(solid + dashes)
    n = len(xy)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS,
                                 bearing_deg=np.full(n, 90.0), length_m=np.full(n, 3.0))
    assert index.half_length.tolist() == [0, 1.5, 1.5, 1.5, 1.5, 0, 0, 0, 0]
    assert np.allclose(np.abs(index.axis[1:5, 0]), 1.0)
    # Given kinds win over the inference.
    kinds = ["solid"] * 5 + ["dash"] * 4
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, kind=kinds,
                                 bearing_deg=np.full(n, 90.0), length_m=np.full(n, 3.0))
    assert index.half_length.tolist() == [1.5] * 5 + [0] * 4
    # Unknown kinds (None, "") are inferred, known ones are taken as they are.
    mixed = ["solid", None, "", None, None, "dash", None, " ", "Solid "]
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, kind=mixed,
                                 bearing_deg=np.full(n, 90.0), length_m=np.full(n, 3.0))
    assert index.half_length.tolist() == [1.5, 1.5, 1.5, 1.5, 1.5, 0, 0, 0, 1.5]


def test_the_kinds_of_an_imported_map_keep_camera_clusters_on_line_ends_from_pulling():
    # The camera clusters a solid line at its own phase. On the line's end
    # pieces, which the geometry alone leaves point-like, a cluster off the
    # piece's centre matches the centre and drags the pose along the line;
    # with the kinds the index has them as segments and the pose stays put.
    # Two solid lines of four 3 m pieces and one point marking.
    pieces = [(-12.0 + 3 * k, 1.8) for k in range(4)] + [(-4.0 + 3 * k, -1.8) for k in range(4)]
    xy = ORIGIN + np.array(pieces + [(0.0, 5.0)])
    n = len(xy)
    kinds = ["solid"] * 8 + ["dash"]
    args = dict(bearing_deg=np.full(n, 90.0), length_m=[3.0] * 8 + [0.2])
    pose = (ORIGIN[0] - 16.0, ORIGIN[1], 0.0)
    # Clusters 1.2 m ahead of the centres of each line's first piece, one on
    # each line's second piece, and the point marking.
    obs = np.array([[5.2, 1.8, 60.0], [9.0, 1.8, 60.0], [13.2, -1.8, 60.0], [16.5, -1.8, 60.0],
                    [16.0, 5.0, 40.0]])
    prior = prior_at(MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS), pose, 1.0, 3.0)
    # Only the point marking fixes the pose along the lines: a pose 1.4 m
    # along matches the other four observations as well. Restarts beside the
    # answer find it and rightly make the answer ambiguous (asserted below);
    # the pull of the end pieces is compared without them.
    opts = Options(view_max_range_m=None, view_min_range_m=None, view_half_fov_deg=None,
                   neighbour_starts=())
    inferred = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, **args)
    known = MapIndex.from_arrays(xy[:, 0], xy[:, 1], None, CRS, kind=kinds, **args)
    assert inferred.half_length[[0, 3, 4, 7]].tolist() == [0, 0, 0, 0]
    assert np.all(known.half_length[:8] == 1.5) and known.half_length[8] == 0
    pulled = localize(inferred, obs, prior, options=opts)
    right = localize(known, obs, prior, options=opts)
    assert errors(pulled, pose)[0] > 1.0
    assert right.status == "ok" and errors(right, pose)[0] < 0.05 and right.inliers == 5
    doubt = localize(known, obs, prior, options=replace(opts, neighbour_starts=Options().neighbour_starts))
    assert doubt.status == "ambiguous" and errors(doubt, pose)[0] < 0.05
    rival = doubt.hypotheses[1]
    assert 1.0 < math.hypot(rival.easting - pose[0], rival.northing - pose[1]) < 2.0


def test_trace_records_the_default_method_from_prior_to_result():
    rng = np.random.default_rng(16)
    xy, w = random_map(rng)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], w, CRS)
    pose = (ORIGIN[0] + 5.0, ORIGIN[1], -0.5)
    scene = observe(xy, pose, Camera(), rng)
    start = perturb(pose, 3.0, 8.0, rng)
    r = localize(index, scene.observations, prior_at(index, start), options=Options(record_trace=True))
    assert r.status == "ok"
    assert r.trace[0] == pytest.approx(start, abs=1e-6)  # the prior
    assert r.trace[-1] == pytest.approx((r.easting, r.northing, r.yaw_grid_rad), abs=1e-9)
    errs = [math.hypot(t[0] - pose[0], t[1] - pose[1]) for t in r.trace]
    assert errs[1] < 1.5 and errs[-1] < 0.2  # the global search lands near, IRLS finishes

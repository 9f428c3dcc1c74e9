"""The scene simulator: reproducible, geometrically right, with the paper's outliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from localizer.geometry import apply
from localizer.simulate import HEAVY, NONE, Camera, Clutter, oracle_pose, sample_poses, simulate_scene

from ._localizer_helpers import karlsruhe

EXACT = Camera(pitch_sigma_deg=0.0, range_noise_m=0.0, range_noise_coeff=0.0,
               bearing_noise_rad=0.0, miss_probability=0.0)


def test_same_seed_same_scene():
    _, smap = karlsruhe()
    a = simulate_scene(smap, sample_poses(smap, 1, np.random.default_rng(1), min_visible=5)[0],
                       np.random.default_rng(2), Camera(), HEAVY)
    b = simulate_scene(smap, sample_poses(smap, 1, np.random.default_rng(1), min_visible=5)[0],
                       np.random.default_rng(2), Camera(), HEAVY)
    assert np.array_equal(a.observations, b.observations)
    assert np.array_equal(a.label, b.label)


def test_noise_free_inliers_lie_on_the_map_and_in_the_view():
    _, smap = karlsruhe()
    rng = np.random.default_rng(3)
    for pose in sample_poses(smap, 5, rng, min_visible=5):
        s = simulate_scene(smap, pose, rng, EXACT, NONE)
        assert s.inlier.all() and len(s.observations) >= 5
        world = apply(pose, s.observations[:, :2])
        assert np.allclose(world, s.true_xy, atol=1e-6)
        r = np.hypot(s.observations[:, 0], s.observations[:, 1])
        b = np.degrees(np.abs(np.arctan2(s.observations[:, 1], s.observations[:, 0])))
        assert np.all((r >= 4.0) & (r <= 25.0) & (b <= 30.0))
        # Weights like pixel counts: positive and falling with range on average.
        assert np.all(s.observations[:, 2] >= 3)
        near, far = r < np.median(r), r >= np.median(r)
        if near.any() and far.any():
            assert np.median(s.observations[near, 2]) > np.median(s.observations[far, 2])
        # Dashes and stop lines are seen at their map centroids.
        point = np.isin(s.label, ["dash", "stop_line"])
        d = np.min(np.hypot(*(s.true_xy[point, None, :] - smap.marking_xy[None]).transpose(2, 0, 1)), 1)
        assert np.all(d < 1e-9)
        assert oracle_pose(s) == pytest.approx(tuple(pose), abs=1e-6)


def test_outliers_are_labelled_and_range_noise_grows_with_range():
    _, smap = karlsruhe()
    rng = np.random.default_rng(4)
    poses = sample_poses(smap, 30, rng, min_visible=4)
    labels, near_err, far_err = [], [], []
    for pose in poses:
        s = simulate_scene(smap, pose, rng, Camera(pitch_sigma_deg=0.0), HEAVY)
        labels += list(s.label)
        out = ~s.inlier
        assert set(s.label[out]) <= {"curb", "vehicle", "clutter"}
        assert set(s.label[~out]) <= {"dash", "solid", "stop_line"}
        truth_v = np.array([[math.cos(pose[2]), math.sin(pose[2])], [-math.sin(pose[2]), math.cos(pose[2])]])
        v = (truth_v @ (s.true_xy[~out] - pose[:2]).T).T
        err = np.hypot(*(s.observations[~out, :2] - v).T)
        r = np.hypot(*v.T)
        near_err += list(err[r < 10])
        far_err += list(err[r > 18])
    assert {"curb", "vehicle", "clutter", "dash", "solid"} <= set(labels)
    assert np.median(far_err) > 3 * np.median(near_err)


def test_clutter_levels_order():
    _, smap = karlsruhe()
    rng = np.random.default_rng(5)
    poses = sample_poses(smap, 40, rng, min_visible=4)

    def outlier_share(level: Clutter) -> float:
        r = np.random.default_rng(6)
        n = [simulate_scene(smap, p, r, Camera(), level) for p in poses]
        return float(np.mean(np.concatenate([~s.inlier for s in n])))

    none, paper, heavy = outlier_share(NONE), outlier_share(Clutter()), outlier_share(HEAVY)
    assert none == 0.0
    assert 0.1 < paper < 0.45 < heavy


def test_line_aware_oracle_ignores_where_along_a_solid_line_a_cluster_lies():
    _, smap = karlsruhe()
    rng = np.random.default_rng(7)
    for pose in sample_poses(smap, 20, rng, min_visible=3):
        s = simulate_scene(smap, pose, rng, EXACT, NONE)
        solid = s.label == "solid"
        if solid.sum() >= 2 and (~solid).sum() >= 2:
            break
    else:
        pytest.fail("no scene with solid and point-like markings")
    # Slide the solid pieces' true positions along their lines.
    s.true_xy[solid] += 1.2 * s.true_dir[solid]
    assert oracle_pose(s) == pytest.approx(tuple(pose), abs=1e-6)
    moved = oracle_pose(s, line_aware=False)
    assert math.hypot(moved[0] - pose[0], moved[1] - pose[1]) > 0.05

"""A map's edge: what the camera sees beyond it must not make a rival pose sure (Options.edge_share)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from localizer import MapIndex, Options, Prior, localize
from localizer.index import map_extent
from localizer.simulate import Camera, Clutter, perturb, sample_poses, simulate_scene

from ._localizer_helpers import KarlsruheMarkings, karlsruhe


def test_the_extent_is_the_markings_convex_hull():
    xy = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5]], float) + [457000, 5428000]
    hull = map_extent(xy)
    inside = (hull[:, :2] @ [457005, 5428005] + hull[:, 2]).max()
    outside = (hull[:, :2] @ [457013, 5428005] + hull[:, 2]).max()
    assert inside == pytest.approx(-5) and outside == pytest.approx(3)  # metres beyond the nearest side
    assert map_extent(xy[:2]) is None and map_extent(np.array([[0, 0], [1, 1], [2, 2.0]])) is None
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1])
    assert np.allclose(index.hull, hull)


def _edge_scenes(n: int, sigma: float, dist: tuple[float, float], seed: int = 1):
    """Scenes with the map cut 5-25 m ahead of the vehicle, and a prior ``dist`` metres off."""
    whole, smap = karlsruhe()
    marks = KarlsruheMarkings()
    rng = np.random.default_rng(seed)
    for pose in sample_poses(smap, n, rng, Camera(), min_visible=4):
        scene = simulate_scene(smap, pose, rng, Camera(), Clutter())
        init = perturb(pose, rng.uniform(*dist), rng.uniform(-15, 15), rng)
        lon, lat = whole.frame.to_lonlat(init[0], init[1])
        prior = Prior(lat=lat, lon=lon, heading_deg=float(whole.frame.grid_yaw_to_heading(init[2], lon, lat)),
                      position_sigma_m=sigma, heading_sigma_deg=9.0)  # fmt: skip
        yield pose, scene.observations, prior, marks.cut(pose, ends_m=rng.uniform(5.0, 25.0)), whole


def _graded(p, pose):
    if p.easting is None:
        return p.status, math.inf
    return p.status, math.hypot(p.easting - pose[0], p.northing - pose[1])


def test_a_map_ending_ahead_makes_no_rival_sure():
    """From 8-10 m: without the check, rivals a dash period back win surely; with it, none does,
    and the answers say why."""
    without, with_check, reasons = [], [], []
    for pose, obs, prior, cut, _ in _edge_scenes(40, 6.5, (8.0, 10.0)):
        without.append(_graded(localize(cut, obs, prior, options=Options(edge_share=None)), pose))
        p = localize(cut, obs, prior)
        with_check.append(_graded(p, pose))
        if p.reason and p.status == "ambiguous":
            reasons.append(p.reason)
            assert p.hypotheses and p.mixture_covariance is not None
    wrong_without = sum(s == "ok" and e > 1.0 for s, e in without)
    assert wrong_without >= 5, without  # 10 of these 40 (6-10 on other seeds)
    assert not any(s == "ok" and e > 1.0 for s, e in with_check), with_check
    assert reasons and all("beyond the map's edge" in r for r in reasons)


def test_the_check_leaves_a_tight_prior_and_the_inside_of_a_map_alone():
    """A prior of 1 m reaches no rival a dash period away: answers at the edge are as before. On
    the whole map the same wide-prior scenes keep their statuses where the view stays inside."""
    for pose, obs, prior, cut, whole in _edge_scenes(15, 1.0, (0.5, 2.0)):
        a = localize(cut, obs, prior)
        b = localize(cut, obs, prior, options=Options(edge_share=None))
        assert (a.status, a.easting, a.reason) == (b.status, b.easting, b.reason)
    same = 0
    for pose, obs, prior, cut, whole in _edge_scenes(15, 6.5, (8.0, 10.0)):
        a = localize(whole, obs, prior)
        b = localize(whole, obs, prior, options=Options(edge_share=None))
        assert a.easting == b.easting
        same += a.status == b.status
    assert same >= 14


def test_bad_edge_options_are_refused():
    from localizer import LocalizationInputError

    for bad in ({"edge_share": 1.5}, {"edge_share": -0.1}, {"edge_rival_m": -1.0}, {"edge_reach_m": math.nan}):
        with pytest.raises(LocalizationInputError, match=next(iter(bad))):
            Options(**bad)

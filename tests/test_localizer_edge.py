"""A map's edge: what the camera sees beyond it must not make a rival pose sure (Options.edge_share)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from localizer import LocalizationInputError, MapIndex, Options, Prior, localize
from localizer.index import map_extent
from localizer.simulate import Camera, Clutter, perturb, sample_poses, simulate_scene

from ._localizer_helpers import KarlsruheMarkings, karlsruhe


def test_the_hull_extent_is_the_markings_convex_hull_and_a_metre():
    xy = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5]], float) + [457000, 5428000]
    ext = map_extent(xy)
    assert ext.rule == "hull"
    x0, y0 = 457000.0, 5428000.0
    # a point is beyond when more than a metre beyond one of the hull's sides, corners included
    assert not ext.beyond([x0 + 5, x0 + 10.9, x0 + 10.9], [y0 + 5, y0 + 5, y0 + 10.9]).any()
    assert ext.beyond([x0 + 11.1, x0 + 5, x0 + 11.1], [y0 + 5, y0 - 1.1, y0 + 10.5]).all()
    assert map_extent(xy[:2]) is None and map_extent(np.array([[0, 0], [1, 1], [2, 2.0]])) is None
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1])
    assert index.extent_rule == "hull" and index.extent.area.equals(ext.area)


def test_the_markings_extent_ends_where_the_markings_do():
    """Two stretches of a dashed road 200 m apart and a lone stop line: the hull spans the ground
    between them, the markings' extent ends a metre past each."""
    along = np.arange(0.0, 100.0, 9.0)
    road = np.concatenate([np.column_stack([along, np.zeros_like(along)]),
                           np.column_stack([along, np.full_like(along, 3.5)])])  # fmt: skip
    xy = np.concatenate([road, road + [300.0, 0.0], [[150.0, -200.0]]]) + [457000, 5428000]
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], extent="markings")
    ext = index.extent
    assert ext.rule == "markings"
    x = 457000 + np.array([50.0, 4.5, 99.0 + 0.9, 99.0 + 1.1, 200.0, 150.0, 150.0 + 1.1])
    y = 5428000 + np.array([1.75, 1.75, 1.75, 1.75, 1.75, -200.0, -200.0])
    assert ext.beyond(x, y).tolist() == [False, False, False, True, True, False, True]
    hull = MapIndex.from_arrays(xy[:, 0], xy[:, 1]).extent
    assert not hull.beyond(x[:6], y[:6]).any()
    with pytest.raises(LocalizationInputError, match="extent"):
        MapIndex.from_arrays(xy[:, 0], xy[:, 1], extent="convex")


def test_markings_far_from_each_other_are_each_a_metre_around_it():
    """Markings 40 m apart along a bend (sparse detections, the stop lines of a rural road): no
    triangle between them is short enough to keep, so each counts alone, a metre around it, and
    the disks of two that lie closer than two metres are one."""
    t = np.arange(0.0, 4000.0, 40.0)
    xy = np.column_stack([t, 0.002 * (t - 2000.0) ** 2 / 100.0])
    xy = np.concatenate([xy, xy[-1:] + [1.5, 0.0]]) + [457000, 5428000]
    ext = MapIndex.from_arrays(xy[:, 0], xy[:, 1], extent="markings").extent
    x0, y0 = xy[50]
    x1, y1 = xy[-1]
    x = np.array([x0, x0 + 0.9, x0 + 1.1, x0 + 20.0, x0, x0, x1 - 0.75, x1 + 1.1])
    y = np.array([y0, y0, y0, y0, y0 + 0.9, y0 + 1.1, y1, y1])
    assert ext.beyond(x, y).tolist() == [False, False, True, True, False, True, False, True]
    assert shapely.get_num_geometries(ext.area) == len(t)  # one part each, the last two as one


def test_a_stretch_left_out_of_a_map_is_its_edge_with_the_markings_extent():
    """A map with 60 m of road left out 5-25 m ahead, inside the hull of what it holds: by the
    hull a rival a dash period away wins surely; by the markings' extent no answer is sure there."""
    marks = KarlsruheMarkings()
    by_hull, by_markings = [], []
    for pose, obs, prior, _, _ in _edge_scenes(40, 6.5, (8.0, 10.0), seed=3):
        start = float(np.random.default_rng(len(by_hull)).uniform(5.0, 25.0))
        by_hull.append(_graded(localize(marks.gap(pose, start), obs, prior), pose))
        p = localize(marks.gap(pose, start, extent="markings"), obs, prior)
        by_markings.append((*_graded(p, pose), "beyond the map's edge" in (p.reason or "")))
    assert sum(s == "ok" and e > 1.0 for s, e in by_hull) >= 4, by_hull  # 6 of these 40 (4 on seeds 2 and 4)
    assert not any(s == "ok" and e > 1.0 for s, e, _ in by_markings), by_markings
    assert sum(s == "ambiguous" and edge for s, _, edge in by_markings) >= 35, by_markings


def test_an_extent_with_imaged_ground_is_that_ground_and_the_markings_beyond_it():
    """A road imaged along 100 m of its length, dashes on all of it, a lone marking placed by
    hand far beyond: the extent is the imaged ground (grown by a metre) joined to the markings'
    own extent where they leave it; ground inside the hull that nothing vouches for is beyond."""
    import shapely

    x0, y0 = 457000.0, 5428000.0
    along = np.arange(0.0, 160.0, 9.0)
    xy = np.concatenate([np.column_stack([along, np.zeros_like(along)]),
                         np.column_stack([along, np.full_like(along, 3.5)]), [[60.0, 80.0]]]) + [x0, y0]
    imaged = shapely.box(x0 - 10, y0 - 20, x0 + 100, y0 + 20)
    index = MapIndex.from_arrays(xy[:, 0], xy[:, 1], extent="markings", extent_area=imaged)
    ext = index.extent
    assert ext.rule == "markings" and index.extent_area is imaged
    x = x0 + np.array([-9.9, 50.0, 99.0, 130.0, 153.0 + 0.9, 153.0 + 1.1, 60.0, 60.0, 130.0, -10.1, 50.0])
    y = y0 + np.array([-15.0, 19.9, -19.9, 1.75, 1.75, 1.75, 80.5, 40.0, 15.0, -15.0, 20.1])
    # the imaged ground, the road beyond it to a metre past its last dash, the lone marking; not
    # the ground between road and marking, nor beside the road beyond the imagery, nor past the
    # imagery's border: the imaged ground is not grown (nothing is known past it)
    assert ext.beyond(x, y).tolist() == [False, False, False, False, False, True, False, True, True, True, True]
    # a marking beyond the imagery has its metre, as by the markings' rule alone
    assert ext.beyond([x0 + 108.0, x0 + 108.0], [y0 - 0.9, y0 - 1.1]).tolist() == [False, True]
    assert not MapIndex.from_arrays(xy[:, 0], xy[:, 1]).extent.beyond(x[7], y[7])  # the hull's
    # markings inside the imaged ground add nothing to it: the extent is the same without them
    inside = (xy[:, 0] > x0 + 35) & (xy[:, 0] < x0 + 65) & (np.abs(xy[:, 1] - y0) < 5)
    assert inside.sum() >= 6
    assert map_extent(xy[~inside], "markings", area=imaged).area.equals(ext.area)
    # the ground alone makes an extent where the markings do not
    assert not map_extent(xy[:2], "markings", area=imaged).beyond(x0 + 50, y0 + 19.9)
    assert map_extent(xy[:2], "markings", area=shapely.Polygon()) is None
    with pytest.raises(LocalizationInputError, match="extent_area"):
        MapIndex.from_arrays(xy[:, 0], xy[:, 1], extent_area=[(0, 0), (1, 0), (1, 1)])


def test_a_stretch_the_imagery_left_out_is_a_maps_edge_and_the_imaged_ground_is_not():
    """Before a stretch of road the imagery left out (the map built from the rest) no answer is
    sure, as by the markings' extent; on the whole imaged map answers are as sure as by the hull,
    where the markings' extent alone holds most of them back at the ends of the map's parts."""
    marks = KarlsruheMarkings()
    whole = {"imagery": marks.index(extent="markings", extent_area=marks.imaged()),
             "hull": marks.index(), "markings": marks.index(extent="markings")}
    gap, sure = [], {k: 0 for k in whole}
    for i, (pose, obs, prior, _, _) in enumerate(_edge_scenes(40, 6.5, (8.0, 10.0), seed=3)):
        start = float(np.random.default_rng(i).uniform(5.0, 25.0))
        p = localize(marks.gap(pose, start, extent="imagery"), obs, prior)
        gap.append((*_graded(p, pose), "beyond the map's edge" in (p.reason or "")))
        for k, index in whole.items():
            s, e = _graded(localize(index, obs, prior), pose)
            sure[k] += s == "ok" and e <= 0.5
    assert not any(s == "ok" and e > 1.0 for s, e, _ in gap), gap
    assert sum(s == "ambiguous" and edge for s, _, edge in gap) >= 35, gap
    # 24, 23 and 5 of these 40
    assert sure["imagery"] >= sure["hull"] - 1 and sure["imagery"] >= sure["markings"] + 10, sure


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
    the answers say why, and their mixture covariance holds the truth."""
    without, with_check, reasons, inside = [], [], [], []
    for pose, obs, prior, cut, _ in _edge_scenes(40, 6.5, (8.0, 10.0)):
        without.append(_graded(localize(cut, obs, prior, options=Options(edge_share=None)), pose))
        p = localize(cut, obs, prior)
        with_check.append(_graded(p, pose))
        if p.reason and p.status == "ambiguous":
            reasons.append(p.reason)
            assert p.hypotheses and p.mixture_covariance is not None
            # its uncertainty is the prior's at least: the truth in its 95 % ellipse
            mix = np.asarray(p.mixture_covariance)[:2, :2]
            assert np.linalg.eigvalsh(mix - np.eye(2) * 6.5**2).min() > -1e-6
            d = np.array([pose[0] - p.easting, pose[1] - p.northing])
            inside.append(d @ np.linalg.solve(mix, d) <= 5.991)
    assert len(inside) >= 10 and all(inside), inside
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


def test_the_reach_of_the_check_is_measured_from_the_prior_not_from_the_answer():
    """An answer at the side of the prior's region: a rival the prior admits may lie beyond the
    reach counted from the answer. Dashes every 9 m on three lanes up to x = 72 m (the extent
    ends at 73 m); a pose at x = 20 m sees the dashes at 27, 36 and 45 m; the fix's sigma of
    6.5 m reaches 19.5 m. Counted from the answer, the farthest view puts them at 65.5 m at
    most, inside the map; counted from a fix 15.2 m ahead, a third of them lie at 79.7 m."""
    from localizer.core import edge_reason

    x0, y0 = 500_000.0, 5_400_000.0
    xs = np.arange(0.0, 73.0, 9.0)
    rows = np.array([-3.5, 0.0, 3.5])
    x = np.tile(xs, rows.size) + x0
    y = np.repeat(rows, xs.size) + y0
    index = MapIndex.from_arrays(x, y, crs="EPSG:25832")
    pose = (x0 + 20.0, y0 + 1.75, 0.0)
    seen = (x - pose[0] >= 4.0) & (x - pose[0] <= 25.0)
    obs = np.column_stack([x[seen] - pose[0], y[seen] - pose[1], np.full(seen.sum(), 50.0)])
    assert len(obs) == 9
    cov = np.eye(2) * 6.5**2
    assert edge_reason(index, obs, pose, cov, Options()) is None
    assert edge_reason(index, obs, pose, cov, Options(), centre=(pose[0] + 1.0, pose[1])) is None
    why = edge_reason(index, obs, pose, cov, Options(), centre=(pose[0] + 15.2, pose[1] - 2.0))
    assert why is not None and why.startswith("33% of what the camera sees lies beyond the map's edge "
                                              "from 35 m ahead of it, within the prior's reach"), why
    # a fix as far behind reaches past the map's start (at -1 m) instead
    why = edge_reason(index, obs, pose, cov, Options(), centre=(pose[0] - 15.2, pose[1]))
    assert why is not None and "from 35 m behind it" in why
    assert edge_reason(index, obs, pose, cov, Options(), centre=(pose[0] - 5.0, pose[1])) is None


def test_bad_edge_options_are_refused():
    from localizer import LocalizationInputError

    for bad in ({"edge_share": 1.5}, {"edge_share": -0.1}, {"edge_rival_m": -1.0}, {"edge_reach_m": math.nan}):
        with pytest.raises(LocalizationInputError, match=next(iter(bad))):
            Options(**bad)


def _drive_frames(smap, drive, rng) -> list:
    """The camera frames of ``drive`` (scenes with the default clutter), each with exact odometry."""
    from localizer.simulate import odometry
    from localizer.track import Frame

    return [Frame(simulate_scene(smap, tuple(p), rng, Camera(), Clutter()).observations,
                  odometry(drive[k - 1], p) if k else (0.0, 0.0, 0.0)) for k, p in enumerate(drive)]


def _drives_onto_a_map(n: int, seed: int = 2):
    """Drives of 12 frames onto a map that begins 4-20 m ahead of the first, from 8-10 m priors."""
    from localizer.simulate import sample_trajectories

    whole, smap = karlsruhe()
    marks = KarlsruheMarkings()
    rng = np.random.default_rng(seed)
    for drive in sample_trajectories(smap, n, 12, 1.5, rng, Camera(), min_visible=4):
        frames = _drive_frames(smap, drive, rng)
        init = perturb(drive[0], rng.uniform(8.0, 10.0), rng.uniform(-15, 15), rng)
        lon, lat = whole.frame.to_lonlat(init[0], init[1])
        prior = Prior(lat=lat, lon=lon, heading_deg=float(whole.frame.grid_yaw_to_heading(init[2], lon, lat)),
                      position_sigma_m=6.5, heading_sigma_deg=9.0)  # fmt: skip
        yield drive, frames, prior, marks.cut(drive[0], begins_m=rng.uniform(4.0, 20.0)), whole


def test_a_drive_onto_a_map_follows_no_rival_surely():
    """A drive whose first frames see ground the map does not hold: without the check a track a
    dash period ahead of the truth wins for good; with it, no frame is sure and wrong, and the
    held-back frames say why."""
    from localizer.track import localize_sequence

    wrong_without, wrong_with, reasons = 0, 0, []
    for drive, frames, prior, cut, _ in _drives_onto_a_map(16):
        for options, counter in ((Options(edge_share=None), "without"), (None, "with")):
            r = localize_sequence(cut, frames, prior, options=options)
            wrong = sum(p.status == "ok" and math.hypot(p.easting - t[0], p.northing - t[1]) > 1.0
                        for p, t in zip(r.poses, drive))
            if counter == "without":
                wrong_without += wrong
            else:
                wrong_with += wrong
                reasons += [p.reason for p in r.poses if p.status == "ambiguous" and p.reason]
    assert wrong_without >= 12, wrong_without  # frames of 4 of these 16 drives
    assert wrong_with == 0
    assert reasons and all("beyond the map's edge" in s for s in reasons)


def test_an_established_drive_keeps_its_answers_and_its_state_says_so():
    """On the whole map the same drives are sure where they were, their tracks established; a
    state without the flag (from before it was kept) is established again at its next frame."""
    from localizer.core import edge_reason
    from localizer.track import Frame, TrackState, localize_sequence

    continued = 0
    for drive, frames, prior, _, whole in _drives_onto_a_map(4):
        a = localize_sequence(whole, frames, prior)
        b = localize_sequence(whole, frames, prior, options=Options(edge_share=None))
        assert [p.status for p in a.poses] == [p.status for p in b.poses]
        assert [p.easting for p in a.poses] == [p.easting for p in b.poses]
        best, cov = a.state.tracks[0][:3], np.array(a.state.gps_covariance)[:2, :2]
        if a.pose.status != "ok" or edge_reason(whole, np.asarray(frames[-1].observations), best, cov, Options()):
            continue  # not sure, or sure since before the whole map's own edge came within reach
        continued += 1
        data = a.state.to_dict()
        assert data["tracks"][0]["established"] is True
        again = TrackState.from_dict(data)
        assert again == a.state
        for t in data["tracks"]:
            del t["established"]
        old = TrackState.from_dict(data)
        assert not any(t[7] for t in old.tracks)
        more = localize_sequence(whole, [Frame(frames[-1].observations, (0.0, 0.0, 0.0))], state=old)
        assert more.pose.status == "ok" and more.state.tracks[0][7] is True
    assert continued >= 2


def test_a_drive_up_to_a_map_that_ends_is_not_sure_of_a_pose_a_period_back():
    """The handover case with no overlap: a drive starting 22 m before the map ends, from a
    3 m fix. Without the check it follows a pose one dash period back, `ok`, frame after frame;
    with it every frame before the end is `ambiguous`, most saying why (the others were not sure)."""
    from localizer.simulate import sample_trajectories
    from localizer.track import localize_sequence

    whole, smap = karlsruhe()
    rng = np.random.default_rng(4)
    drive = sample_trajectories(smap, 1, 30, 1.5, rng, Camera(), min_visible=6)[0]
    frames = _drive_frames(smap, drive, rng)
    heading = np.array([math.cos(drive[0][2]), math.sin(drive[0][2])])
    ends = float((0.5 * (drive[-1][:2] - drive[0][:2])) @ heading)
    assert 20.0 < ends < 24.0
    cut = KarlsruheMarkings().cut(drive[0], ends_m=ends)
    lon, lat = whole.frame.to_lonlat(drive[0][0] + 1.5, drive[0][1] - 1.0)
    prior = Prior(lat=lat, lon=lon, heading_deg=float(whole.frame.grid_yaw_to_heading(drive[0][2] + 0.05, lon, lat)),
                  position_sigma_m=3.0, heading_sigma_deg=8.0)  # fmt: skip
    before = [k for k, p in enumerate(drive) if (p[:2] - drive[0][:2]) @ heading < ends]
    without = localize_sequence(cut, frames, prior, options=Options(edge_share=None)).poses
    held = localize_sequence(cut, frames, prior).poses
    off = [math.hypot(p.easting - t[0], p.northing - t[1]) for p, t in zip(without, drive)]
    assert sum(without[k].status == "ok" and off[k] > 8.0 for k in before) >= 10
    assert not any(p.status == "ok" and math.hypot(p.easting - t[0], p.northing - t[1]) > 1.0
                   for p, t in zip(held, drive))
    assert all(held[k].status == "ambiguous" for k in before)
    assert sum("map's edge" in (held[k].reason or "") for k in before) >= len(before) // 2


def test_an_index_kept_in_a_file_answers_as_the_index_it_copies():
    """A pickled index (the service keeps a city's in a file between processes) is read-only, its
    extent prepared for point queries, its coordinate conversions working, and it localizes the
    same frames to the same poses, the check at a map's edge included."""
    import pickle

    reasons = set()
    for _pose, obs, prior, cut, _whole in _edge_scenes(4, 6.5, (8.0, 10.0)):
        _ = cut.extent
        copy = pickle.loads(pickle.dumps(cut, protocol=5))
        assert copy is not cut and len(copy) == len(cut)
        for name in ("xy", "weight", "axis", "half_length", "expect_xy", "expect_owner", "expect_solid"):
            assert not getattr(copy, name).flags.writeable, name
        assert shapely.is_prepared(copy.extent.area) and copy.extent.area.equals(cut.extent.area)
        assert copy.frame.to_xy(8.4152842, 49.0051049) == cut.frame.to_xy(8.4152842, 49.0051049)
        a, b = localize(cut, obs, prior), localize(copy, obs, prior)
        assert (a.status, a.reason, a.probability) == (b.status, b.reason, b.probability)
        assert (a.easting, a.northing, a.heading_deg) == (b.easting, b.northing, b.heading_deg)
        reasons.add(a.reason is not None)
    assert True in reasons  # the edge check spoke in at least one

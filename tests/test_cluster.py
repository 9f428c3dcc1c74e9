"""Clustering marking pixels and measuring the clusters."""

from __future__ import annotations

import math

import numpy as np
import pytest
from affine import Affine
from skimage.draw import polygon

from mapbuilder.cluster import (
    ClusterParams,
    detect_markings,
    label_pixels,
    measure_clusters,
    split_long,
)
from tests._build_helpers import stall_centres

X0, Y0 = 456000.0, 5430000.0


def _grid(res):
    return Affine(res, 0, X0, 0, -res, Y0)


def _draw(img, transform, cx, cy, length, width, bearing_deg, value=1.0):
    """Paint a rectangle centred at world (cx, cy) with its long axis along a bearing."""
    b = math.radians(bearing_deg)
    u = np.array([math.sin(b), math.cos(b)])
    v = np.array([u[1], -u[0]])
    corners = [np.array([cx, cy]) + su * length / 2 * u + sv * width / 2 * v
               for su, sv in [(-1, -1), (1, -1), (1, 1), (-1, 1)]]
    inv = ~transform
    cr = np.array([inv @ tuple(p) for p in corners]) - 0.5  # pixel centres at integers
    rr, cc = polygon(cr[:, 1], cr[:, 0], img.shape)
    img[rr, cc] = value
    return len(rr)


def _angle_diff(a, b):
    d = (np.asarray(a) - np.asarray(b)) % 180.0
    return np.minimum(d, 180.0 - d)


def test_measures_centroid_bearing_length_width_of_rectangles():
    res = 0.04
    t = _grid(res)
    img = np.zeros((800, 800), np.float32)
    rng = np.random.default_rng(1)
    truth = []
    for i in range(9):
        cx = X0 + 4 + (i % 3) * 11 + rng.uniform(-1, 1)
        cy = Y0 - 4 - (i // 3) * 11 + rng.uniform(-1, 1)
        bearing = rng.uniform(0, 180)
        length = rng.uniform(1.0, 3.0)
        width = rng.uniform(0.12, 0.45)
        score = rng.uniform(0.6, 0.95)
        n = _draw(img, t, cx, cy, length, width, bearing, score)
        truth.append((cx, cy, bearing, length, width, score, n))
    labels, n = label_pixels(img, None, 0.5)
    c = measure_clusters(labels, img, t, n)
    assert len(c) == 9
    for cx, cy, bearing, length, width, score, npx in truth:
        i = int(np.argmin(np.hypot(c.x - cx, c.y - cy)))
        assert math.hypot(c.x[i] - cx, c.y[i] - cy) < 0.01
        assert _angle_diff(c.bearing_deg[i], bearing) < 1.5
        assert c.length_m[i] == pytest.approx(length, abs=0.06)
        assert c.width_m[i] == pytest.approx(width, abs=0.03)
        assert c.weight[i] == npx
        assert c.score[i] == pytest.approx(score, rel=1e-5)
        # End points lie on the axis, length apart, in the direction of the bearing.
        dx, dy = c.x1[i] - c.x0[i], c.y1[i] - c.y0[i]
        assert math.hypot(dx, dy) == pytest.approx(c.length_m[i], rel=1e-6)
        assert math.degrees(math.atan2(dx, dy)) % 360 == pytest.approx(c.bearing_deg[i], abs=1e-6)
        assert 0 <= c.bearing_deg[i] < 180
        # Pixel centroid agrees with the world centroid.
        assert t.c + c.col[i] * res == pytest.approx(c.x[i], abs=1e-6)
        assert t.f - c.row[i] * res == pytest.approx(c.y[i], abs=1e-6)


@pytest.mark.parametrize("bearing", [0.0, 45.0, 90.0, 135.0])
def test_bearing_is_clockwise_from_north(bearing):
    t = _grid(0.05)
    img = np.zeros((200, 200), np.float32)
    _draw(img, t, X0 + 5, Y0 - 5, 3.0, 0.2, bearing)
    c = detect_markings(img, None, t)
    assert len(c) == 1
    assert _angle_diff(c.bearing_deg[0], bearing) < 0.5


def test_shapes_no_marking_has_are_dropped():
    t = _grid(0.05)
    img = np.zeros((400, 400), np.float32)
    _draw(img, t, X0 + 5, Y0 - 5, 2.5, 0.15, 30)     # a dash: kept
    _draw(img, t, X0 + 12, Y0 - 5, 4.0, 1.8, 0)      # a car roof: too wide
    _draw(img, t, X0 + 5, Y0 - 14, 0.1, 0.1, 0)      # a speck: too small
    _draw(img, t, X0 + 14, Y0 - 14.01, 2.0, 0.03, 90)  # a thin crack: too narrow
    c = detect_markings(img, None, t)
    assert len(c) == 1
    assert c.x[0] == pytest.approx(X0 + 5, abs=0.02)


def test_invalid_pixels_are_never_marking_pixels():
    t = _grid(0.05)
    img = np.zeros((200, 200), np.float32)
    _draw(img, t, X0 + 5, Y0 - 5, 2.5, 0.15, 0)
    valid = np.ones_like(img, bool)
    valid[:, :] = False
    assert len(detect_markings(img, valid, t)) == 0


def test_long_lines_are_cut_into_short_pieces():
    res = 0.05
    t = _grid(res)
    img = np.zeros((600, 600), np.float32)
    npx = _draw(img, t, X0 + 15, Y0 - 15, 20.0, 0.15, 60)
    c = detect_markings(img, None, t, ClusterParams(max_length_m=3.0, min_length_m=0.1,
                                                     min_area_m2=0.005))
    assert 7 <= len(c) <= 9
    assert c.length_m.max() <= 3.0 + 2 * res
    assert c.weight.sum() >= 0.99 * npx  # only slivers at the ends may drop out
    # Every piece lies on the line and keeps its direction.
    u = np.array([math.sin(math.radians(60)), math.cos(math.radians(60))])
    off = np.column_stack([c.x - X0 - 15, c.y - Y0 + 15])
    assert np.abs(off @ np.array([u[1], -u[0]])).max() < 0.02
    assert _angle_diff(c.bearing_deg, 60).max() < 1.0
    # Every piece, the two at the line's ends too, knows it is one.
    assert c.piece.dtype == bool and c.piece.all()
    # A marking not much longer than a piece (a 3 m dash) is not cut.
    img[:] = 0
    _draw(img, t, X0 + 15, Y0 - 15, 3.2, 0.15, 10)
    dash = detect_markings(img, None, t)
    assert len(dash) == 1 and not dash.piece.any()


def test_cuts_do_not_depend_on_the_window():
    """Two overlapping windows of one long line cut it at the same places."""
    res = 0.05
    t = _grid(res)
    img = np.zeros((400, 1600), np.float32)
    _draw(img, t, X0 + 40, Y0 - 10, 76.0, 0.15, 88)
    params = ClusterParams(min_length_m=0.1, min_area_m2=0.005)
    a = detect_markings(img[:, :900], None, t, params)
    b_t = t @ Affine.translation(700, 0)
    b = detect_markings(img[:, 700:], None, b_t, params)
    # Pieces well inside both windows (x 36..44 m) must be identical.
    sel_a = (a.x > X0 + 37) & (a.x < X0 + 43)
    sel_b = (b.x > X0 + 37) & (b.x < X0 + 43)
    assert sel_a.sum() >= 2
    np.testing.assert_allclose(np.sort(a.x[sel_a]), np.sort(b.x[sel_b]), atol=1e-9)
    np.testing.assert_array_equal(np.sort(a.weight[sel_a]), np.sort(b.weight[sel_b]))


def test_a_dash_broken_by_wear_is_joined():
    res = 0.05
    t = _grid(res)
    img = np.zeros((200, 200), np.float32)
    _draw(img, t, X0 + 5, Y0 - 4.2, 1.3, 0.15, 0)
    _draw(img, t, X0 + 5, Y0 - 5.8, 1.3, 0.15, 0)   # a 0.3 m worn gap
    apart = detect_markings(img, None, t, ClusterParams(min_length_m=0.1, join_gap_m=0))
    assert len(apart) == 2
    for params in (ClusterParams(min_length_m=0.1, join_gap_m=0.6),  # collinear join
                   ClusterParams(link_m=0.4, min_length_m=0.1, join_gap_m=0)):  # link distance
        joined = detect_markings(img, None, t, params)
        assert len(joined) == 1
        assert joined.length_m[0] == pytest.approx(2.9, abs=0.1)
        assert joined.y[0] == pytest.approx(Y0 - 5.0, abs=0.02)
        assert joined.weight[0] == apart.weight.sum()


def test_only_continuing_clusters_are_joined():
    res = 0.05
    t = _grid(res)
    img = np.zeros((300, 300), np.float32)
    # A double line: parallel, 0.25 m between centres, side by side.
    _draw(img, t, X0 + 3, Y0 - 5, 3.0, 0.12, 0)
    _draw(img, t, X0 + 3.25, Y0 - 5, 3.0, 0.12, 0)
    # Two dashes 1.5 m apart end to end: a gap, not wear.
    _draw(img, t, X0 + 8, Y0 - 2.5, 2.0, 0.15, 0)
    _draw(img, t, X0 + 8, Y0 - 6.0, 2.0, 0.15, 0)
    # A stall line ending 0.2 m before a perpendicular line.
    _draw(img, t, X0 + 12, Y0 - 4, 2.0, 0.12, 0)
    _draw(img, t, X0 + 12, Y0 - 5.3, 3.0, 0.12, 90)
    c = detect_markings(img, None, t, ClusterParams(min_length_m=0.1, join_gap_m=1.0))
    assert len(c) == 6


def test_split_long_keeps_short_clusters():
    t = _grid(0.1)
    labels = np.zeros((50, 50), np.int32)
    labels[10:12, 5:20] = 1
    out, n = split_long(labels, t)
    assert n == 1
    np.testing.assert_array_equal(out > 0, labels > 0)


def test_bad_params_are_rejected():
    with pytest.raises(ValueError, match="threshold"):
        ClusterParams(threshold=1.5)
    with pytest.raises(ValueError, match="width"):
        ClusterParams(min_width_m=0.7)
    for low in (0.0, 0.2, 0.3):
        with pytest.raises(ValueError, match="threshold_low"):
            ClusterParams(threshold=0.2, threshold_low=low)
    for angle in (0.0, -10.0, 120.0):
        with pytest.raises(ValueError, match="junction_angle_deg"):
            ClusterParams(junction_angle_deg=angle)


def test_a_hairpin_is_cut_into_single_strokes():
    """Both legs of a U fall in the same cut bins; each piece must still be one stroke."""
    res = 0.05
    t = _grid(res)
    img = np.zeros((400, 400), np.float32)
    _draw(img, t, X0 + 10, Y0 - 6, 10.0, 0.15, 90)
    _draw(img, t, X0 + 10, Y0 - 6.8, 10.0, 0.15, 90)
    _draw(img, t, X0 + 14.95, Y0 - 6.4, 0.95, 0.15, 0)   # the bend joining the legs
    c = detect_markings(img, None, t, ClusterParams(min_length_m=0.1, min_area_m2=0.005))
    assert len(c) >= 7
    legs = (c.width_m < 0.3) & (_angle_diff(c.bearing_deg, 90.0) < 5.0)
    assert set(np.round(c.y[legs] - Y0, 1)) <= {-6.0, -6.8}
    # what is not a piece of a leg is the bend, a stroke of its own
    bend = ~legs
    assert bend.sum() <= 1
    assert np.all(np.abs(c.x[bend] - (X0 + 14.95)) < 0.1)


def test_hysteresis_keeps_faint_parts_attached_to_a_marking():
    t = _grid(0.05)
    prob = np.zeros((200, 200), np.float32)
    _draw(prob, t, X0 + 5, Y0 - 4.0, 1.5, 0.15, 0, value=0.9)
    _draw(prob, t, X0 + 5, Y0 - 5.5, 1.5, 0.15, 0, value=0.35)   # its faint, worn half
    _draw(prob, t, X0 + 8, Y0 - 5.0, 2.0, 0.15, 0, value=0.35)   # faint noise on its own
    plain = detect_markings(prob, None, t)
    assert len(plain) == 1 and plain.length_m[0] == pytest.approx(1.5, abs=0.1)
    hyst = detect_markings(prob, None, t, ClusterParams(threshold_low=0.3))
    assert len(hyst) == 1
    assert hyst.length_m[0] == pytest.approx(3.0, abs=0.1)
    assert hyst.x[0] == pytest.approx(X0 + 5, abs=0.02)


def _stripe_image(res, sides):
    """A vertical 0.15 m white stripe at x = 10 m; ``sides`` = (left, right) grey levels
    beyond 0.05 m from it (the near surround stays asphalt on the left)."""
    h, w = 200, 300
    x = (np.arange(w) + 0.5) * res
    img = np.full((h, w, 3), 70, np.uint8)
    img[:, (x >= 10.0) & (x < 10.15)] = 210
    img[:, x >= 10.2] = sides[1]
    img[:, x < 9.95] = sides[0]
    return img


def test_context_features_tell_one_sided_from_two_sided_stripes():
    from mapbuilder.cluster import CONTEXT_FEATURES, context_features

    res = 0.05
    t = _grid(res)
    prob = np.zeros((200, 300), np.float32)
    x = (np.arange(300) + 0.5) * res
    prob[:, (x >= 10.0) & (x < 10.15)] = 0.9
    c = detect_markings(prob, None, t)
    assert len(c) >= 1
    f = dict(zip(CONTEXT_FEATURES, context_features(c, _stripe_image(res, (70, 70)), None, t).T))
    g = dict(zip(CONTEXT_FEATURES, context_features(c, _stripe_image(res, (70, 160)), None, t).T))
    # paint on asphalt: much brighter than both sides, which are alike
    assert np.all(f["contrast_near"] > 0.5) and np.all(f["side_difference_far"] < 0.02)
    # a kerb: the far side is bright sidewalk
    assert np.all(g["side_difference_far"] > 0.3) and np.all(g["contrast_far"] < 0.25)
    assert np.allclose(f["width"], 0.15, atol=0.03)
    assert np.allclose(f["spread_ratio"], 1.0, atol=0.15)
    # samples in nodata carry no evidence (zeros), never NaN
    valid = np.ones((200, 300), bool)
    valid[:, :150] = False
    h = context_features(c, _stripe_image(res, (70, 70)), valid, t)
    assert np.isfinite(h).all()


def test_detect_markings_applies_a_verifier_only_when_asked():
    from mapbuilder.cluster import CONTEXT_FEATURES

    class Half:
        """Accepts every other cluster."""

        def predict(self, feats):
            assert feats.shape[1] == len(CONTEXT_FEATURES)
            return np.array([0.9 if i % 2 else 0.1 for i in range(len(feats))], np.float32)

    res = 0.05
    t = _grid(res)
    img = np.zeros((400, 400), np.float32)
    for i in range(4):
        _draw(img, t, X0 + 3 + 4 * i, Y0 - 10, 2.0, 0.15, 0.0, 0.9)
    rgb = np.full((400, 400, 3), 70, np.uint8)
    rgb[img > 0] = 210
    assert len(detect_markings(img, None, t)) == 4
    assert len(detect_markings(img, None, t, ClusterParams(), rgb=rgb, verifier=Half())) == 4
    kept = detect_markings(img, None, t, ClusterParams(verify=True), rgb=rgb, verifier=Half())
    assert len(kept) == 2


def test_rejected_pieces_that_continue_an_accepted_line_are_taken_back():
    from mapbuilder.cluster import Clusters, continues_accepted

    def clusters(segs):
        segs = np.array(segs, float)
        x0, y0, x1, y1 = segs.T
        length = np.hypot(x1 - x0, y1 - y0)
        z = np.zeros(len(segs))
        return Clusters(x=(x0 + x1) / 2, y=(y0 + y1) / 2, col=z, row=z,
                        weight=np.ones(len(segs), np.int64), length_m=length,
                        width_m=z + 0.15,
                        bearing_deg=np.degrees(np.arctan2(x1 - x0, y1 - y0)) % 180,
                        x0=x0, y0=y0, x1=x1, y1=y1, score=z + 0.8, spread_m=z + 0.15)

    c = clusters([
        (0, 0, 3, 0), (3.2, 0, 6.2, 0), (6.4, 0.02, 9.4, 0.02),  # one line, three pieces
        (9.7, 0.5, 12.7, 0.5),  # beyond its end but 0.5 m to the side: another line
        (3.5, 0.4, 3.5, 2.4),  # across it
        (20, 0, 23, 0), (23.2, 0, 26.2, 0),  # a kerb: both pieces rejected
    ])
    keep = np.array([True, False, False, False, False, False, False])
    got = continues_accepted(c, keep)
    # the second piece continues the first, the third the second
    assert got.tolist() == [True, True, True, False, False, False, False]
    assert continues_accepted(c, keep, rounds=1).tolist()[:3] == [True, True, False]
    assert not continues_accepted(c, np.zeros(7, bool)).any()

    # A kerb the verifier accepts in one place: its neighbour, rejected outright
    # (probability below the floor), is not taken back, nor anything beyond it;
    # a piece it only doubts is.
    keep = np.array([True, False, False, False, False, True, False])
    prob = np.array([0.9, 0.02, 0.3, 0.3, 0.3, 0.7, 0.3])
    got = continues_accepted(c, keep, prob=prob, min_prob=0.15)
    assert got.tolist() == [True, False, False, False, False, True, True]
    prob[1] = 0.2
    got = continues_accepted(c, keep, prob=prob, min_prob=0.15)
    assert got.tolist()[:3] == [True, True, True]
    assert continues_accepted(c, keep, prob=prob, min_prob=0.25).tolist()[:3] == [
        True, False, False]


def test_the_continuation_floor_is_a_probability():
    ClusterParams(verify_continuation_min=0.0)
    ClusterParams(verify_threshold=0.05)  # a loose verifier keeps the default floor
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="verify_continuation_min"):
            ClusterParams(verify_continuation_min=bad)


def test_wide_short_clusters_stay_whole():
    """A stop line (0.5 m wide, 6 m across the road) is one marking; a solid line of
    the same length, or a wide line longer than a carriageway, is cut into pieces."""
    res = 0.1
    t = _grid(res)
    img = np.zeros((300, 500), np.float32)
    _draw(img, t, X0 + 10, Y0 - 5, 6.0, 0.5, 90.0)  # stop line
    _draw(img, t, X0 + 10, Y0 - 12, 6.0, 0.15, 90.0)  # solid lane line
    _draw(img, t, X0 + 25, Y0 - 20, 12.0, 0.5, 90.0)  # wide line, 12 m
    c = detect_markings(img, None, t)
    by_row = {round(Y0 - y): sorted(np.round(c.length_m[np.abs(c.y - y) < 0.5], 1).tolist())
              for y in (Y0 - 5, Y0 - 12, Y0 - 20)}
    assert by_row[5] == [6.0]
    assert len(by_row[12]) >= 2 and max(by_row[12]) <= 3.6  # cut on the world grid
    assert sum(by_row[12]) == pytest.approx(6.0, abs=0.2)
    assert len(by_row[20]) >= 4 and max(by_row[20]) <= 3.6
    assert abs(c.x[np.abs(c.y - (Y0 - 5)) < 0.5][0] - (X0 + 10)) < 0.05
    # only the cut clusters are pieces: the stop line kept whole is not
    np.testing.assert_array_equal(c.piece, np.abs(c.y - (Y0 - 5)) >= 0.5)
    assert len(c.take(c.piece)) == len(c) - 1 and len(c.take(np.zeros(len(c), bool)).piece) == 0
    # the old behaviour on request
    cut = detect_markings(img, None, t, ClusterParams(whole_width_m=None))
    assert np.sum(np.abs(cut.y - (Y0 - 5)) < 0.5) >= 2


def test_long_clusters_rejected_in_the_middle_are_checked_on_their_halves():
    """A 3.4 m line with a car beside one end: a crop verifier that rejects any crop with
    something bright beside the line rejects the centre crop and the crop on that half,
    accepts the crop on the other half, so the line is kept; a 1.5 m one is not re-checked."""
    from mapbuilder.cluster import CROP_ACROSS, halves_accepted

    class Clean:
        """A crop verifier: paint when nothing bright lies beside the crop's middle rows."""

        kind = "crops"

        def __init__(self):
            self.asked = 0

        def predict_crops(self, crops, scalars):
            self.asked += len(crops)
            mid = CROP_ACROSS // 2
            side = np.concatenate([crops[:, 0, :mid - 3], crops[:, 0, mid + 3:]], axis=1)
            return np.where(side.max(axis=(1, 2)) > 0.5, 0.05, 0.95).astype(np.float32)

        def predict_clusters(self, clusters, rgb, valid, transform, prob):
            from mapbuilder.cluster import cluster_crops

            return self.predict_crops(*cluster_crops(clusters, rgb, valid, transform, prob))

    res = 0.1
    t = _grid(res)
    prob = np.zeros((200, 300), np.float32)
    _draw(prob, t, X0 + 10, Y0 - 10, 3.4, 0.15, 90.0, 0.9)  # the line, x 8.3-11.7
    _draw(prob, t, X0 + 20, Y0 - 10, 1.5, 0.15, 90.0, 0.9)  # a short one
    rgb = np.full((200, 300, 3), 70, np.uint8)
    rgb[prob > 0] = 210
    car = np.zeros_like(prob)
    _draw(car, t, X0 + 8.6, Y0 - 10.6, 0.6, 0.5, 90.0)  # bright car body beside its west end
    _draw(car, t, X0 + 20, Y0 - 10.6, 1.0, 0.5, 90.0)  # and beside the short one
    rgb[car > 0] = 230
    v = Clean()
    plain = ClusterParams(verify=True, verify_halves_m=0)
    assert len(detect_markings(prob, None, t, plain, rgb=rgb, verifier=v)) == 0
    kept = detect_markings(prob, None, t, ClusterParams(verify=True), rgb=rgb, verifier=v)
    assert len(kept) == 1 and abs(kept.x[0] - (X0 + 10)) < 0.1
    # only long rejected clusters cost extra crops: two per cluster
    c = detect_markings(prob, None, t)
    v.asked = 0
    got = halves_accepted(c, np.ones(len(c), bool), v, rgb, None, t, prob)
    assert got.tolist() == [abs(x - (X0 + 10)) < 0.1 for x in c.x] and v.asked == 2
    # context verifiers are not asked
    v.kind = "context"
    assert not halves_accepted(c, np.ones(len(c), bool), v, rgb, None, t, prob).any()


def _comb(res):
    """A 14 m line (bearing 90°) with four 3.4 m stall lines ending on it at 60° to it."""
    t = _grid(res)
    img = np.zeros((int(12 / res), int(24 / res)), np.float32)
    _draw(img, t, X0 + 12, Y0 - 9, 14.0, 0.12, 90.0)
    stalls = stall_centres((X0 + 7, Y0 - 9), 4, 3.0, 3.4, 30.0)
    for cx, cy in stalls:
        _draw(img, t, cx, cy, 3.4, 0.12, 30.0)
    return t, img, stalls


def test_lines_meeting_at_a_junction_are_separate_markings():
    """Stall lines that end on a line are one cluster with it until the junction is cut."""
    from mapbuilder.cluster import split_junctions

    res = 0.1
    t, img, stalls = _comb(res)
    params = ClusterParams(min_length_m=0.3)
    c = detect_markings(img, None, t, params)
    d = np.hypot(c.x[:, None] - stalls[:, 0], c.y[:, None] - stalls[:, 1])
    near = d.argmin(axis=0)
    assert d.min(axis=0).max() < 0.15
    assert _angle_diff(c.bearing_deg[near], 30.0).max() < 3.0
    assert np.all(c.length_m[near] > 3.1) and np.all(c.length_m[near] < 3.6)
    # the line they end on is still found along its whole length
    on_line = (np.abs(c.y - (Y0 - 9)) < 0.1) & (_angle_diff(c.bearing_deg, 90.0) < 3.0)
    assert c.length_m[on_line].sum() == pytest.approx(14.0, abs=0.5)
    # without the junction cut the stall lines are lost in the comb's pieces
    whole = detect_markings(img, None, t, ClusterParams(min_length_m=0.3,
                                                        junction_angle_deg=None))
    dw = np.hypot(whole.x[:, None] - stalls[:, 0], whole.y[:, None] - stalls[:, 1])
    assert dw.min(axis=0).max() > 0.5
    # the labels themselves: one comb in; out, each stall line one part of its own
    labels, n = label_pixels(img)
    assert n == 1
    rows, cols = np.nonzero(labels)
    lab = split_junctions(rows, cols, labels[rows, cols], res)
    for cx, cy in stalls:
        one = np.zeros_like(img)
        _draw(one, t, cx, cy, 3.4, 0.12, 30.0)
        mine = one[rows, cols] > 0
        part = np.bincount(lab[mine]).argmax()
        assert (lab[mine] == part).mean() > 0.9
        assert (mine[lab == part]).mean() > 0.9
    # clusters larger than any group of touching markings are left alone
    big = split_junctions(rows, cols, labels[rows, cols], res, max_area_m2=2.0)
    assert big.max() == 1


def test_a_stop_line_meeting_a_lane_line_keeps_its_own_centroid():
    res = 0.1
    t = _grid(res)
    img = np.zeros((250, 300), np.float32)
    _draw(img, t, X0 + 15, Y0 - 20, 26.0, 0.15, 0.0)  # lane line, north-south
    _draw(img, t, X0 + 15 + 3.0 + 0.07, Y0 - 12, 6.0, 0.5, 90.0)  # stop line ending on it
    c = detect_markings(img, None, t)
    stop = np.flatnonzero(c.width_m > 0.3)
    assert len(stop) == 1
    i = stop[0]
    assert c.x[i] == pytest.approx(X0 + 18.07, abs=0.1)
    assert c.y[i] == pytest.approx(Y0 - 12, abs=0.03)
    assert c.length_m[i] == pytest.approx(6.0, abs=0.25)
    whole = detect_markings(img, None, t, ClusterParams(junction_angle_deg=None))
    assert not np.any((np.abs(whole.x - (X0 + 18.07)) < 0.1) & (np.abs(whole.y - (Y0 - 12)) < 0.03)
                      & (whole.width_m > 0.3))


def test_curves_and_straight_stripes_are_not_cut_at_junctions():
    from mapbuilder.cluster import split_junctions

    res = 0.1
    img = np.zeros((260, 260), np.float32)
    # a quarter circle of radius 15 m, 0.15 m wide; a wide straight stop line
    yy, xx = np.mgrid[0:260, 0:260] * res
    r = np.hypot(xx - 1.0, yy - 1.0)
    img[(np.abs(r - 15.0) < 0.075) & (xx > 1.0) & (yy > 1.0)] = 1.0
    img[200:205, 40:100] = 1.0
    labels, n = label_pixels(img)
    assert n == 2
    rows, cols = np.nonzero(labels)
    lab = split_junctions(rows, cols, labels[rows, cols], res)
    # the same two clusters (labels may be numbered differently)
    assert lab.max() == 2
    assert len(set(zip(lab.tolist(), labels[rows, cols].tolist()))) == 2


def test_junction_cuts_do_not_depend_on_the_window():
    res = 0.1
    t, img, stalls = _comb(res)
    params = ClusterParams(min_length_m=0.3)
    a = detect_markings(img[:, :150], None, t, params)
    b = detect_markings(img[:, 60:], None, t @ Affine.translation(60, 0), params)
    # the second stall line (x 10–12 m) lies well inside both windows
    sel_a = np.hypot(a.x - stalls[1, 0], a.y - stalls[1, 1]) < 0.3
    sel_b = np.hypot(b.x - stalls[1, 0], b.y - stalls[1, 1]) < 0.3
    assert sel_a.sum() == 1 and sel_b.sum() == 1
    assert a.x[sel_a][0] == pytest.approx(b.x[sel_b][0], abs=1e-9)
    assert a.weight[sel_a][0] == b.weight[sel_b][0]


def test_an_end_on_a_line_across_it_moves_to_that_lines_axis():
    """A stop line painted from the lane line's axis is measured from there, not from its edge."""
    res = 0.1
    t = _grid(res)
    img = np.zeros((250, 300), np.float32)
    _draw(img, t, X0 + 15, Y0 - 20, 26.0, 0.2, 0.0)  # lane line, north-south, axis at x = 15 m
    _draw(img, t, X0 + 18.0, Y0 - 12, 6.0, 0.5, 90.0)  # stop line from the axis, x 15–21 m
    _draw(img, t, X0 + 25.0, Y0 - 5.0, 3.0, 0.12, 0.0)  # a dash 0.5 m from a line across it
    _draw(img, t, X0 + 25.0, Y0 - 7.0, 4.0, 0.15, 90.0)
    c = detect_markings(img, None, t)
    stop = np.flatnonzero(c.width_m > 0.3)
    assert len(stop) == 1
    i = stop[0]
    assert min(c.x0[i], c.x1[i]) == pytest.approx(X0 + 15.0, abs=0.03)
    # the free end stays where the paint ends (less the corners of a wide
    # stroke's end, which the junction cut leaves apart)
    assert max(c.x0[i], c.x1[i]) == pytest.approx(X0 + 21.0, abs=0.12)
    assert c.x[i] == pytest.approx(0.5 * (c.x0[i] + c.x1[i]), abs=1e-9)
    assert c.x[i] == pytest.approx(X0 + 18.0, abs=0.06)
    assert c.y[i] == pytest.approx(Y0 - 12, abs=0.03)
    assert c.length_m[i] == pytest.approx(6.0, abs=0.12)
    # a gap is not a junction: the dash keeps its own ends
    dash = np.flatnonzero((np.abs(c.x - (X0 + 25.0)) < 0.1) & (_angle_diff(c.bearing_deg, 0.0) < 3))
    assert len(dash) == 1
    assert c.y[dash[0]] == pytest.approx(Y0 - 5.0, abs=0.05)
    assert c.length_m[dash[0]] == pytest.approx(3.0, abs=0.15)
    # without the extension the stop line ends at the lane line's edge
    short = detect_markings(img, None, t, ClusterParams(extend_junctions=False))
    j = np.flatnonzero(short.width_m > 0.3)[0]
    assert min(short.x0[j], short.x1[j]) - (X0 + 15.0) > 0.08

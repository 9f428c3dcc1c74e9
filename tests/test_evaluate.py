"""Scoring a map against true markings: ``mapbuilder.evaluate`` and ``lanemap evaluate``."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from mapbuilder.evaluate import evaluate_markings
from mapbuilder.model import Marking

LANEMAP = [sys.executable, "-m", "service.cli"]
BOUNDS = (0.0, 0.0, 100.0, 100.0)


def dash(x, y, **kw):
    kw.setdefault("kind", "dash")
    return Marking(x=x, y=y, length_m=kw.pop("length_m", 3.0), bearing_deg=kw.pop("bearing_deg", 0.0), **kw)


def test_discrete_markings_match_one_to_one_within_the_tolerance():
    truth = [dash(10, 10), dash(20, 10), dash(30, 10)]
    detected = [dash(10.1, 10.05), dash(10.2, 10.0), dash(20.4, 10), dash(30, 10.25)]
    ev = evaluate_markings(detected, truth, BOUNDS, tolerance_m=0.3, border_m=0)
    # 10,10 takes the nearer of two detections; the other is false; 20.4 is too far
    assert list(ev.detection_ok) == [True, False, False, True]
    assert list(ev.found) == [True, False, True]
    assert (ev.n_correct, ev.n_detected, ev.n_found, ev.n_true) == (2, 4, 2, 3)
    assert ev.precision == 0.5 and ev.recall == pytest.approx(2 / 3)
    assert ev.centroid_rmse_m == pytest.approx(math.sqrt((0.1**2 + 0.05**2 + 0.25**2) / 2))
    assert [m.x for m in ev.missed] == [20] and [m.x for m in ev.false_detections] == [10.2, 20.4]
    assert ev.recall_by_kind() == {"dash": {"true": 3, "found": 2}}


def test_line_pieces_are_scored_by_their_axis_whatever_the_phase():
    # a solid line along y = 50, cut into 3 m pieces at one phase in the truth and another in the map
    truth = [dash(x, 50, kind="solid", bearing_deg=90.0) for x in np.arange(11.5, 40, 3.0)]
    detected = [dash(x, 50.1, kind=None, bearing_deg=90.0) for x in np.arange(11.2, 39, 3.0)]
    detected.append(dash(25, 50.6, kind=None, bearing_deg=90.0))  # beside the line: false
    ev = evaluate_markings(detected, truth, BOUNDS, border_m=0)
    assert ev.n_correct == len(detected) - 1 and not ev.detection_ok[-1]
    assert ev.n_found == len(truth)
    assert ev.cross_track_rmse_m == pytest.approx(0.1) and ev.centroid_errors_m.size == 0
    # a marking longer than the builder keeps whole is a line too, and so is one the truth calls continuous
    long_stop = dash(60, 70, kind="stop_line", length_m=12.0, bearing_deg=90.0)
    flagged = dash(60, 80, kind="stall", extra={"continuous": True}, bearing_deg=90.0)
    ev = evaluate_markings([dash(61.0, 70.05, bearing_deg=90.0), dash(61.2, 80, bearing_deg=90.0)],
                           [long_stop, flagged], BOUNDS, border_m=0)  # fmt: skip
    assert list(ev.is_line) == [True, True] and ev.n_correct == 2 and ev.n_found == 2


def test_the_border_and_hidden_markings_are_left_out():
    truth = [dash(1.0, 50), dash(50, 50), dash(60, 50, extra={"visible": 0.5})]
    detected = [dash(1.0, 50), dash(50, 50), dash(60, 50)]
    ev = evaluate_markings(detected, truth, BOUNDS, border_m=2.0)
    assert ev.n_detected == 2 and ev.n_true == 1 and ev.n_found == 1
    assert ev.precision == 1.0  # the detection of the half-hidden dash is right, it just is not counted
    empty = evaluate_markings([], truth, BOUNDS)
    assert empty.n_detected == 0 and math.isnan(empty.precision) and empty.recall == 0.0
    with pytest.raises(ValueError, match="tolerance_m"):
        evaluate_markings(detected, truth, BOUNDS, tolerance_m=0)


def _run(args, env, cwd, **kw):
    return subprocess.run([*LANEMAP, *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=180, **kw)  # fmt: skip


def test_cli_scores_a_map_against_its_truth(db_url, tmp_path):
    """A map imported from a Lanelet2 layout scores 1.0 against that layout; with markings
    deleted, moved and added the figures say by how much, ``--errors`` shows where, and
    ``--min-recall`` fails a batch job."""
    from tests._localizer_helpers import KARLSRUHE_OSM

    env = dict(os.environ, LANEMAP_DATABASE_URL=db_url, LANEMAP_DATA_DIR=str(tmp_path / "data"))
    env.pop("LANEMAP_DEBUG", None)
    assert _run(["from-lanelet2", KARLSRUHE_OSM, "truth.geojson"], env, tmp_path).returncode == 0
    truth = json.loads((tmp_path / "truth.geojson").read_text())
    n = len(truth["features"])
    assert _run(["import", "ka", "truth.geojson", "--create"], env, tmp_path).returncode == 0
    same = _run(["evaluate", "ka", "truth.geojson", "--json"], env, tmp_path)
    assert same.returncode == 0, same.stderr
    fig = json.loads(same.stdout)
    assert same.stderr == ""  # no bars unless on a terminal or asked for
    bars = _run(["evaluate", "ka", "truth.geojson", "--json", "--progress"], env, tmp_path)
    assert json.loads(bars.stdout) == fig
    lines = bars.stderr.replace("\r", "\n")
    assert "read truth.geojson: 100%" in lines and f"{n}/{n}" in lines and "read ka: 100%" in lines, lines
    assert fig["precision"] == 1.0 and fig["recall"] == 1.0 and fig["true_markings"] == n
    assert fig["centroid_rmse_m"] < 1e-3 and fig["cross_track_rmse_m"] < 1e-3

    # the map loses 4 dashes, one dash moves 1 m, and a stray marking appears
    feats = truth["features"]
    dashes = [k for k, f in enumerate(feats) if f["properties"]["kind"] == "dash"]
    edited = [f for k, f in enumerate(feats) if k not in dashes[:4]]
    moved = next(f for f in edited if f["properties"]["kind"] == "dash")
    lon, lat = moved["geometry"]["coordinates"]
    moved["geometry"] = {"type": "Point", "coordinates": [lon, lat + 1.0 / 111_200]}
    lon0, lat0 = feats[dashes[10]]["geometry"]["coordinates"]
    edited.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon0 + 3e-5, lat0 + 3e-5]},
                   "properties": {"kind": "dash", "length_m": 3.0, "bearing_deg": 10.0}})  # fmt: skip
    (tmp_path / "map.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": edited}))
    assert _run(["import", "ka2", "map.geojson", "--create"], env, tmp_path).returncode == 0
    out = _run(["evaluate", "ka2", "truth.geojson", "--errors", "errors.geojson", "--min-recall", "0.995"],
               env, tmp_path)  # fmt: skip
    assert out.returncode == 3, out.stderr
    assert out.stderr.strip() == f"warning: recall {(n - 5) / n:.3f} is below 0.995"
    assert f"precision {(n - 5) / (n - 3):.3f}  ({n - 5} of {n - 3} markings of the map lie on a true one)" \
        in out.stdout, out.stdout
    assert f"recall    {(n - 5) / n:.3f}  ({n - 5} of {n} true markings found)" in out.stdout, out.stdout
    errs = json.loads((tmp_path / "errors.geojson").read_text())["features"]
    kinds = sorted(f["properties"]["error"] for f in errs)
    assert kinds == ["false", "false", "missed", "missed", "missed", "missed", "missed"]

    bad = [(["evaluate", "ka", "truth.geojson", "--tolerance", "0"], "--tolerance must be a positive"),
           (["evaluate", "ka", "truth.geojson", "--status", "maybe"], "--status: 'maybe' is not one of"),
           (["evaluate", "ka", "missing.geojson"], "cannot read missing.geojson"),
           (["evaluate", "nope", "truth.geojson"], "unknown map 'nope'")]  # fmt: skip
    for args, says in bad:
        proc = _run(args, env, tmp_path)
        assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert says in proc.stderr, proc.stderr


def test_matches_are_as_many_as_can_be_made_then_the_closest():
    # A is nearest to T1, but only A can reach T2: the assignment pairs A-T2 and B-T1
    truth = [dash(10.0, 10.0), dash(10.2, 10.0)]
    detected = [dash(10.1, 10.0), dash(9.8, 10.0)]
    ev = evaluate_markings(detected, truth, BOUNDS, border_m=0)
    assert ev.n_correct == 2 and ev.n_found == 2
    assert sorted(np.round(ev.centroid_errors_m, 6)) == [0.1, 0.2]


def test_groups_of_near_markings_are_assigned_as_the_whole_set_would_be():
    """The assignment runs on each group of markings linked by pairs within the tolerance;
    a brute-force assignment over all of them agrees on the number of matches and their total
    distance."""
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(3)
    for _ in range(40):
        centres = rng.uniform(0, 60, (10, 2))
        a = centres[rng.integers(0, 10, rng.integers(1, 50))] + rng.normal(0, 0.2, (1, 2))
        a = a + rng.normal(0, 0.2, a.shape)
        b = centres[rng.integers(0, 10, rng.integers(1, 50))] + rng.normal(0, 0.2, (1, 2))
        b = b + rng.normal(0, 0.2, b.shape)
        ev = evaluate_markings([dash(x, y) for x, y in a], [dash(x, y) for x, y in b],
                               (-10, -10, 70, 70), border_m=0)  # fmt: skip
        d = np.hypot(*(a[:, None] - b[None]).transpose(2, 0, 1))
        cost = np.where(d <= 0.3, d, 1e6)
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] <= 0.3
        assert ev.n_correct == ok.sum()
        assert ev.centroid_errors_m.sum() == pytest.approx(cost[r[ok], c[ok]].sum())


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def api(request):
    from tests._api_helpers import shared_server

    return shared_server(request.param)


def test_api_scores_a_map_as_the_cli_does(api, tmp_path):
    """``POST /collections/{id}/evaluate``: the figures and the false and missed markings of
    the CLI, over HTTP, for a reader; bad input is a problem, not a 500."""
    import httpx

    from tests._localizer_helpers import KARLSRUHE_OSM

    env = dict(os.environ, LANEMAP_DATABASE_URL=api.db_url, LANEMAP_DATA_DIR=str(tmp_path / "data"))
    env.pop("LANEMAP_DEBUG", None)
    assert _run(["from-lanelet2", KARLSRUHE_OSM, "truth.geojson"], env, tmp_path).returncode == 0
    truth = json.loads((tmp_path / "truth.geojson").read_text())
    window = {**truth, "features": truth["features"][:300]}
    map_id = api.new_map(prefix="ev")
    imported = {**truth, "features": truth["features"][3:300]}  # three missed
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=imported, headers=api.auth, timeout=60)
    assert r.status_code == 201, r.text
    url = f"{api.base_url}/collections/{map_id}/evaluate"
    r = httpx.post(url, json=window, timeout=60)  # no token: reading is enough
    assert r.status_code == 200, r.text
    got = r.json()
    assert (got["precision"], got["found"], got["true_markings"]) == (1.0, 297, 300)
    missed = [f for f in got["errors"]["features"] if f["properties"]["error"] == "missed"]
    assert len(missed) == 3 and len(got["errors"]["features"]) == 3
    want = {tuple(round(c, 7) for c in f["geometry"]["coordinates"]) for f in truth["features"][:3]}
    assert {tuple(round(c, 7) for c in f["geometry"]["coordinates"]) for f in missed} == want
    (tmp_path / "window.geojson").write_text(json.dumps(window))
    cli = _run(["evaluate", map_id, "window.geojson", "--json"], env, tmp_path)
    assert cli.returncode == 0, cli.stderr
    assert {k: v for k, v in json.loads(cli.stdout).items() if k not in ("truth",)} == \
        {k: v for k, v in got.items() if k != "errors"}  # fmt: skip
    assert "errors" not in httpx.post(url, json=window, params={"errors": "false"}, timeout=60).json()

    empty = api.new_map(prefix="ev0", crs=None)
    problems = [
        (url, {"type": "FeatureCollection", "features": []}, {}, 422, "invalid-geojson"),
        (url, {"type": "Nope"}, {}, 422, "invalid-geojson"),
        (url, window, {"status": "approved"}, 400, "invalid-parameter"),
        (url, window, {"tolerance": "0"}, 422, "validation-error"),
        (f"{api.base_url}/collections/no-such-map/evaluate", window, {}, 404, "unknown-map"),
        (f"{api.base_url}/collections/{empty}/evaluate", window, {}, 409, "empty-map"),
    ]
    for where, body, params, status, kind in problems:
        r = httpx.post(where, json=body, params=params, timeout=60)
        assert r.status_code == status and r.headers["content-type"].startswith("application/problem+json"), \
            (kind, r.status_code, r.text)
        assert r.json()["type"].endswith(kind), r.text

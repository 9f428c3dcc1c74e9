"""``lanemap localize`` end to end: a stored Karlsruhe map, a simulated camera frame."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from localizer import GeoFrame
from localizer.simulate import Camera, Clutter, sample_poses, simulate_scene
from service.cli import app

from ._localizer_helpers import karlsruhe, karlsruhe_store


@pytest.fixture(scope="module")
def stored_map(tmp_path_factory):
    return karlsruhe_store(tmp_path_factory.mktemp("loc"))


def frame_and_prior(seed: int):
    _, smap = karlsruhe()
    rng = np.random.default_rng(seed)
    pose = sample_poses(smap, 1, rng, min_visible=6)[0]
    scene = simulate_scene(smap, pose, rng, Camera(), Clutter())
    frame = GeoFrame("EPSG:25832")
    lon, lat = frame.to_lonlat(pose[0] + 0.8, pose[1] - 0.6)
    heading = float(frame.grid_yaw_to_heading(pose[2] + math.radians(5), lon, lat))
    return pose, scene, lat, lon, heading


def test_cli_localizes_against_a_stored_map(stored_map, tmp_path, monkeypatch):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    pose, scene, lat, lon, heading = frame_and_prior(6)
    path = tmp_path / "obs.json"
    path.write_text(json.dumps(
        {"observations": [{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]}))
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
        "--observations", str(path), "--position-sigma", "2", "--heading-sigma", "8",
    ])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["status"] == "ok" and out["crs"] == "EPSG:25832"
    assert math.hypot(out["easting"] - pose[0], out["northing"] - pose[1]) < 0.3
    # "-" reads the observations from standard input: the same answer
    piped = CliRunner().invoke(app, [
        "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
        "--observations", "-", "--position-sigma", "2", "--heading-sigma", "8",
    ], input=path.read_text())  # fmt: skip
    assert piped.exit_code == 0, piped.output
    assert json.loads(piped.stdout) == out
    # Five markings leave a little doubt in most places (the first such frame
    # of a few is taken): asking for more than the answer's probability makes
    # it ambiguous, with the same pose.
    few = tmp_path / "few.json"
    for seed in range(6, 26):
        _, f_scene, f_lat, f_lon, f_heading = frame_and_prior(seed)
        heavy = f_scene.observations[np.argsort(-f_scene.observations[:, 2])[:5]]
        few.write_text(json.dumps([{"x": x, "y": y, "weight": w} for x, y, w in heavy]))
        args = ["localize", "ka", "--lat", str(f_lat), "--lon", str(f_lon), "--heading", str(f_heading),
                "--observations", str(few), "--position-sigma", "2", "--heading-sigma", "8"]  # fmt: skip
        out = json.loads(CliRunner().invoke(app, args).stdout)
        if out["status"] == "ok" and out["probability"] < 0.9999:
            break
    else:
        pytest.fail("no frame gave an ok answer in some doubt")
    res = CliRunner().invoke(app, [*args, "--min-probability", "0.9999"])
    strict = json.loads(res.stdout)
    assert strict["status"] == "ambiguous" and strict["easting"] == pytest.approx(out["easting"]), strict
    # A script that reads only the exit code must not take it for a sure answer.
    assert res.exit_code == 3, res.output
    warn = res.stderr.strip().splitlines()
    assert len(warn) == 1 and warn[0].startswith("warning: the answer is ambiguous"), warn
    # ... and says what the hypotheses leave known: the mixture's sigmas along and across the heading.
    m = np.array(strict["mixture_covariance"])
    yaw = math.radians(90.0 - strict["heading_deg"])  # within the meridian convergence of the grid's
    u, v = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
    along, across = (float(x) for x in re.search(r"±([\d.]+) m along the heading and ±([\d.]+) m across",
                                                    warn[0]).groups())
    assert along == pytest.approx(math.sqrt(u @ m[:2, :2] @ u), abs=0.02)
    assert across == pytest.approx(math.sqrt(v @ m[:2, :2] @ v), abs=0.02)
    # The fix's error ellipse instead of one sigma.
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
        "--observations", str(path), "--position-ellipse", f"4, 1.5, {heading:.3f}", "--heading-sigma", "8",
    ])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["status"] == "ok" and math.hypot(out["easting"] - pose[0], out["northing"] - pose[1]) < 0.3
    # A bare list works too, and the paper's method answers from the same prior.
    path.write_text(json.dumps([{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]))
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
        "--observations", str(path), "--method", "pink2008",
    ])
    paper = json.loads(res.stdout)
    assert res.exit_code == {"ok": 0, "failed": 4}[paper["status"]], res.output


def test_cli_failed_answer_prints_the_pose_json_and_exits_4(stored_map, tmp_path, monkeypatch):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    _, scene, lat, lon, heading = frame_and_prior(6)
    path = tmp_path / "obs.json"
    path.write_text(json.dumps([{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]))
    # The same frame with a GPS fix in Berlin: a valid request, but no map there.
    for method in ("default", "pink2008"):
        res = CliRunner().invoke(app, [
            "localize", "ka", "--lat", "52.52", "--lon", "13.40", "--heading", str(heading),
            "--observations", str(path), "--method", method,
        ])
        assert res.exit_code == 4, res.output
        out = json.loads(res.stdout)
        assert out["status"] == "failed" and "no map markings within" in out["reason"], out
        err = res.stderr.strip().splitlines()
        assert err == [f"error: localization failed: {out['reason']}"], err
    # A drive is judged by its last frame.
    drive = tmp_path / "drive.json"
    frame0 = {"observations": json.loads(path.read_text())}
    drive.write_text(json.dumps({"frames": [frame0, {**frame0, "motion": {"dx": 0, "dy": 0}}]}))
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", "52.52", "--lon", "13.40", "--heading", "0", "--frames", str(drive),
    ])
    assert res.exit_code == 4, res.output
    assert [p["status"] for p in json.loads(res.stdout)["poses"]] == ["failed", "failed"]


@pytest.mark.parametrize(
    "content, extra, needle",
    [
        ("{not json", [], "not valid JSON"),
        ("\udcff\udcfe", [], "is not valid JSON: not UTF-8 text"),
        ('{"obs": []}', [], "'observations'"),
        ('[{"x": 1, "y": "NaN", "weight": 1}]', [], "NaN"),
        ('[{"x": 1, "y": 2, "weight": 0}]', [], "weights must be positive"),
        ('[{"x": 1, "y": 2}]', ["--method", "nope"], "--method"),
        ('[{"x": 1, "y": 2}]', ["--position-sigma", "0"], "position_sigma"),
        ('[{"x": 1, "y": 2}]', ["--min-probability", "1"], "--min-probability must be between"),
        ('[{"x": 1, "y": 2}]', ["--position-ellipse", "3,1"], "MAJOR,MINOR,ORIENTATION"),
        ('[{"x": 1, "y": 2}]', ["--position-ellipse", "1,3,0"], "larger than sigma_major_m"),
        ('[{"x": 1, "y": 2}]', ["--position-ellipse", "3,1,0", "--position-sigma", "2"], "not both"),
        ('[{"x": 1, "y": 2}]', ["--method", "pink2008", "--min-probability", "0.9"], "pink2008 has no"),
    ],
)
def test_cli_bad_input_is_one_line(stored_map, tmp_path, monkeypatch, content, extra, needle):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    path = tmp_path / "obs.json"
    path.write_bytes(content.encode("utf-8", "surrogateescape"))  # the surrogates: bytes that are not UTF-8
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", "49.0", "--lon", "8.43", "--heading", "90",
        "--observations", str(path), *extra,
    ])
    assert res.exit_code == 1, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines


def test_cli_unknown_map_and_missing_file(stored_map, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    path = tmp_path / "obs.json"
    path.write_text("[]")
    from service.cli import main

    for args, needle in [
        (["localize", "nope", "--lat", "49", "--lon", "8.4", "--heading", "0",
          "--observations", str(path)], "unknown map"),
        (["localize", "ka", "--lat", "49", "--lon", "8.4", "--heading", "0",
          "--observations", str(tmp_path / "missing.json")], "cannot read"),
    ]:
        monkeypatch.setattr("sys.argv", ["lanemap", *args])
        with pytest.raises(SystemExit) as exc:
            main()
        assert exc.value.code == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err


def simulated_drive(seed: int, n: int):
    """A drive of ``n`` frames as the CLI reads them, its true poses, and a GPS fix near its start."""
    from localizer.simulate import odometry, sample_trajectories

    _, smap = karlsruhe()
    rng = np.random.default_rng(seed)
    drive = sample_trajectories(smap, 1, n, 1.5, rng, min_visible=6)[0]
    frames = []
    for k, p in enumerate(drive):
        scene = simulate_scene(smap, tuple(p), rng, Camera(), Clutter())
        f = {"observations": [{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]}
        if k:
            dx, dy, dyaw = odometry(drive[k - 1], p)
            f["motion"] = {"dx": dx, "dy": dy, "dyaw_deg": math.degrees(dyaw)}
        frames.append(f)
    frame = GeoFrame("EPSG:25832")
    lon, lat = frame.to_lonlat(drive[0][0] + 1.0, drive[0][1] - 0.5)
    heading = float(frame.grid_yaw_to_heading(drive[0][2] + math.radians(4), lon, lat))
    return frames, drive, lat, lon, heading


def test_cli_localizes_a_drive_of_frames(stored_map, tmp_path, monkeypatch):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    frames, drive, lat, lon, heading = simulated_drive(2, 6)
    path = tmp_path / "drive.json"
    path.write_text(json.dumps({"frames": frames}))
    res = CliRunner().invoke(app, [
        "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
        "--frames", str(path), "--position-sigma", "2", "--heading-sigma", "8",
    ])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert len(out["poses"]) == 6 and out["tracks"] >= 1
    last = out["poses"][-1]
    assert last["status"] == "ok"
    assert math.hypot(last["easting"] - drive[-1][0], last["northing"] - drive[-1][1]) < 0.5

    for content, extra, needle in [
        (json.dumps({"frames": frames}), ["--observations", str(path)], "either --observations"),
        (json.dumps({"frames": [frames[0], {"observations": []}]}), [], "frames[1].motion"),
        (json.dumps({"frames": []}), [], "non-empty 'frames'"),
        (json.dumps({"frames": frames}), ["--method", "pink2008"], "default method only"),
    ]:
        path.write_text(content)
        res = CliRunner().invoke(app, [
            "localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
            "--frames", str(path), *extra,
        ])
        assert res.exit_code == 1, res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines


def test_a_first_run_says_it_is_compiling(stored_map, tmp_path):
    """A fresh installation compiles the localizer (seconds): the first run says so, later ones do not."""
    import os
    import subprocess
    import sys

    pose, scene, lat, lon, heading = frame_and_prior(6)
    path = tmp_path / "obs.json"
    path.write_text(json.dumps([{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]))
    env = {**os.environ, "LANEMAP_DATABASE_URL": stored_map, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    cmd = [sys.executable, "-m", "service.cli", "localize", "ka", "--lat", str(lat), "--lon", str(lon),
           "--heading", str(heading), "--observations", str(path), "--position-sigma", "2"]  # fmt: skip
    runs = [subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300) for _ in range(2)]
    for res in runs:
        assert res.returncode == 0, res.stderr
        out = json.loads(res.stdout)
        assert math.hypot(out["easting"] - pose[0], out["northing"] - pose[1]) < 0.3
    assert runs[0].stderr.startswith("note: compiling the localizer"), runs[0].stderr
    assert "note:" not in runs[1].stderr, runs[1].stderr


def test_cli_streams_a_drive_through_a_state_file(stored_map, tmp_path, monkeypatch):
    """--state: a drive sent in parts gives the poses of one call; the file is written whole, or not at all."""
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    frames, drive, lat, lon, heading = simulated_drive(3, 6)
    gps = ["--lat", str(lat), "--lon", str(lon), "--heading", str(heading), "--position-sigma", "2"]

    def run(part, *extra):
        path = tmp_path / "part.json"
        path.write_text(json.dumps({"frames": part}))
        return CliRunner().invoke(app, ["localize", "ka", "--frames", str(path), *extra])

    whole = run(frames, *gps)
    assert whole.exit_code == 0, whole.output
    state = tmp_path / "drive.state.json"
    first = run(frames[:2], *gps, "--state", str(state))
    assert first.exit_code == 0, first.output
    assert json.loads(state.read_text()) == json.loads(first.stdout)["state"]
    rest = run(frames[2:], "--state", str(state))  # no GPS options: the state continues the drive
    assert rest.exit_code == 0, rest.output
    streamed = json.loads(first.stdout)["poses"] + json.loads(rest.stdout)["poses"]
    assert streamed == json.loads(whole.stdout)["poses"]
    assert json.loads(state.read_text())["frames"] == 6
    assert math.hypot(streamed[-1]["easting"] - drive[-1][0], streamed[-1]["northing"] - drive[-1][1]) < 0.5

    kept = state.read_text()
    for part, extra, needle in [
        (frames[2:], [], "frames[0].motion"),  # continuing: the first frame needs the odometry
        (frames[3:], ["--lat", str(lat)], "together"),
        (frames[3:], ["--observations", "x.json"], "either --observations"),
    ]:
        if not extra:
            part = [{"observations": part[0]["observations"]}] + part[1:]
        res = run(part, "--state", str(state), *extra)
        assert res.exit_code == 1, res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
        assert state.read_text() == kept  # a refused call leaves the drive's state as it was
    res = run(frames[:1], "--state", str(tmp_path / "new.json"))
    assert res.exit_code == 1 and "does not exist yet" in res.stderr
    state.write_text('{"crs": "EPSG:25832", "frames": 0}')
    res = run(frames[3:], "--state", str(state))
    assert res.exit_code == 1 and "not a drive's state" in res.stderr and "state.frames" in res.stderr


def test_a_maps_coverage_is_the_options_the_maps_own_or_the_servers(stored_map, tmp_path, monkeypatch):
    """The Karlsruhe map is seven separate parts: by their hull a fix 8 m off near a part's end
    is answered surely; covering only the ground between its markings, the camera sees past the
    map's edge. --coverage decides, else the map's own coverage (lanemap maps update), else
    LANEMAP_MAP_COVERAGE as for the server, else the hull."""
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    monkeypatch.delenv("LANEMAP_MAP_COVERAGE", raising=False)
    path = tmp_path / "obs.json"
    for seed in range(40):
        _, scene, lat, lon, heading = frame_and_prior(seed)
        path.write_text(json.dumps([{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]))
        args = ["localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
                "--observations", str(path), "--position-sigma", "8", "--heading-sigma", "8"]  # fmt: skip
        hull = CliRunner().invoke(app, args)
        markings = CliRunner().invoke(app, [*args, "--coverage", "markings"])
        if hull.exit_code == 0 and markings.exit_code == 3:
            break
    else:
        pytest.fail("no frame was sure by the hull and held back by the markings' extent")
    held, sure = json.loads(markings.stdout), json.loads(hull.stdout)
    assert held["status"] == "ambiguous" and "beyond the map's edge" in held["reason"]

    def answer(*extra):
        return json.loads(CliRunner().invoke(app, [*args, *extra]).stdout)

    assert answer("--coverage", "hull") == sure
    assert answer("--coverage", "imagery") == held  # no build has recorded the ground it imaged
    monkeypatch.setenv("LANEMAP_MAP_COVERAGE", "markings")
    assert answer() == held and answer("--coverage", "hull") == sure
    monkeypatch.setenv("LANEMAP_MAP_COVERAGE", "hull")
    try:
        res = CliRunner().invoke(app, ["maps", "update", "ka", "--coverage", "markings"])
        assert res.exit_code == 0 and "coverage markings" in res.output, res.output
        assert json.loads(CliRunner().invoke(app, ["maps", "show", "ka"]).stdout)["coverage"] == "markings"
        assert answer() == held and answer("--coverage", "hull") == sure
    finally:
        res = CliRunner().invoke(app, ["maps", "update", "ka", "--coverage", "default"])
        assert res.exit_code == 0 and "as the server is set" in res.output, res.output
    assert json.loads(CliRunner().invoke(app, ["maps", "show", "ka"]).stdout)["coverage"] is None
    assert answer() == sure
    bad = CliRunner().invoke(app, [*args, "--coverage", "convex"])
    assert bad.exit_code == 1 and bad.output.count("\n") == 1, bad.output
    assert "--coverage must be one of hull, markings, imagery" in bad.output
    bad = CliRunner().invoke(app, ["maps", "update", "ka", "--coverage", "convex", "--title", "never written"])
    assert bad.exit_code == 1 and "--coverage must be one of hull, markings, imagery or default" in bad.output, \
        bad.output
    assert json.loads(CliRunner().invoke(app, ["maps", "show", "ka"]).stdout)["title"] != "never written"
    monkeypatch.setenv("LANEMAP_MAP_COVERAGE", "convex")
    bad = CliRunner().invoke(app, args)
    assert bad.exit_code == 1 and "LANEMAP_MAP_COVERAGE must be one of hull, markings" in bad.output
    # once a build recorded imagery of the whole district, the map speaks for its ground
    import shapely

    from mapbuilder.store import Store
    from tests._localizer_helpers import KarlsruheMarkings

    monkeypatch.setenv("LANEMAP_MAP_COVERAGE", "hull")
    store = Store(stored_map)
    store.replace_detected("ka", "ortho-0a1b2c3d/1024/0/0", [], ground=shapely.to_wkb(KarlsruheMarkings().imaged()))
    store.close()
    assert answer("--coverage", "imagery") == sure


def test_maps_coverage_writes_the_ground_a_map_speaks_for(tmp_path, monkeypatch, capsys):
    """``lanemap maps coverage MAP [OUT]``: the extent localization draws, as a GeoJSON Feature in
    WGS84, by the map's own coverage or ``--coverage``; errors are one line and write nothing."""
    import shapely
    from shapely.geometry import shape

    monkeypatch.setenv("LANEMAP_DATABASE_URL", karlsruhe_store(tmp_path))
    monkeypatch.delenv("LANEMAP_MAP_COVERAGE", raising=False)
    from mapbuilder.store import Store

    lon, lat = np.array([(m.lon, m.lat) for m in Store().iter_markings("ka")]).T
    out = tmp_path / "coverage.geojson"
    res = CliRunner().invoke(app, ["maps", "coverage", "ka", str(out)])
    assert res.exit_code == 0 and "coverage hull" in res.stdout and "written to" in res.stdout, res.output
    hull = json.loads(out.read_text())
    assert hull["type"] == "Feature" and hull["geometry"]["type"] == "Polygon"
    assert shapely.contains_xy(shape(hull["geometry"]), lon, lat).all()
    res = CliRunner().invoke(app, ["maps", "coverage", "ka", "--coverage", "markings"])
    parts = json.loads(res.stdout)
    assert parts["properties"]["coverage"] == "markings" and parts["geometry"]["type"] == "MultiPolygon"
    assert shapely.contains_xy(shape(parts["geometry"]), lon, lat).all()
    assert parts["properties"]["area_m2"] < 0.5 * hull["properties"]["area_m2"]
    for args, says in ((["maps", "coverage", "ka", "--coverage", "convex"], "--coverage must be one of"),
                       (["maps", "coverage", "nowhere"], "nowhere"),
                       (["maps", "coverage", "ka", str(tmp_path / "no" / "such" / "c.geojson")], "does not exist")):
        from service.cli import main

        monkeypatch.setattr("sys.argv", ["lanemap", *args])
        with pytest.raises(SystemExit) as exc:
            main()
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 1 and len(err) == 1 and err[0].startswith("error: ") and says in err[0], err
    assert not (tmp_path / "no").exists()


def test_a_large_maps_index_is_kept_for_the_next_call(stored_map, tmp_path, monkeypatch):
    """A map of at least ``LANEMAP_INDEX_DIR_FROM`` markings has its index built once and kept in
    ``LANEMAP_INDEX_DIR``: the next call reads it (and says nothing about building), a call after an
    edit updates it with the edit and keeps the edited map's, deleting the map deletes them, and
    ``off`` keeps none."""
    import shutil

    from mapbuilder.model import Marking
    from mapbuilder.store import Store

    url = f"sqlite:///{tmp_path / 'copy.sqlite'}"
    shutil.copy(stored_map.removeprefix("sqlite:///"), tmp_path / "copy.sqlite")
    kept = tmp_path / "kept"
    monkeypatch.setenv("LANEMAP_DATABASE_URL", url)
    monkeypatch.setenv("LANEMAP_INDEX_DIR", str(kept))
    monkeypatch.setenv("LANEMAP_INDEX_DIR_FROM", "500")
    pose, scene, lat, lon, heading = frame_and_prior(6)
    path = tmp_path / "obs.json"
    path.write_text(json.dumps({"observations": [{"x": x, "y": y, "weight": w} for x, y, w in scene.observations]}))
    args = ["localize", "ka", "--lat", str(lat), "--lon", str(lon), "--heading", str(heading),
            "--observations", str(path), "--position-sigma", "2", "--heading-sigma", "8"]

    def run():
        res = CliRunner().invoke(app, args)
        assert res.exit_code in (0, 4), res.output  # 4: failed
        return json.loads(res.stdout), res.stderr

    first, said = run()
    assert re.search(r"note: building the localization index of map ka \([\d,]+ markings\); it is kept in", said)
    (file,) = kept.glob("*.index")
    again, said = run()
    assert again == first and "building" not in said and list(kept.glob("*.index")) == [file]
    # lanemap maps coverage shares them: the hull's is read, the markings' built and kept beside it
    res = CliRunner().invoke(app, ["maps", "coverage", "ka", "-", "--coverage", "hull"])
    assert res.exit_code == 0 and "building" not in res.stderr and json.loads(res.stdout)["geometry"]
    res = CliRunner().invoke(app, ["maps", "coverage", "ka", "-", "--coverage", "markings"])
    assert res.exit_code == 0 and "note: building the localization index of map ka" in res.stderr
    assert len(list(kept.glob("*-markings-*.index"))) == 1 and list(kept.glob("*-hull-*.index")) == [file]
    # What the file holds answers, not the database: a file made to hold no markings near the
    # vehicle answers failed, and is taken as long as the map has not moved on.
    import pickle

    held = pickle.loads(file.read_bytes())
    far = held["index"].__class__.from_arrays(held["index"].xy[:, 0] + 5000.0, held["index"].xy[:, 1], crs="EPSG:25832")
    file.write_bytes(pickle.dumps({**held, "index": far}))
    assert run()[0]["status"] == "failed"
    file.write_bytes(pickle.dumps(held))
    store = Store(url)
    store.add_markings("ka", [Marking(x=pose[0] + 500.0, y=pose[1], length_m=3.0, width_m=0.12, weight=30.0)])
    store.close()
    edited, said = run()
    # the kept index is updated with the edit, not built anew, and kept in place of the older
    assert "building" not in said and edited["status"] == "ok"
    assert abs(edited["easting"] - first["easting"]) < 1e-6
    assert len(list(kept.glob("*-hull-*.index"))) == 1 and not file.exists()  # the edited map's replaced it
    # more changes than an update takes on: built anew, and the older file not even read
    from service import map_index
    from service.index_files import IndexFiles

    monkeypatch.setattr(map_index, "UPDATE_MIN", 10)
    store = Store(url)
    store.add_markings("ka", [Marking(x=pose[0] + 600.0 + 3.0 * k, y=pose[1], length_m=3.0, width_m=0.12, weight=30.0)
                              for k in range(store.get_map("ka", with_count=True).count // 5)])  # fmt: skip
    store.close()
    reads = []
    read = IndexFiles._read
    monkeypatch.setattr(IndexFiles, "_read", lambda self, path, *a: reads.append(path) or read(self, path, *a))
    rebuilt, said = run()
    assert "note: building the localization index" in said and not reads and rebuilt["status"] == "ok"
    assert len(list(kept.glob("*-hull-*.index"))) == 1
    # deleting the map deletes what was kept of it
    res = CliRunner().invoke(app, ["maps", "delete", "ka", "--yes"])
    assert res.exit_code == 0 and not list(kept.glob("*.index")), res.output
    shutil.copy(stored_map.removeprefix("sqlite:///"), tmp_path / "again.sqlite")
    monkeypatch.setenv("LANEMAP_DATABASE_URL", f"sqlite:///{tmp_path / 'again.sqlite'}")
    monkeypatch.setenv("LANEMAP_INDEX_DIR", "off")
    shutil.rmtree(kept)
    assert run()[0] == first and not kept.exists()

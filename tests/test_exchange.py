"""GeoJSON/GeoPackage import and export, through the library and the real `lanemap` command."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pyogrio
import pytest

from mapbuilder import migrate
from mapbuilder.geojson import GeoJSONError, read_feature_collection, read_geojson_file
from mapbuilder.store import Store

from .conftest import KARLSRUHE_OSM

LANEMAP = [sys.executable, "-m", "service.cli"]


class Result:
    def __init__(self, returncode: int, stdout: str, stderr: str):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


@pytest.fixture
def cli(monkeypatch, capsys):
    """Run the real ``lanemap`` entry point in this process (faster than a subprocess)."""
    from service.cli import main

    def call(args, db_url, cwd, check=True):
        monkeypatch.setenv("LANEMAP_DATABASE_URL", db_url)
        monkeypatch.setenv("LANEMAP_DATA_DIR", str(cwd / "data"))
        monkeypatch.delenv("LANEMAP_DEBUG", raising=False)
        monkeypatch.chdir(cwd)
        monkeypatch.setattr(sys, "argv", ["lanemap", *map(str, args)])
        capsys.readouterr()
        code = 0
        try:
            main()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        out, err = capsys.readouterr()
        if check and code != 0:
            raise AssertionError(f"lanemap {args} failed: {err}")
        return Result(code, out, err)

    return call


def run(args, db_url, cwd, check=True):
    """Run ``lanemap`` as a separate process, as a user would."""
    env = dict(os.environ, LANEMAP_DATABASE_URL=db_url, LANEMAP_DATA_DIR=str(cwd / "data"))
    env.pop("LANEMAP_DEBUG", None)
    proc = subprocess.run(
        [*LANEMAP, *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"lanemap {args} failed: {proc.stderr}")
    return proc


def _props(fc):
    """Features as sortable tuples; positions kept to 1e-7° (1 cm) for sorting."""
    out = []
    for f in fc["features"]:
        p = f["properties"]
        lon, lat = f["geometry"]["coordinates"]
        out.append(
            (round(lon, 7), round(lat, 7), p["kind"], round(p["length_m"], 6),
             round(p["width_m"], 6), round(p["bearing_deg"], 6), float(p["weight"]),
             p["source"], p["status"], lon, lat)
        )  # fmt: skip
    return sorted(out)


def _same_features(a, b):
    pa, pb = _props(a), _props(b)
    assert len(pa) == len(pb)
    for x, y in zip(pa, pb):
        assert x[2:9] == y[2:9]
        assert x[9:] == pytest.approx(y[9:], abs=1e-9)  # lon/lat within 0.1 mm


def test_karlsruhe_round_trip_through_the_cli(db_url, tmp_path, cli):
    # The first steps run the console entry point in-process; the export and the
    # failing import below go through a real subprocess.
    cli(["from-lanelet2", KARLSRUHE_OSM, "ka.geojson"], db_url, tmp_path)
    source = json.loads((tmp_path / "ka.geojson").read_text())
    assert len(source["features"]) > 800
    cli(["maps", "create", "ka", "--title", "Karlsruhe", "--crs", "EPSG:25832"], db_url, tmp_path)
    out = cli(["import", "ka", "ka.geojson"], db_url, tmp_path).stdout
    assert f"imported {len(source['features'])} markings" in out
    run(["export", "ka", "out.geojson"], db_url, tmp_path)
    exported = json.loads((tmp_path / "out.geojson").read_text())
    _same_features(exported, source)
    assert all(f["properties"]["version"] == 1 and f["id"] for f in exported["features"])

    # The export imports again into a new map unchanged (ids and versions are the store's).
    cli(["import", "ka2", "out.geojson", "--create"], db_url, tmp_path)
    cli(["export", "ka2", "again.geojson"], db_url, tmp_path)
    _same_features(json.loads((tmp_path / "again.geojson").read_text()), source)

    # GeoPackage: points in the storage CRS, readable by GDAL.
    cli(["export", "ka", "ka.gpkg"], db_url, tmp_path)
    info = pyogrio.read_info(tmp_path / "ka.gpkg")
    assert info["crs"] == "EPSG:25832" and info["features"] == len(source["features"])
    assert info["geometry_type"] == "Point"
    store = Store(db_url)
    ours = {m.id: m for m in store.iter_markings("ka")}
    meta, _, geometry, field_data = pyogrio.raw.read(tmp_path / "ka.gpkg")
    ids = field_data[list(meta["fields"]).index("marking_id")]
    import shapely

    pts = shapely.from_wkb(geometry)
    for i, p in zip(ids[:50], pts[:50]):
        assert (p.x, p.y) == pytest.approx((ours[int(i)].x, ours[int(i)].y), abs=1e-6)

    # ... and imports again, as it was (the ids and versions are the store's)
    cli(["import", "ka3", "ka.gpkg", "--create"], db_url, tmp_path)
    cli(["export", "ka3", "from-gpkg.geojson"], db_url, tmp_path)
    _same_features(json.loads((tmp_path / "from-gpkg.geojson").read_text()), source)

    listing = json.loads(cli(["maps", "list", "--json"], db_url, tmp_path).stdout)
    assert {m["id"]: m["markings"] for m in listing} == {k: len(source["features"]) for k in ("ka", "ka2", "ka3")}


def _fc(*features):
    return {"type": "FeatureCollection", "features": list(features)}


def _pt(lon=8.43, lat=49.0, **props):
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon, lat]}, "properties": props}


BAD_FILES = [
        ("{not json", "is not valid JSON"),
        ('{"type": "Feature"}', "has no geometry"),
        (json.dumps(_fc(_pt(), {"type": "Feature", "geometry": None, "properties": {}})), "feature 1: has no geometry"),
        (json.dumps(_fc(_pt(lon=49.0, lat=108.4))), "feature 0: coordinates [49.0, 108.4] out of range"),
        (json.dumps(_fc(_pt(weight=0))), "feature 0: property 'weight' must be > 0"),
        (json.dumps(_fc(_pt(weight="heavy"))), "property 'weight' must be a number"),
        (json.dumps(_fc(_pt(source="guess"))), "property 'source' must be one of"),
        ('{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": {"type": "Point", "coordinates": [NaN, 1]}}]}', "invalid JSON number NaN"),
        (json.dumps({"type": "FeatureCollection"}), "no \"features\" array"),
        (json.dumps({"type": "Topology"}), "not a GeoJSON FeatureCollection"),
        (json.dumps(_fc({"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}})), "geometry must be a Point"),
]


def _no_constant(value: str):
    raise GeoJSONError(f"invalid JSON number {value}")  # as lanemap reads GeoJSON: NaN is no number



def test_a_geopackage_is_built_a_chunk_at_a_time_and_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """A GeoPackage's columns are built ``GPKG_CHUNK`` markings at a time: every marking arrives
    once, in order, with its fields; an empty map is an empty layer; a failure after some chunks
    leaves the file that was there before, and no part of the new one."""
    import shapely

    from mapbuilder import geojson
    from mapbuilder.model import Marking

    monkeypatch.setattr(geojson, "GPKG_CHUNK", 7)
    ms = [Marking(x=457000.0 + k, y=5428000.0 - k, weight=k + 1, score=None if k % 5 else k / 30, kind="dash",
                  id=100 + k, version=2, extra={"k": k}) for k in range(23)]  # fmt: skip
    assert geojson.write_gpkg(tmp_path / "m.gpkg", iter(ms), "EPSG:25832") == 23
    meta, _, geometry, fields = pyogrio.raw.read(tmp_path / "m.gpkg")
    col = dict(zip(meta["fields"], fields))
    assert meta["crs"] == "EPSG:25832" and list(col["marking_id"]) == [m.id for m in ms]
    assert [p.x for p in shapely.from_wkb(geometry)] == [m.x for m in ms]
    assert list(col["weight"]) == [m.weight for m in ms] and [json.loads(e)["k"] for e in col["extra"]] == list(range(23))
    assert np.isnan(col["score"][1]) and col["score"][5] == pytest.approx(5 / 30)

    assert geojson.write_gpkg(tmp_path / "empty.gpkg", iter([]), "EPSG:25832") == 0
    assert pyogrio.read_info(tmp_path / "empty.gpkg")["features"] == 0

    def failing():
        yield from ms[:15]
        raise RuntimeError("the database went away")

    before = (tmp_path / "m.gpkg").read_bytes()
    with pytest.raises(RuntimeError, match="went away"):
        geojson.write_gpkg(tmp_path / "m.gpkg", failing(), "EPSG:25832")
    assert (tmp_path / "m.gpkg").read_bytes() == before and sorted(os.listdir(tmp_path)) == ["empty.gpkg", "m.gpkg"]

def test_a_file_is_read_a_feature_at_a_time_as_json_would_read_it(tmp_path):
    """``read_geojson_file`` parses a FeatureCollection's features one at a time (a city's file
    would not fit in memory parsed whole) and reads the same markings as ``json.loads`` then
    ``read_feature_collection``, whatever the members' order, spacing and placement; what the
    one refuses the other does; a byte order mark is dropped; its progress goes up to the
    exact count."""
    feats = [_pt(8.43 + 1e-5 * k, 49.0 + 1e-6 * k, weight=1 + k, kind="dash", note={"k": [k, None]})
             for k in range(25_003)]  # fmt: skip
    texts = [json.dumps(_fc(*feats)), json.dumps({"features": feats, "bbox": [1, 2, 3, 4], "type": "FeatureCollection",
                                                  "crs": {"properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}}),
             json.dumps(_fc(*feats[:3]), indent="\t").replace("\n", "\r\n"), json.dumps(_fc()), json.dumps(feats[7]),
             " \n" + json.dumps(_fc(*feats[:2]), separators=(",", ":")) + "\n\n"]  # fmt: skip
    for k, text in enumerate(texts):
        path = tmp_path / f"good{k}.geojson"
        path.write_bytes(("\ufeff" if k == 2 else "").encode() + text.encode())
        calls = []
        got = read_geojson_file(path, progress=lambda done, total: calls.append((done, total)))
        assert got == read_feature_collection(json.loads(text)), k
        if k < 2:
            assert [d for d, _ in calls] == sorted({*range(10_000, 25_003, 10_000), 25_003})
            assert calls[-1] == (25_003, 25_003) and all(abs(t - 25_003) < 500 for _, t in calls), calls
    for k, text in enumerate(["{", "[]", "", '{"type": "FeatureCollection", "features": []} {}', "{}",
                              '{"type": "FeatureCollection", "features": [],}', '{"features": [] "type": 1}',
                              '{"type": "FeatureCollection", "features": [%s,]}' % json.dumps(feats[0]),
                              '{"type": "FeatureCollection", "features": [%s' % json.dumps(feats[0]),
                              '{"type": "FeatureCollection", 7: []}', '{"type": "FeatureCollection", "features": 7}',
                              '{"features": [], "crs": {"properties": {"name": "EPSG:25832"}}, "type": "FeatureCollection"}',
                              *[t for t, _ in BAD_FILES]]):  # fmt: skip
        path = tmp_path / f"bad{k}.geojson"
        path.write_text(text)
        with pytest.raises(GeoJSONError) as streamed:
            read_geojson_file(path)
        try:
            read_feature_collection(json.loads(text, parse_constant=_no_constant))
        except json.JSONDecodeError as exc:
            assert f"{exc.msg} at line {exc.lineno} column {exc.colno}" in str(streamed.value), (text, streamed)
        except GeoJSONError as exc:  # what is not JSON says so, and where: "bad7.geojson is not valid JSON: ..."
            assert str(streamed.value) == str(exc) or str(streamed.value) == f"{path} is not valid JSON: {exc}", text
        else:
            raise AssertionError(f"json.loads took {text!r}")
    two = tmp_path / "two.geojson"
    two.write_text('{"type": "FeatureCollection", "features": [], "features": []}')
    with pytest.raises(GeoJSONError, match='two "features" members'):
        read_geojson_file(two)


def test_bad_input_is_one_clear_line_and_writes_nothing(db_url, tmp_path, cli):
    run = cli
    good = tmp_path / "good.geojson"
    good.write_text(json.dumps(_fc(_pt(), _pt(8.431, 49.001))))
    run(["import", "m", good, "--create"], db_url, tmp_path)
    # JSON that Python's own parser reads, but lanemap does not: a number that overflows to
    # infinity (stored in a marking's extra, no export could write it), and nesting deep enough
    # to exhaust the parser's recursion.
    beyond = [(json.dumps(_fc(_pt(weight=2))).replace('"weight": 2', '"note": 1e999, "weight": 2'), "invalid JSON number 1e999"),
              ('{"type": "FeatureCollection", "features": [' + "[" * 100_000 + "]" * 100_000 + "]}",
               "nested too deeply")]  # fmt: skip
    for k, (content, message) in enumerate(BAD_FILES + beyond):
        bad = tmp_path / f"bad{k}.geojson"
        bad.write_text(content)
        proc = run(["import", "m", bad], db_url, tmp_path, check=False)
        assert proc.returncode == 1
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], proc.stderr
        assert "Traceback" not in proc.stderr
    # A file whose last feature is bad writes none of the good ones before it
    # (through a real process, as a user runs it).
    many = _fc(*[_pt(8.43 + i * 1e-4, 49.0) for i in range(500)], _pt(lon=200.0))
    (tmp_path / "many.geojson").write_text(json.dumps(many))
    proc = globals()["run"](["import", "m", "many.geojson"], db_url, tmp_path, check=False)
    assert proc.returncode == 1 and proc.stderr.startswith("error: feature 500: coordinates")
    assert "Traceback" not in proc.stderr
    assert Store(db_url).get_map("m", with_count=True).count == 2


CLI_ERRORS = [
        (["import", "nope", "good.geojson"], "unknown map 'nope'"),
        (["maps", "create", "m"], "map 'm' already exists"),
        (["maps", "create", "bad id"], "invalid map id"),
        (["maps", "create", "geo", "--crs", "EPSG:4326"], "not projected"),
        (["export", "nope", "x.geojson"], "unknown map 'nope'"),
        (["export", "m", "x.shp"], "use a .geojson or .gpkg"),
        (["export", "m", "no/such/x.geojson"], "cannot write no/such/x.geojson: folder no/such does not exist"),
        (["export", "m", "no/such/x.gpkg"], "cannot write no/such/x.gpkg: folder no/such does not exist"),
        (["import", "m", "missing.geojson"], "cannot read missing.geojson"),
        (["maps", "delete", "nope", "--yes"], "unknown map 'nope'"),
]


def test_cli_errors(sqlite_url, tmp_path, cli):
    run = cli
    (tmp_path / "good.geojson").write_text(json.dumps(_fc(_pt())))
    run(["import", "m", "good.geojson", "--create"], sqlite_url, tmp_path)
    for args, message in CLI_ERRORS:
        proc = run(args, sqlite_url, tmp_path, check=False)
        assert proc.returncode != 0, args
        assert message in proc.stderr and "Traceback" not in proc.stderr, (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1


def test_unknown_properties_survive_a_round_trip(store, tmp_path):
    store.create_map("m")
    items = read_feature_collection(_fc(_pt(lane="3", survey={"by": "x"}, kind="dash", weight=40)))
    store.add_markings("m", items, lonlat=True)
    from mapbuilder.geojson import write_geojson

    write_geojson(tmp_path / "o.geojson", store.iter_markings("m"))
    back = read_geojson_file(tmp_path / "o.geojson")[0]
    assert back.extra == {"lane": "3", "survey": {"by": "x"}}
    assert (back.kind, back.weight) == ("dash", 40)


def test_non_wgs84_crs_member_is_refused():
    fc = _fc(_pt())
    fc["crs"] = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::25832"}}
    with pytest.raises(GeoJSONError, match="must be WGS84"):
        read_feature_collection(fc)


def test_retitle_map_cli(db_url, tmp_path, cli):
    cli(["maps", "create", "m", "--title", "old"], db_url, tmp_path)
    out = cli(["maps", "update", "m", "--title", "Karlsruhe, Kaiserstraße"], db_url, tmp_path)
    assert out.stdout.strip() == "map m is now titled 'Karlsruhe, Kaiserstraße'"
    assert json.loads(cli(["maps", "show", "m"], db_url, tmp_path).stdout)["title"] == "Karlsruhe, Kaiserstraße"
    bad = cli(["maps", "update", "nope", "--title", "x"], db_url, tmp_path, check=False)
    assert bad.returncode == 1 and bad.stderr.strip() == "error: unknown map 'nope'"
    long = cli(["maps", "update", "m", "--title", "x" * 501], db_url, tmp_path, check=False)
    assert long.returncode == 1 and "at most 500 characters" in long.stderr


def test_summary_cli(sqlite_url, tmp_path, cli):
    """``lanemap maps summary``: the counts and the review's progress, as lines and as JSON."""
    pts = [_pt(8.43 + k * 1e-4, source="detected", score=0.45 + k / 100, weight=40) for k in range(4)]
    pts += [_pt(8.43, 49.001, kind="stop_line", status="accepted", weight=40)]
    (tmp_path / "g.geojson").write_text(json.dumps(_fc(*pts)))
    cli(["import", "m", "g.geojson", "--create"], sqlite_url, tmp_path)
    lines = cli(["maps", "summary", "m"], sqlite_url, tmp_path).stdout.splitlines()
    assert lines[:5] == ["map m at revision 1: 5 markings",
                         "  status  accepted 1, unreviewed 4",
                         "  source  detected 4, imported 1",
                         "  kind    stop_line 1, unknown 4",
                         "  review  0 of 4 detections reviewed (0.0 %): 0 accepted, 0 rejected, 4 to go"]  # fmt: skip
    assert lines[5] == "  unreviewed detections by score:" and len(lines) == 16
    assert lines[10] == "    0.4-0.5         4  " + "#" * 30 and lines[11].split() == ["0.5-0.6", "0"]
    data = json.loads(cli(["maps", "summary", "m", "--json"], sqlite_url, tmp_path).stdout)
    assert data["detections"] == {"unreviewed": 4, "accepted": 0, "rejected": 0} and data["reviewed_share"] == 0.0
    assert data["unreviewed_scores"][4] == 4 and sum(data["unreviewed_scores"]) == 4
    bad = cli(["maps", "summary", "nope"], sqlite_url, tmp_path, check=False)
    assert bad.returncode == 1 and bad.stderr.strip() == "error: unknown map 'nope'"
    # a district: the box around the first two detections
    box = json.loads(cli(["maps", "summary", "m", "--json", "--bbox", "8.42995,48.9999,8.43015,49.0001"],
                         sqlite_url, tmp_path).stdout)  # fmt: skip
    assert (box["markings"], box["detections"]["unreviewed"], box["unreviewed_scores"][4]) == (2, 2, 2)
    bad = cli(["maps", "summary", "m", "--bbox", "1,2,3"], sqlite_url, tmp_path, check=False)
    assert bad.returncode == 1 and bad.stderr.startswith("error: --bbox: give 4 numbers")


def test_review_cli(sqlite_url, tmp_path, cli):
    """``lanemap review``: a dry run changes nothing; the review is one changeset by ``cli``; bad
    thresholds are one line each."""
    pts = [_pt(8.43 + k * 1e-4, source="detected", score=s, weight=40) for k, s in enumerate([0.05, 0.5, 0.92, 0.97])]
    (tmp_path / "g.geojson").write_text(json.dumps(_fc(*pts)))
    cli(["import", "m", "g.geojson", "--create"], sqlite_url, tmp_path)
    out = cli(["review", "m", "--accept-from", "0.9", "--reject-below", "0.1", "--dry-run"], sqlite_url, tmp_path)
    assert out.stdout.strip() == "map m: would have 2 detections accepted and 1 rejected; nothing changed (--dry-run)"
    assert Store(sqlite_url).summary("m").detections["unreviewed"] == 4
    out = cli(["review", "m", "--accept-from", "0.9", "--reject-below", "0.1", "--comment", "sure"], sqlite_url, tmp_path)
    assert out.stdout.strip() == "map m: 2 detections accepted and 1 rejected in changeset 2 (revision 2)"
    store = Store(sqlite_url)
    assert store.summary("m").detections == {"unreviewed": 1, "accepted": 2, "rejected": 1}
    cs = store.get_changeset("m", 2)
    assert (cs.who, cs.comment, cs.n_update) == ("cli", "sure", 3)
    out = cli(["review", "m", "--accept-from", "0.99"], sqlite_url, tmp_path)
    assert out.stdout.strip() == "map m: no unreviewed detection with a score is in that range; nothing changed"
    for args, says in ((["m"], "give --accept-from SCORE, --reject-below SCORE or both"),
                       (["m", "--accept-from", "0.5", "--reject-below", "0.6"], "--reject-below 0.6 is above --accept-from 0.5"),
                       (["m", "--accept-from", "0.5", "--bbox", "1,2"], "--bbox: give 4 numbers"),
                       (["nope", "--accept-from", "0.5"], "unknown map 'nope'")):  # fmt: skip
        bad = cli(["review", *args], sqlite_url, tmp_path, check=False)
        lines = bad.stderr.strip().splitlines()
        assert bad.returncode == 1 and len(lines) == 1 and lines[0].startswith(f"error: {says}"), (args, lines)
    assert cli(["review", "m", "--accept-from", "1.5"], sqlite_url, tmp_path, check=False).returncode == 2


def test_a_usage_error_is_one_line_naming_the_help(sqlite_url, tmp_path):
    """A mistyped command line (an unknown option or command, a missing argument, a value out of
    range) is one ``error:`` line that names the command's help, exit code 2, as a user sees it;
    the command or group named alone still shows its help."""
    for args, says in ((["import", "g.geojson", "--map", "m"], "error: No such option: --map; see 'lanemap import --help'"),
                       (["import"], "error: Missing argument 'MAP'; see 'lanemap import --help'"),
                       (["nosuch"], "error: No such command 'nosuch'; see 'lanemap --help'"),
                       (["maps", "create"], "error: Missing argument 'MAP'; see 'lanemap maps create --help'"),
                       (["review", "m", "--accept-from", "1.5"],
                        "error: Invalid value for '--accept-from': Input should be less than or equal to 1; "
                        "see 'lanemap review --help'")):  # fmt: skip
        bad = run(args, sqlite_url, tmp_path, check=False)
        assert (bad.returncode, bad.stdout, bad.stderr.splitlines()) == (2, "", [says]), (args, bad.stderr)
    for args in ([], ["maps"]):
        shown = run(args, sqlite_url, tmp_path, check=False)
        assert shown.returncode == 2 and "Usage: lanemap" in shown.stdout + shown.stderr, shown.stderr


def test_delete_map_cli(sqlite_url, tmp_path, cli):
    run = cli
    (tmp_path / "g.geojson").write_text(json.dumps(_fc(_pt())))
    run(["import", "m", "g.geojson", "--create"], sqlite_url, tmp_path)
    assert "deleted map m" in run(["maps", "delete", "m", "--yes"], sqlite_url, tmp_path).stdout
    assert "no maps" in run(["maps", "list"], sqlite_url, tmp_path).stdout


def test_db_upgrade_cli(sqlite_url, tmp_path, cli):
    run = cli
    out = run(["db", "upgrade"], sqlite_url, tmp_path).stdout
    head = migrate.head_revision()
    assert f"(empty) -> {head}" in out
    assert f"database: {head}" in run(["db", "current"], sqlite_url, tmp_path).stdout


def test_import_and_export_show_progress_when_asked(db_url, tmp_path):
    """``--progress``: bars with rate and ETA that end at the file's and the map's counts; none on a pipe."""
    n = 12_345  # more than two of the reader's and the store's steps
    feats = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": [8.40 + i * 1e-6, 49.0]},
              "properties": {"length_m": 3.0, "width_m": 0.15, "bearing_deg": 90.0}} for i in range(n)]
    (tmp_path / "many.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))

    def final(stderr, desc):
        frames = [f for f in stderr.replace("\r", "\n").splitlines() if f.startswith(desc)]
        assert len(frames) >= 3, stderr  # it moved on the way, not only at the end
        return frames[-1]

    proc = run(["import", "m", "many.geojson", "--create", "--progress"], db_url, tmp_path)
    assert proc.stdout.strip() == f"imported {n} markings into m"
    assert re.search(r"100%.*12\.3k/12\.3k .*feature/s", final(proc.stderr, "read many.geojson")), proc.stderr
    assert re.search(r"100%.*12\.3k/12\.3k .*marking/s", final(proc.stderr, "import m")), proc.stderr
    proc = run(["export", "m", "out.gpkg", "--progress"], db_url, tmp_path)
    assert re.search(r"100%.*12\.3k/12\.3k .*marking/s", final(proc.stderr, "export m")), proc.stderr
    assert proc.stdout.strip() == f"exported {n} markings to out.gpkg"
    # Without the flag, on a pipe: nothing on stderr but errors.
    proc = run(["export", "m", "out.geojson"], db_url, tmp_path)
    assert proc.stderr == "" and len(json.loads((tmp_path / "out.geojson").read_text())["features"]) == n


def _command_names(cli) -> set[str]:
    return {c.name for c in cli.registered_commands} | {g.name for g in cli.registered_groups}


def test_each_command_is_found_in_the_module_the_cli_imports_for_it():
    from service.cli import COMMAND_MODULES, make_app

    assert _command_names(make_app()) == set(COMMAND_MODULES)
    for module in set(COMMAND_MODULES.values()):
        assert _command_names(make_app([module])) == {
            name for name, m in COMMAND_MODULES.items() if m == module
        }, module


def test_a_command_imports_only_what_it_needs(sqlite_url, tmp_path):
    """``lanemap maps list`` does not wait for the localizer or the build pipeline to import;
    ``lanemap localize`` does not wait for the build pipeline."""
    probe = (
        "import atexit, sys\n"
        "atexit.register(lambda: print('LOADED', sorted(m for m in ('localizer', 'mapbuilder.build',"
        " 'mapbuilder.cluster', 'rasterio') if m in sys.modules), file=sys.stderr))\n"
        "sys.argv = ['lanemap', *sys.argv[1:]]\n"
        "from service.cli import main\n"
        "main()\n"
    )
    env = dict(os.environ, LANEMAP_DATABASE_URL=sqlite_url, LANEMAP_DATA_DIR=str(tmp_path / "data"))
    loaded = {}
    for args in (["maps", "list"], ["-v", "maps", "list"], ["localize", "--help"], ["--help"]):
        proc = subprocess.run([sys.executable, "-c", probe, *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        line = next(x for x in proc.stderr.splitlines() if x.startswith("LOADED"))
        loaded[" ".join(args)] = line.split(" ", 1)[1]
    assert loaded["maps list"] == loaded["-v maps list"] == "[]", loaded
    assert loaded["localize --help"] == "['localizer']", loaded
    assert "mapbuilder.build" in loaded["--help"], loaded  # the full help lists every command


def test_export_keeps_what_status_and_bbox_select(db_url, tmp_path, cli):
    """``--status`` and ``--bbox`` export exactly the markings they select, in both formats;
    bad values are one line each and write nothing."""
    rng = np.random.default_rng(5)
    statuses = ["unreviewed", "accepted", "rejected"]
    points = [(8.40 + rng.uniform(0, 0.02), 49.0 + rng.uniform(0, 0.01), statuses[k % 3]) for k in range(300)]
    fc = _fc(*[_pt(lon, lat, status=st, kind="dash", weight=10) for lon, lat, st in points])
    (tmp_path / "in.geojson").write_text(json.dumps(fc))
    cli(["import", "m", "in.geojson", "--create"], db_url, tmp_path)
    box = (8.405, 49.002, 8.413, 49.0075)
    inside = {(round(lon, 7), round(lat, 7), st) for lon, lat, st in points
              if box[0] <= lon <= box[2] and box[1] <= lat <= box[3]}  # fmt: skip
    assert 20 < len(inside) < 150
    bbox = ",".join(map(str, box))
    cases = [
        ([], {(round(lo, 7), round(la, 7), st) for lo, la, st in points}),
        (["--status", "accepted,unreviewed"],
         {(round(lo, 7), round(la, 7), st) for lo, la, st in points if st != "rejected"}),
        (["--bbox", bbox], inside),
        (["--bbox", bbox, "--status", "rejected"], {p for p in inside if p[2] == "rejected"}),
        (["--bbox", "1,1,2,2"], set()),
    ]
    for args, want in cases:
        out = cli(["export", "m", "out.geojson", *args], db_url, tmp_path)
        got = json.loads((tmp_path / "out.geojson").read_text())["features"]
        assert {(round(f["geometry"]["coordinates"][0], 7), round(f["geometry"]["coordinates"][1], 7),
                 f["properties"]["status"]) for f in got} == want, args  # fmt: skip
        assert out.stdout.strip() == f"exported {len(want)} markings to out.geojson"
    cli(["export", "m", "out.gpkg", "--bbox", bbox, "--status", "accepted"], db_url, tmp_path)
    info = pyogrio.read_info(tmp_path / "out.gpkg")
    assert info["features"] == sum(p[2] == "accepted" for p in inside)
    (tmp_path / "out.geojson").unlink()
    for args, says in ((["--status", "approved"], "--status: 'approved' is not one of"),
                       (["--bbox", "8.4,49.0,8.3,49.1"], "--bbox: minLon is greater than maxLon"),
                       (["--bbox", "8.4,49.0"], "--bbox: give 4 numbers")):  # fmt: skip
        proc = cli(["export", "m", "out.geojson", *args], db_url, tmp_path, check=False)
        assert proc.returncode == 1 and proc.stderr.strip() == proc.stderr.strip().splitlines()[0]
        assert says in proc.stderr, proc.stderr
        assert not (tmp_path / "out.geojson").exists()


def test_export_to_standard_output_pipes_into_import(sqlite_url, tmp_path):
    """``lanemap export MAP -`` writes GeoJSON to standard output (its count to standard
    error), which ``lanemap import OTHER -`` reads from standard input."""
    fc = _fc(*[_pt(8.43 + 1e-4 * k, 49.0, status="accepted" if k % 2 else "rejected", weight=5 + k)
               for k in range(40)])  # fmt: skip
    (tmp_path / "in.geojson").write_text(json.dumps(fc))
    run(["import", "a", "in.geojson", "--create"], sqlite_url, tmp_path)
    env = dict(os.environ, LANEMAP_DATABASE_URL=sqlite_url, LANEMAP_DATA_DIR=str(tmp_path / "data"))
    env.pop("LANEMAP_DEBUG", None)
    out = subprocess.run([*LANEMAP, "export", "a", "-", "--status", "accepted"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stderr.strip() == "exported 20 markings to standard output"
    exported = json.loads(out.stdout)
    assert len(exported["features"]) == 20
    into = subprocess.run([*LANEMAP, "import", "b", "-", "--create"], input=out.stdout, cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert into.returncode == 0 and into.stdout.strip() == "imported 20 markings into b", into.stderr
    back = subprocess.run([*LANEMAP, "export", "b", "-"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert sorted(f["properties"]["weight"] for f in json.loads(back.stdout)["features"]) == list(
        range(6, 45, 2))
    bad = subprocess.run([*LANEMAP, "import", "b", "-"], input="{not json", cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert bad.returncode == 1
    assert bad.stderr.startswith("error: standard input is not valid JSON") and len(bad.stderr.splitlines()) == 1


def test_version_is_the_installed_distributions(tmp_path):
    from importlib import metadata

    proc = subprocess.run([*LANEMAP, "--version"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"lanemap {metadata.version('lanemap')}"


def _write_layer(path, crs, points, fields: dict, layer="survey", geometry_type="Point", geoms=None):
    import shapely

    import warnings

    geoms = geoms if geoms is not None else shapely.points(np.asarray(points))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # pyogrio's note on a layer written without a CRS
        pyogrio.raw.write(str(path), geometry=shapely.to_wkb(geoms), field_data=[np.asarray(v) for v in fields.values()],
                          fields=list(fields), crs=crs, geometry_type=geometry_type, driver="GPKG", layer=layer)  # fmt: skip


def test_a_geopackage_extra_that_is_not_finite_json_stays_text(sqlite_url, tmp_path, cli):
    """An ``extra`` column is taken apart only where it is JSON with finite numbers: one that
    holds Infinity is kept as text, so that the map it is imported into can be exported again."""
    pts = np.array([[457000.0, 5428000.0], [457010.0, 5428000.0]])
    _write_layer(tmp_path / "x.gpkg", "EPSG:25832", pts,
                 {"extra": np.array(['{"lane": 2}', '{"lane": Infinity}'], dtype=object)})  # fmt: skip
    cli(["import", "x", "x.gpkg", "--create"], sqlite_url, tmp_path)
    got = json.loads(cli(["export", "x", "-"], sqlite_url, tmp_path).stdout)["features"]
    assert [f["properties"].get("lane") for f in got] == [2, None]
    assert got[1]["properties"]["extra"] == '{"lane": Infinity}'


def test_a_geopackage_survey_in_another_crs_is_imported_and_scored(sqlite_url, tmp_path, cli):
    """A GeoPackage of Points in any CRS (here Gauss-Krüger zone 3, as older German surveys are):
    positions through PROJ, known columns as properties, other columns kept, missing values left out;
    ``evaluate`` takes it as the truth."""
    from pyproj import Transformer

    lonlat = np.array([[8.4300 + 2e-4 * k, 49.0000 + 1e-5 * k] for k in range(12)])
    gk = np.column_stack(Transformer.from_crs("EPSG:4326", "EPSG:31467", always_xy=True).transform(*lonlat.T))
    kinds = np.array(["dash"] * 10 + ["stop_line", None], dtype=object)
    _write_layer(tmp_path / "survey.gpkg", "EPSG:31467", gk, {
        "kind": kinds, "weight": np.full(12, 40.0), "length_m": np.full(12, 3.0),
        "score": np.array([np.nan] * 11 + [0.5]), "lane": np.arange(12, dtype=np.int64)})  # fmt: skip
    out = cli(["import", "s", "survey.gpkg", "--create"], sqlite_url, tmp_path)
    assert out.stdout.strip() == "imported 12 markings into s"
    got = sorted(json.loads(cli(["export", "s", "-"], sqlite_url, tmp_path).stdout)["features"],
                 key=lambda f: f["properties"]["lane"])  # fmt: skip
    for f, (lon, lat), kind in zip(got, lonlat, kinds):
        assert f["geometry"]["coordinates"] == pytest.approx([lon, lat], abs=1e-8)  # 1 mm
        p = f["properties"]
        assert (p.get("kind"), p["weight"], p["length_m"], p["source"]) == (kind, 40.0, 3.0, "imported")
    assert [f["properties"]["lane"] for f in got] == list(range(12))
    assert [f["properties"].get("score") for f in got] == [None] * 11 + [0.5]
    # the survey as the truth of the map made from it: everything found
    res = json.loads(cli(["evaluate", "s", "survey.gpkg", "--json"], sqlite_url, tmp_path).stdout)
    assert (res["precision"], res["recall"]) == (1.0, 1.0)


def test_a_geopackage_that_is_not_markings_is_one_line_and_writes_nothing(sqlite_url, tmp_path, cli):
    import shapely

    cli(["maps", "create", "m", "--crs", "EPSG:25832"], sqlite_url, tmp_path)
    pts = np.array([[457000.0 + k, 5428000.0] for k in range(3)])
    _write_layer(tmp_path / "lines.gpkg", "EPSG:25832", None, {"kind": np.array(["solid"], dtype=object)},
                 geometry_type="LineString", geoms=shapely.linestrings([pts]))  # fmt: skip
    _write_layer(tmp_path / "bad.gpkg", "EPSG:25832", pts, {"status": np.array(["accepted", "ok", "rejected"], dtype=object)})
    _write_layer(tmp_path / "nocrs.gpkg", None, pts, {"weight": np.ones(3)})
    _write_layer(tmp_path / "two.gpkg", "EPSG:25832", pts, {"weight": np.ones(3)}, layer="a")
    _write_layer(tmp_path / "two.gpkg", "EPSG:25832", pts, {"weight": np.ones(3)}, layer="b")
    (tmp_path / "text.gpkg").write_text("not a database")
    cases = {
        "lines.gpkg": "lines.gpkg, layer 'survey', row 1: has a LineString (a Point at the marking's centroid is required)",
        "bad.gpkg": "bad.gpkg, layer 'survey', row 2: property 'status' must be one of unreviewed, accepted, rejected, got 'ok'",
        "nocrs.gpkg": "nocrs.gpkg, layer 'survey' has no CRS",
        "two.gpkg": "two.gpkg has 2 layers (a, b) and none named 'markings'",
        "text.gpkg": "text.gpkg is not a GeoPackage GDAL can open",
        "missing.gpkg": "cannot read missing.gpkg",
    }
    for name, says in cases.items():
        proc = cli(["import", "m", name], sqlite_url, tmp_path, check=False)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 1 and len(lines) == 1 and lines[0].startswith(f"error: {says}"), (name, lines)
    assert Store(sqlite_url).get_map("m", with_count=True).count == 0

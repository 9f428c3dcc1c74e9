"""The README's localization examples, run as they are written there."""

from __future__ import annotations

import json
import math
import re
import shlex
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from pyproj import Transformer
from typer.testing import CliRunner

from service.cli import app
from tests._api_helpers import shared_server
from tests.test_api_features import karlsruhe_fc  # noqa: F401 (fixture)

from ._localizer_helpers import karlsruhe_store

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
TRUTH = json.loads((REPO / "docs" / "examples" / "truth.json").read_text())


def _off(answer: dict, truth: dict) -> float:
    return math.hypot(answer["easting"] - truth["easting"], answer["northing"] - truth["northing"])


def _heading_off(answer: dict, truth: dict) -> float:
    return abs((answer["heading_deg"] - truth["heading_deg"] + 180.0) % 360.0 - 180.0)


@pytest.fixture(scope="module")
def stored_map(tmp_path_factory):
    return karlsruhe_store(tmp_path_factory.mktemp("examples"))


def test_the_readme_localize_commands_answer_as_documented(stored_map, monkeypatch, tmp_path):
    monkeypatch.setenv("LANEMAP_DATABASE_URL", stored_map)
    monkeypatch.chdir(REPO)
    lines = [ln for ln in README.splitlines() if ln.startswith("lanemap localize ka ")]
    assert len(lines) == 5, lines
    outs = []
    for line in lines:
        argv = shlex.split(line.split("#")[0])[1:]
        if "--state" in argv:  # the drive's state goes to a scratch folder, not the checkout
            k = argv.index("--state") + 1
            argv[k] = str(tmp_path / argv[k])
        res = CliRunner().invoke(app, argv)
        assert res.exit_code == 0, (line, res.output)
        out = json.loads(res.stdout)
        outs.append(out)
        if "--frames" in argv:
            assert all(p["status"] == "ok" for p in out["poses"]), out
            answer = out["poses"][-1]
        else:
            answer = out
        if "drive-start" in line:  # its seventh frame: checked below against the whole drive's
            continue
        truth = TRUTH["frame"] if "frame.json" in line else TRUTH["drive_last"]
        assert answer["status"] == "ok"
        assert _off(answer, truth) < 0.3 and _heading_off(answer, truth) < 1.0, (line, answer)
    # Streamed in two parts with the state between them: the poses of the whole drive.
    whole, start, rest = outs[2], outs[3], outs[4]
    assert start["poses"] + rest["poses"] == whole["poses"]
    assert rest["state"]["frames"] == 8


def test_the_readme_api_examples_answer_as_documented(karlsruhe_fc):  # noqa: F811
    api = shared_server("sqlite")
    map_id = api.new_map(prefix="readme")
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=api.auth, timeout=60)
    assert r.status_code == 201
    url = f"{api.base_url}/collections/{map_id}/localize"
    # The single frame written out in the README, and the answer printed below it.
    section = README[README.index("### Localization\n"):]
    body = json.loads(re.search(r"/localize -H 'Content-Type: application/json' -d '(\{.*?\})'\n", section,
                                re.S).group(1))
    documented = json.loads(re.search(r"```json\n(\{.*?\})\n```", section, re.S).group(1))
    answer = httpx.post(url, json=body, timeout=60).json()
    assert answer["status"] == documented["status"] == "ok", answer
    assert _off(answer, documented) < 0.05 and _heading_off(answer, documented) < 0.1, answer
    # The example files are request bodies as they are.
    frame = httpx.post(url, content=(REPO / "docs/examples/frame.json").read_bytes(),
                       headers={"Content-Type": "application/json"}, timeout=60).json()
    assert frame["status"] == "ok" and _off(frame, TRUTH["frame"]) < 0.3, frame
    assert "-d @docs/examples/drive.json" in section
    drive = httpx.post(f"{url}/sequence", content=(REPO / "docs/examples/drive.json").read_bytes(),
                       headers={"Content-Type": "application/json"}, timeout=60).json()
    assert len(drive["poses"]) == 8 and drive["poses"][-1]["status"] == "ok", drive
    # The streaming example: its state is the one the drive's first seven frames end with, and
    # the eighth frame sent with it answers as the whole drive does.
    start = httpx.post(f"{url}/sequence", content=(REPO / "docs/examples/drive-start.json").read_bytes(),
                       headers={"Content-Type": "application/json"}, timeout=60).json()
    streaming = section[section.index("**Streaming a drive.**"):]
    documented_state = json.loads(re.search(r'"state": (\{.*?\}\}),\n  "frames"', streaming, re.S).group(1))
    assert start["state"]["frames"] == documented_state["frames"] == 7
    for got, doc in zip(start["state"]["tracks"] + [start["state"]["gps"]],
                        documented_state["tracks"] + [documented_state["gps"]]):  # fmt: skip
        assert got.keys() == doc.keys(), (got, doc)
        assert all(np.asarray(got[k], float) == pytest.approx(np.asarray(doc[k], float), abs=1e-6)
                   for k in got), (got, doc)
    nxt = json.loads((REPO / "docs/examples/drive-next.json").read_text())
    last = httpx.post(f"{url}/sequence", json={**nxt, "state": start["state"]}, timeout=60).json()
    assert start["poses"] + last["poses"] == drive["poses"]
    # The example client streams drive.json frame by frame to the same answers.
    out = subprocess.run([sys.executable, str(REPO / "docs/examples/stream_drive.py"), api.base_url, map_id,
                          str(REPO / "docs/examples/drive.json")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 8 and all(f"p={p['probability']:.4f} lat={p['lat']:.7f}" in line
                                   for line, p in zip(lines, drive["poses"])), (lines, drive["poses"])
    # ... and without naming the map, on the one where the drive starts (this server holds other
    # maps of the same streets, so only the last pose is checked against the truth)
    out = subprocess.run([sys.executable, str(REPO / "docs/examples/stream_drive.py"), api.base_url, "-",
                          str(REPO / "docs/examples/drive.json")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    lat, lon = (float(v) for v in re.search(r"lat=(\S+) lon=(\S+)", lines[-1]).groups())
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True).transform(lon, lat)
    assert len(lines) == 8 and lines[-1].startswith("frame 7: ok")
    picked = re.search(r" map=(\S+)$", lines[0]).group(1)
    assert httpx.get(f"{api.base_url}/collections/{picked}").status_code == 200
    assert not any(" map=" in line for line in lines[1:])  # the drive stayed on it
    assert _off({"easting": e, "northing": n}, TRUTH["drive_last"]) < 0.3
    assert re.search(r"`ok` at (\S+),\s+(\S+),", streaming).groups() == (
        f"{last['poses'][-1]['lat']:.7f}", f"{last['poses'][-1]['lon']:.7f}")
    assert _off(drive["poses"][-1], TRUTH["drive_last"]) < 0.3
    # What /docs offers to try on the demo map answers too.
    from service.routers.localize import LocalizeIn, SequenceIn

    tried = httpx.post(url, json=LocalizeIn.model_json_schema()["example"], timeout=60).json()
    assert tried["status"] == "ok" and _off(tried, TRUTH["frame"]) < 0.3, tried
    from service.routers.localize import PoseOut

    shown = PoseOut.model_json_schema()["example"]  # the answer /docs shows for it
    assert _off(tried, shown) < 0.05 and _heading_off(tried, shown) < 0.1 and tried["inliers"] == shown["inliers"]
    tried = httpx.post(f"{url}/sequence", json=SequenceIn.model_json_schema()["example"], timeout=60).json()
    assert [p["status"] for p in tried["poses"]] == ["ok", "ok"], tried


def test_the_api_documents_the_example_frame_and_drive():
    from service.routers.localize import LocalizeIn, SequenceIn

    example = LocalizeIn.model_json_schema()["example"]
    frame = json.loads((REPO / "docs" / "examples" / "frame.json").read_text())
    assert {k: example[k] for k in ("gps", "observations")} == frame
    LocalizeIn.model_validate(example)
    example = SequenceIn.model_json_schema()["example"]
    drive = json.loads((REPO / "docs" / "examples" / "drive.json").read_text())
    assert example == {"gps": drive["gps"], "frames": drive["frames"][:2]}
    SequenceIn.model_validate(example)


def test_the_mirror_example_keeps_a_copy_current(tmp_path):
    """``docs/examples/mirror_map.py``: a full read, then only changes, a fleet's copy without
    rejected markings, and a map made anew read whole again; the copy always equals the map."""
    from tests._api_helpers import feature

    api = shared_server("sqlite")
    map_id = api.new_map()
    script = REPO / "docs" / "examples" / "mirror_map.py"

    def run(path, *extra):
        proc = subprocess.run([sys.executable, str(script), api.base_url, map_id, str(path), *extra],
                              capture_output=True, text=True, timeout=60)  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        return proc.stdout.strip(), json.loads(path.read_text())

    def items(status=None):
        params = {"limit": 1000, **({"status": status} if status else {})}
        fc = httpx.get(f"{api.base_url}/collections/{map_id}/items", params=params).json()
        return {f["id"]: f["properties"]["version"] for f in fc["features"]}

    def held(copy):
        return {f["id"]: f["properties"]["version"] for f in copy["features"]}

    feats = [feature(8.428 + k * 1e-4, 49.0071, kind="dash") for k in range(6)]
    with api.client(headers=api.auth) as c:
        assert c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats}).status_code == 201
        full, fleet = tmp_path / "copy.geojson", tmp_path / "fleet.geojson"
        line, copy = run(full)
        assert line == f"{full}: 6 markings at revision 1 (6 written, 0 removed by this run)" and held(copy) == items()
        ids = sorted(items(), key=int)
        r = c.post(f"/collections/{map_id}/changesets", json={"comment": "x", "changes": [
            {"op": "update", "id": ids[0], "patch": {"properties": {"status": "rejected"}}},
            {"op": "delete", "id": ids[1]},
            {"op": "create", "feature": feature(8.4291, 49.0071)}]})  # fmt: skip
        assert r.status_code == 201, r.text
        line, copy = run(full)
        assert line.endswith("6 markings at revision 2 (2 written, 1 removed by this run)") and held(copy) == items()
        line, copy = run(fleet, "accepted,unreviewed")
        assert held(copy) == items("accepted,unreviewed") and ids[0] not in held(copy)
        # the map made anew: its revisions go on past the old one's, and a copy of the old one is
        # read whole again
        assert c.delete(f"/collections/{map_id}").status_code == 204
        assert c.post("/collections", json={"id": map_id, "crs": "EPSG:25832"}).status_code == 201
        assert c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats[:2]}).status_code == 201
        line, copy = run(full)
        assert line.endswith("2 markings at revision 4 (2 written, 0 removed by this run)") and held(copy) == items()


def test_a_mirrored_copy_localizes_on_board_as_the_server_does(karlsruhe_fc, tmp_path):  # noqa: F811
    """``mirror_map.py`` then ``localize_onboard.py``: the example frame answered from the copy,
    without the server, in the map's own CRS, at the true pose and where the server puts it."""
    api = shared_server("sqlite")
    map_id = api.new_map(prefix="onboard")
    r = httpx.post(f"{api.base_url}/collections/{map_id}/import", json=karlsruhe_fc, headers=api.auth, timeout=60)
    assert r.status_code == 201
    copy = tmp_path / "copy.geojson"
    examples = REPO / "docs" / "examples"
    out = subprocess.run([sys.executable, str(examples / "mirror_map.py"), api.base_url, map_id, str(copy),
                          "accepted,unreviewed"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert json.loads(copy.read_text())["storageCrs"] == "http://www.opengis.net/def/crs/EPSG/0/25832"
    out = subprocess.run([sys.executable, str(examples / "localize_onboard.py"), str(copy),
                          str(examples / "frame.json")], capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr
    onboard = json.loads(out.stdout)
    served = httpx.post(f"{api.base_url}/collections/{map_id}/localize",
                        content=(examples / "frame.json").read_bytes(),
                        headers={"Content-Type": "application/json"}, timeout=60).json()  # fmt: skip
    assert onboard["status"] == served["status"] == "ok", onboard
    truth = {"lat": TRUTH["frame"]["lat"], "lon": TRUTH["frame"]["lon"]}
    metres = 111_320.0
    for pose in (onboard, served):
        dn = (pose["lat"] - truth["lat"]) * metres
        de = (pose["lon"] - truth["lon"]) * metres * math.cos(math.radians(truth["lat"]))
        assert math.hypot(de, dn) < 0.3 and _heading_off(pose, TRUTH["frame"]) < 1.0, pose
    dn = (onboard["lat"] - served["lat"]) * metres
    de = (onboard["lon"] - served["lon"]) * metres * math.cos(math.radians(served["lat"]))
    # the same markings in the same CRS: the same answer (it differed by 5 cm in a UTM zone of
    # the copy's own choosing)
    assert onboard["crs"] == served["crs"] == "EPSG:25832"
    assert math.hypot(de, dn) < 0.001 and _heading_off(onboard, served) < 0.001, (de, dn)

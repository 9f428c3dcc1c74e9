"""Bad input never gives a server error: problem details, limits, auth settings, and schemathesis."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys

import httpx
import pytest

from tests._api_helpers import feature, shared_server, start_server
from tests.test_api_features import assert_problem

PROBLEM = "application/problem+json"
READ_TOKEN = "read-only-secret"


@pytest.fixture(scope="module")
def api():
    return shared_server("sqlite")


@pytest.fixture(scope="module")
def strict(tmp_path_factory):
    """A server with small limits, tokens required for reads, a read-only token, and CORS for one origin."""
    tmp = tmp_path_factory.mktemp("strict")
    server = start_server(
        f"sqlite:///{tmp / 'db.sqlite'}", tmp / "data",
        env={"LANEMAP_READ_TOKEN_REQUIRED": "1", "LANEMAP_READ_TOKENS": f"fleet={READ_TOKEN}",
             "LANEMAP_MAX_BODY_BYTES": "20000", "LANEMAP_MAX_IMPORT_BYTES": "40000",
             "LANEMAP_MAX_UPLOAD_BYTES": "100000", "LANEMAP_CORS_ORIGINS": "http://editor.example",
             "LANEMAP_MAX_OBSERVATIONS": "50", "LANEMAP_MAX_DRIVE_OBSERVATIONS": "120"},
    )  # fmt: skip
    yield server
    server.stop()


def test_malformed_bodies_are_4xx_problems(api):
    map_id = api.new_map()
    url = f"{api.base_url}/collections/{map_id}/items"
    h = {**api.auth, "Content-Type": "application/json"}
    cases = [
        (b'{"type": "Feature", ', 400, "not valid JSON"),
        (b'{"type": "Feature", "geometry": {"type": "Point", "coordinates": [NaN, 49]}}', 400, "NaN"),
        (b'{"type": "Feature", "geometry": {"type": "Point", "coordinates": [Infinity, 49]}}', 400, "Infinity"),
        (b'{"type": "Feature", "geometry": {"type": "Point", "coordinates": [1e999, 49]}}', 400, "out of range"),
        (b"[" * 100000 + b"]" * 100000, 400, "not valid JSON"),
        (b"\xff\xfe\x00garbage", 400, "not valid JSON"),
        (b'{"a": ' + b"1" * 5000 + b"}", 400, "not valid JSON"),
    ]
    for body, status, words in cases:
        assert_problem(httpx.post(url, content=body, headers=h, timeout=30), status, words)
    r = httpx.post(url, content=b"x=1", headers={**api.auth, "Content-Type": "application/x-www-form-urlencoded"})
    assert_problem(r, 415, "Content-Type")
    r = httpx.post(url, content=b'{"type": "Feature"}', headers={**api.auth, "Content-Type": "text/plain"})
    assert_problem(r, 415)
    assert_problem(httpx.post(url, headers=api.auth), 422, "body")
    assert httpx.get(url).json()["numberMatched"] == 0


@pytest.mark.parametrize("path, status", [
    ("/collections/nope", 404),
    ("/collections/nope/items", 404),
    ("/collections/{m}/items/abc", 404),
    ("/collections/{m}/items/99999999999999999999999", 404),
    ("/collections/{m}/items/-1", 404),
    ("/collections/{m}/items/123456", 404),
    ("/collections/{m}/history?limit=0", 422),
    ("/collections/{m}/changesets/xyz", 404),
    ("/jobs/1234567", 404),
    ("/jobs/x", 404),
    ("/no/such/route", 404),
    ("/collections/{m}/imagery/tiles/WebMercatorQuad/3/9/1.png", 400),
    ("/collections/{m}/imagery/tiles/WebMercatorQuad/99/1/1.png", 422),
    ("/collections/{m}/imagery/tiles/WebMercatorQuad/3/1/1.png", 404),
])  # fmt: skip
def test_unknown_and_invalid_ids_are_problems(api, path, status):
    map_id = api.new_map()
    assert_problem(httpx.get(api.base_url + path.replace("{m}", map_id)), status)


def test_wrong_method_is_405_problem(api):
    r = httpx.put(f"{api.base_url}/conformance", json={}, headers=api.auth)
    assert_problem(r, 405, "PUT")


def test_limits_read_tokens_and_cors(strict):
    c = httpx.Client(base_url=strict.base_url, timeout=30)
    assert_problem(c.get("/collections"), 401, "token")
    assert_problem(c.get("/collections", headers={"Authorization": "Bearer nope"}), 401)
    assert c.get("/collections", headers=strict.auth).status_code == 200
    map_id = strict.new_map()
    big = {"type": "FeatureCollection", "features": [feature(8.4, 49.0, note="x" * 100)] * 300}
    r = c.post(f"/collections/{map_id}/import", json=big, headers=strict.auth)
    assert_problem(r, 413, "40000 bytes")
    # An import has a limit of its own (LANEMAP_MAX_IMPORT_BYTES), above that of other JSON bodies.
    mid = {"type": "FeatureCollection", "features": [feature(8.4, 49.0, note="x" * 100)] * 150}
    assert 20000 < len(json.dumps(mid)) < 40000
    assert_problem(c.post(f"/collections/{map_id}/evaluate", json=mid, headers=strict.auth), 413, "20000 bytes")
    r = c.post(f"/collections/{map_id}/import", json=mid, headers=strict.auth)
    assert r.status_code == 201 and r.json()["imported"] == 150
    # a body that lies about its size is cut off at the limit as well
    with socket.create_connection(("127.0.0.1", int(strict.base_url.rsplit(":", 1)[1]))) as s:
        s.sendall(b"POST /collections/%s/import HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer %s\r\n"
                  b"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
                  % (map_id.encode(), strict.token.encode()))  # fmt: skip
        chunk = b"[" * 8000
        try:
            for _ in range(6):
                s.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
            s.sendall(b"0\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may answer 413 and close before the rest is sent
        reply = s.recv(4096)
    assert reply.startswith(b"HTTP/1.1 413")
    obs = [{"x": 10.0, "y": 0.0, "weight": 1}] * 51
    r = c.post(f"/collections/{map_id}/localize", json={"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0},
                                                         "observations": obs}, headers=strict.auth)  # fmt: skip
    assert_problem(r, 422, "at most 50")
    # a drive's frames are each within the frame limit, together beyond the drive's
    frames = [{"observations": obs[:40], "motion": {"dx": 1.5, "dy": 0.0, "dyaw_deg": 0.0}} for _ in range(4)]
    drive = {"gps": {"lat": 49, "lon": 8.4, "heading_deg": 0}, "frames": frames}
    r = c.post(f"/collections/{map_id}/localize/sequence", json=drive, headers=strict.auth)
    assert_problem(r, 422, "160 observations over 4 frames, at most 120")
    r = c.post(f"/collections/{map_id}/localize/sequence", json={**drive, "frames": frames[:3]}, headers=strict.auth)
    assert r.status_code == 200 and len(r.json()["poses"]) == 3
    pre = c.options(f"/collections/{map_id}/items", headers={
        "Origin": "http://editor.example", "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "authorization,content-type"})  # fmt: skip
    assert pre.headers["access-control-allow-origin"] == "http://editor.example"
    r = c.get(f"/collections/{map_id}/items", headers={**strict.auth, "Origin": "http://editor.example"})
    assert r.headers["access-control-allow-origin"] == "http://editor.example"
    assert "etag" in r.headers["access-control-expose-headers"].lower()
    other = c.get(f"/collections/{map_id}", headers={**strict.auth, "Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    assert c.get("/collections", headers=strict.auth).status_code == 200  # still serving


def test_a_read_token_reads_and_localizes_but_never_writes(strict):
    """``LANEMAP_READ_TOKENS``: a vehicle's token gets every read on a server whose reads need a
    token, and a 403 on every write, which then changes nothing."""
    c = httpx.Client(base_url=strict.base_url, timeout=30)
    reader = {"Authorization": f"Bearer {READ_TOKEN}"}
    map_id = strict.new_map()
    lon, lat = 8.4280, 49.0071
    feats = [feature(lon + 4e-5 * k, lat, kind="dash", length_m=3.0, bearing_deg=90.0) for k in range(12)]
    r = c.post(f"/collections/{map_id}/import", json={"type": "FeatureCollection", "features": feats},
               headers=strict.auth)  # fmt: skip
    assert r.status_code == 201, r.text
    fid = c.get(f"/collections/{map_id}/items", headers=reader).json()["features"][0]["id"]
    before = c.get(f"/collections/{map_id}", headers=reader).json()
    assert before["numberOfFeatures"] == 12
    assert c.get(f"/collections/{map_id}/items/{fid}", headers=reader).status_code == 200
    assert c.get(f"/collections/{map_id}/history", headers=reader).status_code == 200
    body = {"gps": {"lat": lat, "lon": lon, "heading_deg": 90.0}, "observations": [{"x": 10.0, "y": 0.0}]}
    r = c.post(f"/collections/{map_id}/localize", json=body, headers=reader)
    assert r.status_code == 200 and r.json()["status"] in {"ok", "ambiguous", "failed"}, r.text
    r = c.post("/localize", json=body, headers=reader)  # the map picked by the fix (other tests' maps lie there too)
    assert r.status_code == 200 and r.json()["map"], r.text
    assert c.get(f"/collections/{map_id}/summary", headers=reader).json()["numberOfFeatures"] == 12
    r = c.post(f"/collections/{map_id}/evaluate", json={"type": "FeatureCollection", "features": feats[:6]},
               headers=reader)  # fmt: skip
    assert r.status_code == 200 and r.json()["recall"] == 1.0, r.text
    writes = [
        ("POST", "/collections", {"json": {"id": "by-a-reader"}}),
        ("PATCH", f"/collections/{map_id}", {"json": {"title": "renamed"}}),
        ("POST", f"/collections/{map_id}/items", {"json": feature(lon, lat + 1e-4)}),
        ("PATCH", f"/collections/{map_id}/items/{fid}",
         {"json": {"properties": {"status": "rejected"}}, "headers": {"Content-Type": "application/merge-patch+json"}}),
        ("DELETE", f"/collections/{map_id}/items/{fid}", {}),
        ("POST", f"/collections/{map_id}/changesets",
         {"json": {"comment": "x", "changes": [{"op": "delete", "id": fid}]}}),
        ("POST", f"/collections/{map_id}/import", {"json": {"type": "FeatureCollection", "features": feats}}),
        ("POST", f"/collections/{map_id}/imagery", {"content": b"II*\x00", "headers": {"Content-Type": "image/tiff"}}),
        ("POST", f"/collections/{map_id}/builds", {"json": {"imagery": "1"}}),
        ("POST", f"/collections/{map_id}/review", {"json": {"accept_from": 0.0}}),
        ("DELETE", "/jobs/1", {}),
        ("DELETE", f"/collections/{map_id}", {}),
    ]  # fmt: skip
    for method, path, kw in writes:
        headers = {**reader, **kw.pop("headers", {})}
        problem = assert_problem(c.request(method, path, headers=headers, **kw), 403, "'fleet' may only read")
        assert problem["type"].endswith(":forbidden"), (method, path)
    after = c.get(f"/collections/{map_id}", headers=reader).json()
    assert (after["numberOfFeatures"], after["revision"], after["title"]) == (12, before["revision"], before["title"])
    assert c.get("/collections/by-a-reader", headers=reader).status_code == 404
    # A token the server does not know is still a 401, and the write token still writes.
    assert_problem(c.delete(f"/collections/{map_id}/items/{fid}", headers={"Authorization": "Bearer nope"}), 401)
    assert c.delete(f"/collections/{map_id}/items/{fid}", headers=strict.auth).status_code == 204
    spec = c.get("/openapi.json", headers=reader).json()
    schemes = spec["components"]["securitySchemes"]
    assert schemes["WriteToken"]["scheme"] == schemes["ReadToken"]["scheme"] == "bearer"
    ops = [op for item in spec["paths"].values() for m, op in item.items()]
    writers = [op for op in ops if op.get("security") == [{"WriteToken": []}]]
    assert len(writers) >= 14 and all("403" in op["responses"] for op in writers)
    assert not any("403" in op["responses"] for op in ops if op not in writers)
    assert {"ReadToken": []} in spec["paths"]["/collections/{mapId}/localize"]["post"]["security"]
    assert {"ReadToken": []} in spec["paths"]["/localize"]["post"]["security"]


def test_every_answer_carries_a_request_id_that_the_log_shows(api, strict):
    """``X-Request-ID``: the client's (when it is safe to log) or a fresh one, on answers and refusals alike."""
    fresh = re.compile(r"[0-9a-f]{32}")
    ids = [httpx.get(f"{api.base_url}/conformance").headers["x-request-id"] for _ in range(2)]
    assert all(fresh.fullmatch(i) for i in ids) and ids[0] != ids[1]
    mine = "vehicle-42:frame/7.3"
    r = httpx.get(f"{api.base_url}/collections/no-such-map", headers={"X-Request-ID": mine})
    assert_problem(r, 404)
    assert r.headers["x-request-id"] == mine
    # What could forge or flood a log line is replaced, not echoed.
    for bad in ("two words", "x" * 129, "a;b", 'q"uote'):
        got = httpx.get(f"{api.base_url}/conformance", headers={"X-Request-ID": bad}).headers.get_list("x-request-id")
        assert len(got) == 1 and fresh.fullmatch(got[0]), (bad, got)
    # the body guard's refusal, before any route; and the import's own, which reads its body itself
    for path in ("evaluate", "import"):
        r = httpx.post(f"{strict.base_url}/collections/x/{path}", content=b"{}", headers={
            **strict.auth, "Content-Type": "text/plain", "X-Request-ID": f"refused-{path}"})  # fmt: skip
        assert_problem(r, 415)
        assert r.headers["x-request-id"] == f"refused-{path}"
    # a browser may send one and read it back
    pre = httpx.options(f"{strict.base_url}/collections", headers={
        "Origin": "http://editor.example", "Access-Control-Request-Method": "GET",
        "Access-Control-Request-Headers": "authorization,x-request-id"})  # fmt: skip
    assert pre.status_code == 200 and fresh.fullmatch(pre.headers["x-request-id"])
    r = httpx.get(f"{strict.base_url}/collections", headers={**strict.auth, "Origin": "http://editor.example"})
    assert "x-request-id" in r.headers["access-control-expose-headers"].lower()
    # The operator finds the request's access line by its ID.
    lines = [ln for ln in api.log().splitlines() if f"[{mine}]" in ln]
    assert any('"GET /collections/no-such-map HTTP/1.1" 404' in ln for ln in lines), api.log()[-2000:]


#: Every response must be documented: status, content type, headers and body schema.
SCHEMATHESIS_CHECKS = ("not_a_server_error,status_code_conformance,content_type_conformance,"
                       "response_headers_conformance,response_schema_conformance")


def tiny_geotiff(path, crs: str = "EPSG:25832") -> bytes:
    """A 64 x 64 RGB GeoTIFF at 10 cm near the Karlsruhe test features."""
    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=3, dtype="uint8", crs=crs,
                       transform=from_origin(457900.0, 5428000.0, 0.1, 0.1)) as ds:  # fmt: skip
        ds.write(np.random.default_rng(0).integers(0, 255, (3, 64, 64), dtype=np.uint8))
    return path.read_bytes()


def test_schemathesis_finds_no_server_error_or_undocumented_answer(api, tmp_path):
    """Property-based requests over every operation of the OpenAPI document, with a write token.

    Every identifier in a path names a real object of one map (features, a
    changeset, an edit, imagery, a build job), so that reads and writes get past
    404 to the code behind them. No answer may be a 5xx, and every answer must
    match the document: status code, content type, headers and body schema.
    """
    map_id = api.new_map()
    with api.client(headers=api.auth) as c:
        fid = c.post(f"/collections/{map_id}/items", json=feature(8.428, 49.0071)).json()["id"]
        other = c.post(f"/collections/{map_id}/items", json=feature(8.4281, 49.0071)).json()["id"]
        cs = c.post(f"/collections/{map_id}/changesets", json={"comment": "fuzz", "changes": [
            {"op": "update", "id": other, "patch": {"properties": {"status": "accepted"}}}]})  # fmt: skip
        assert cs.status_code == 201, cs.text
        edit = c.get(f"/collections/{map_id}/history", params={"limit": 1}).json()["edits"][0]["id"]
        img = c.post(f"/collections/{map_id}/imagery", content=tiny_geotiff(tmp_path / "tiny.tif"),
                     headers={"Content-Type": "image/tiff"})  # fmt: skip
        assert img.status_code == 201, img.text
        job = c.post(f"/collections/{map_id}/builds", json={"imagery": img.json()["id"]})
        assert job.status_code == 202, job.text
    config = tmp_path / "schemathesis.toml"
    config.write_text(
        f'[parameters]\n"path.mapId" = "{map_id}"\n"path.featureId" = "{fid}"\n'
        f'"path.changesetId" = "{cs.json()["changeset"]}"\n"path.editId" = "{edit}"\n'
        f'"path.imageryId" = "{img.json()["id"]}"\n"path.jobId" = "{job.json()["jobID"]}"\n'
        '\n[[operations]]\ninclude-path = "/collections/{mapId}"\ninclude-method = "DELETE"\n'
        'parameters = { "path.mapId" = "not-this-one" }\n'
    )
    cmd = [
        sys.executable, "-m", "schemathesis.cli", "--config-file", str(config), "run",
        f"{api.base_url}/openapi.json", "--checks", SCHEMATHESIS_CHECKS, "--max-examples", "20",
        "--seed", "20261122", "--workers", "2", "--no-color", "--request-timeout", "30",
        "-H", f"Authorization: Bearer {api.token}",
    ]  # fmt: skip
    env = {**os.environ, "SCHEMATHESIS_HOOKS": ""}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=400, cwd=tmp_path, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-6000:]
    selected = re.search(r"Selected: (\d+)/(\d+)", out)
    assert selected and selected[1] == selected[2], out[-3000:]  # every operation of the document
    assert re.search(rf"Tested: {selected[1]}\b", out), out[-3000:]
    assert "passed" in out and "Server error" not in out
    assert "Traceback" not in api.log()


def test_openapi_documents_problem_answers(api):
    """Errors are documented as problem+json, with the statuses each operation can answer."""
    spec = httpx.get(f"{api.base_url}/openapi.json").json()
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    ops = [(path, m, op) for path, item in spec["paths"].items() for m, op in item.items()]
    assert len(ops) >= 30
    for path, method, op in ops:
        codes = set(op["responses"])
        assert {"400", "401", "404", "422", "503"} <= codes, (method, path)
        for code in codes - {"200", "201", "202", "204"}:
            assert list(op["responses"][code]["content"]) == [PROBLEM], (method, path, code)
    patch = spec["paths"]["/collections/{mapId}/items/{featureId}"]["patch"]["responses"]
    assert {"409", "412", "413", "415"} <= set(patch)
    assert "application/geo+json" in patch["200"]["content"]
    assert "412" not in spec["paths"]["/collections/{mapId}/changesets"]["post"]["responses"]
    # and the document tells the truth: a validation error is such a problem
    r = httpx.get(f"{api.base_url}/collections/x/history", params={"limit": 0})
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert {"type", "title", "status", "detail"} <= set(r.json())

"""``lanemap serve``: the generated write token, the demo map, several workers, a busy port."""

from __future__ import annotations

import math
import os
import re
import socket
import stat
import subprocess
import sys
import time

import httpx

from tests._api_helpers import feature, start_server


def test_token_is_generated_once_and_kept_private(tmp_path):
    db = f"sqlite:///{tmp_path / 'db.sqlite'}"
    server = start_server(db, tmp_path / "data", token=None)
    try:
        token_file = tmp_path / "data" / "api-token"
        token = token_file.read_text().strip()
        assert len(token) >= 32
        assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
        assert token in server.log()
        server.token = token
        map_id = server.new_map()
        assert httpx.post(f"{server.base_url}/collections/{map_id}/items", json=feature(8.4, 49.0),
                          headers={"Authorization": "Bearer nope"}).status_code == 401  # fmt: skip
    finally:
        server.stop()
    again = start_server(db, tmp_path / "data", token=None)
    try:
        assert (tmp_path / "data" / "api-token").read_text().strip() == token
        again.token = token
        r = httpx.post(f"{again.base_url}/collections/{map_id}/items", json=feature(8.4, 49.0), headers=again.auth)
        assert r.status_code == 201
    finally:
        again.stop()


def test_demo_map_has_markings_and_imagery(tmp_path):
    db = f"sqlite:///{tmp_path / 'db.sqlite'}"
    server = start_server(db, tmp_path / "data", args=("--demo",), timeout=240)
    try:
        log = server.log()
        assert "demo map karlsruhe created" in log and "/editor/" in log
        col = httpx.get(f"{server.base_url}/collections/karlsruhe").json()
        assert col["storageCrs"].endswith("/25832")
        n = col["numberOfFeatures"]
        assert 700 < n < 1000  # the laid-out Lanelet2 example
        imagery = httpx.get(f"{server.base_url}/collections/karlsruhe/imagery").json()["imagery"]
        assert len(imagery) == 1
        w, s, e, nn = imagery[0]["bounds"]
        from mapbuilder.crs import to_wgs84

        lon, lat = to_wgs84("EPSG:25832").transform((w + e) / 2, (s + nn) / 2)
        z = 19
        x = int((lon + 180) / 360 * 2**z)
        y = int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * 2**z)
        t = httpx.get(f"{server.base_url}/collections/karlsruhe/imagery/tiles/WebMercatorQuad/{z}/{x}/{y}.png")
        assert t.status_code == 200 and t.content.startswith(b"\x89PNG")
    finally:
        server.stop()
    again = start_server(db, tmp_path / "data", args=("--demo",))
    try:
        assert "demo map karlsruhe found" in again.log()
        assert httpx.get(f"{again.base_url}/collections/karlsruhe").json()["numberOfFeatures"] == n
    finally:
        again.stop()


def test_several_workers_share_the_store(tmp_path):
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data", args=("--workers", "2"))
    try:
        map_id = server.new_map()
        with server.client(headers=server.auth) as c:
            ids = {c.post(f"/collections/{map_id}/items", json=feature(8.4 + i * 1e-4, 49.0)).json()["id"]
                   for i in range(10)}  # fmt: skip
            assert len(ids) == 10
            assert c.get(f"/collections/{map_id}/items").json()["numberMatched"] == 10
        deadline = time.monotonic() + 60
        while len(re.findall(r"Started server process", server.log())) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(re.findall(r"Started server process", server.log())) == 2
    finally:
        server.stop()


def test_busy_port_is_one_line_error(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
        env.update(LANEMAP_DATA_DIR=str(tmp_path / "data"), LANEMAP_API_TOKENS="x")
        proc = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                              capture_output=True, text=True, env=env, cwd=tmp_path, timeout=60)  # fmt: skip
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert proc.stderr.startswith("error: cannot listen on 127.0.0.1:") and "Traceback" not in proc.stderr

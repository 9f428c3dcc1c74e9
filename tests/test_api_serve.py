"""``lanemap serve``: the generated write token, the demo map, several workers, a busy port."""


from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil

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
        # The example the banner points to localizes on the demo map.
        assert "docs/examples/frame.json" in log
        repo = Path(__file__).resolve().parents[1]
        answer = httpx.post(f"{server.base_url}/collections/karlsruhe/localize", timeout=60,
                            content=(repo / "docs/examples/frame.json").read_bytes(),
                            headers={"Content-Type": "application/json"}).json()
        truth = json.loads((repo / "docs/examples/truth.json").read_text())["frame"]
        assert answer["status"] == "ok", answer
        assert math.hypot(answer["easting"] - truth["easting"], answer["northing"] - truth["northing"]) < 0.3
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


def _established_per_process(root_pid: int, port: int) -> dict[int, int]:
    """Established TCP connections to ``port`` held by each process below ``root_pid``."""
    counts = {}
    for child in psutil.Process(root_pid).children(recursive=True):
        try:
            conns = child.net_connections(kind="tcp")
        except psutil.NoSuchProcess:
            continue
        n = sum(1 for c in conns if c.status == psutil.CONN_ESTABLISHED and c.laddr and c.laddr.port == port)
        if n:
            counts[child.pid] = n
    return counts


def _listening_processes(root_pid: int, port: int) -> set[int]:
    """Processes below ``root_pid`` that listen on ``port`` (the server processes)."""
    pids = set()
    for child in psutil.Process(root_pid).children():
        try:
            if any(c.status == psutil.CONN_LISTEN and c.laddr.port == port for c in child.net_connections("tcp")):
                pids.add(child.pid)
        except psutil.NoSuchProcess:
            pass
    return pids


def _get(sock: socket.socket, path: str) -> tuple[int, bytes]:
    """One ``GET`` on a keep-alive HTTP/1.1 connection; the status code and the body."""
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, "connection closed"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = int(re.search(rb"(?im)^content-length:\s*(\d+)", head).group(1))
    while len(body) < length:
        body += sock.recv(65536)
    return int(head.split()[1]), body


def _get_health(sock: socket.socket) -> int:
    """One ``GET /health`` on a keep-alive HTTP/1.1 connection; the status code."""
    return _get(sock, "/health")[0]


def _spread_connections(server, n: int) -> tuple[list[socket.socket], set[int]]:
    """``n`` keep-alive connections made while both server processes are stopped, so that the
    kernel spreads them over the processes' sockets (as a burst under load); and the processes."""
    port = int(server.base_url.rsplit(":", 1)[1])
    workers = _listening_processes(server.proc.pid, port)
    assert len(workers) == 2
    conns: list[socket.socket] = []
    for pid in workers:
        os.kill(pid, signal.SIGSTOP)
    try:
        for _ in range(n):
            conns.append(socket.create_connection(("127.0.0.1", port), timeout=30))
    finally:
        for pid in sorted(workers):  # one process frees up a little before the other
            os.kill(pid, signal.SIGCONT)
            time.sleep(0.3)
    return conns, workers


def test_several_workers_spread_a_burst_of_keep_alive_connections(tmp_path):
    """Each worker has its own SO_REUSEPORT socket, so the kernel spreads connections over them.

    The 16 clients connect while both server processes are busy (stopped), as
    when a burst of clients arrives under load. With one shared socket
    (uvicorn's own multiprocess mode) the process that got the CPU back first
    accepted every queued connection and served those clients for good. 16
    connections all hashed to one of two sockets would happen once in 2**15 runs.

    Whichever process answers ``/metrics`` then reports what both counted.
    """
    from prometheus_client.parser import text_string_to_metric_families

    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data", args=("--workers", "2"))
    port = int(server.base_url.rsplit(":", 1)[1])
    conns: list[socket.socket] = []
    try:
        conns, workers = _spread_connections(server, 16)
        assert [_get_health(c) for c in conns] == [200] * len(conns)
        counts = _established_per_process(server.proc.pid, port)
        assert sum(counts.values()) == len(conns)
        assert set(counts) == workers, counts  # both served some; the supervising parent none
        # The keep-alive connections stay where they are: a second round moves none.
        assert [_get_health(c) for c in conns] == [200] * len(conns)
        assert _established_per_process(server.proc.pid, port) == counts
        # A connection held by each process (its server side's peer is our local port).
        holder = {c.raddr.port: pid for pid in workers for c in psutil.Process(pid).net_connections("tcp")
                  if c.status == psutil.CONN_ESTABLISHED and c.raddr}  # fmt: skip
        one_each = {holder[c.getsockname()[1]]: c for c in conns}
        assert set(one_each) == workers
        for pid, c in one_each.items():
            status, body = _get(c, "/metrics")
            health = [s.value for f in text_string_to_metric_families(body.decode()) for s in f.samples
                      if s.name == "lanemap_http_requests_total" and s.labels["route"] == "/health"]
            assert status == 200 and health == [2.0 * len(conns)], (pid, health)
        counted_in = {psutil.Process(pid).environ()["PROMETHEUS_MULTIPROC_DIR"] for pid in workers}
        assert len(counted_in) == 1 and os.listdir(next(iter(counted_in)))
    finally:
        for c in conns:
            c.close()
        server.stop()
    assert not os.path.exists(next(iter(counted_in)))  # the server's own folder goes with it


def test_an_operators_metrics_folder_is_made_and_emptied_of_an_earlier_runs_counts(tmp_path):
    """``PROMETHEUS_MULTIPROC_DIR`` named by the operator: made if missing, its old counts dropped."""
    from prometheus_client.parser import text_string_to_metric_families

    folder = tmp_path / "metrics" / "lanemap"
    folder.mkdir(parents=True)
    # An earlier run's count, written as a server process writes it.
    stale = "from service import metrics; metrics.http_requests.labels('GET', '/health', '200').inc(1000)"
    env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(folder)}
    subprocess.run([sys.executable, "-c", stale], env=env, check=True, cwd=Path(__file__).resolve().parents[1])
    assert list(folder.glob("counter_*.db"))
    for where in (folder, tmp_path / "missing" / "folder"):
        server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                              env={"PROMETHEUS_MULTIPROC_DIR": str(where)})  # fmt: skip
        try:
            for _ in range(2):
                assert httpx.get(f"{server.base_url}/health").status_code == 200
            text = httpx.get(f"{server.base_url}/metrics").text
        finally:
            server.stop()
        health = [s.value for f in text_string_to_metric_families(text) for s in f.samples
                  if s.name == "lanemap_http_requests_total" and s.labels["route"] == "/health"]
        assert health == [2.0], (where, health)
        assert where.is_dir() and list(where.glob("counter_*.db"))  # the operator's folder stays


def test_worker_that_cannot_start_is_one_line_error(tmp_path):
    """A server process that ends before it serves stops the server with one ``error:`` line."""
    code = (
        "import uvicorn\n"
        "from service import multiprocess\n"
        "from service.cli_errors import fail\n"
        "socks = multiprocess.bind_reuseport('127.0.0.1', 0, 2)\n"
        "config = uvicorn.Config('service.no_such_module:app', log_level='warning')\n"
        "try:\n"
        "    multiprocess.serve(config, socks, shutdown_timeout_s=10)\n"
        "except multiprocess.WorkerStartError as exc:\n"
        "    print('error:', exc)\n"
        "    raise SystemExit(1)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False,
                          cwd=Path(__file__).resolve().parents[1])  # fmt: skip
    assert proc.returncode == 1
    errors = [line for line in proc.stdout.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "before it started serving" in errors[0], proc.stdout + proc.stderr


def test_a_crashed_worker_is_replaced(tmp_path):
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data", args=("--workers", "2"))
    try:
        port = int(server.base_url.rsplit(":", 1)[1])
        before = _listening_processes(server.proc.pid, port)
        assert len(before) == 2
        victim = min(before)
        os.kill(victim, signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            now = _listening_processes(server.proc.pid, port)
            if len(now) == 2 and victim not in now and "ended with exit code -9" in server.log():
                break
            time.sleep(0.2)
        assert len(now) == 2 and victim not in now, server.log()[-3000:]
        assert f"(pid {victim}) ended with exit code -9" in server.log()
        # Every connection is answered, whichever socket the kernel hashes it to.
        for _ in range(20):
            with server.client() as c:
                assert c.get("/health").status_code == 200
        assert server.proc.poll() is None
    finally:
        server.stop()
    assert server.proc.returncode == 0


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


def test_a_bad_setting_is_one_line_naming_its_variable(tmp_path):
    """A value the server cannot run with is refused at start, as the variable it came from."""
    cases = {
        "LANEMAP_MAX_OBSERVATIONS": ("abc", "unable to parse string as an integer (got 'abc')"),
        "LANEMAP_ITEMS_MAX_LIMIT": ("0", "greater than or equal to 1 (got '0')"),
        "LANEMAP_BUILD_WORKERS": ("0", "greater than or equal to 1 (got '0')"),
        "LANEMAP_HEALTH_TIMEOUT_S": ("nan", "(got 'nan')"),
        "LANEMAP_READ_TOKEN_REQUIRED": ("perhaps", "valid boolean"),
        "LANEMAP_READ_TOKENS": ("car=x", "a read token must differ from every write token"),
        "LANEMAP_FEED_RETENTION_DAYS": ("-3", "greater than 0 (got '-3')"),
        "LANEMAP_FEED_PRUNE_INTERVAL_S": ("0", "greater than 0 (got '0')"),
        "LANEMAP_MAP_COVERAGE": ("convex", "Input should be 'hull', 'markings' or 'imagery' (got 'convex')"),
    }
    for name, (value, says) in cases.items():
        env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
        env.update(LANEMAP_DATA_DIR=str(tmp_path / "data"), LANEMAP_API_TOKENS="x", **{name: value})
        proc = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--port", "0"],
                              capture_output=True, text=True, env=env, cwd=tmp_path, timeout=60)  # fmt: skip
        assert proc.returncode == 1, (name, proc.stdout)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {name}: ") and says in lines[0], lines
        assert "car=x" not in lines[0]  # a token is never printed

def test_an_empty_retention_is_no_retention(monkeypatch):
    """Compose passes ``${LANEMAP_FEED_RETENTION_DAYS:-}`` on as an empty variable: deletions are kept."""
    from service.settings import ServiceSettings

    monkeypatch.setenv("LANEMAP_FEED_RETENTION_DAYS", " ")
    assert ServiceSettings().feed_retention_days is None
    monkeypatch.setenv("LANEMAP_FEED_RETENTION_DAYS", "30")
    assert ServiceSettings().feed_retention_days == 30.0


def test_the_server_prunes_old_deletions_from_the_change_feeds(tmp_path):
    """``LANEMAP_FEED_RETENTION_DAYS``: a server forgets the deletions older than the retention
    from every map's feed by itself; a copy from before them is told to read the map whole, a
    map whose deletions are recent keeps them."""
    retention_s = 1.5
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                          env={"LANEMAP_FEED_RETENTION_DAYS": str(retention_s / 86400),
                               "LANEMAP_FEED_PRUNE_INTERVAL_S": "0.2"})  # fmt: skip
    try:
        with server.client(headers=server.auth) as c:
            for map_id in ("old", "new"):
                assert c.post("/collections", json={"id": map_id, "crs": "EPSG:25832"}).status_code == 201
                fc = {"type": "FeatureCollection", "features": [feature(8.428 + k * 1e-4, 49.0071) for k in range(3)]}
                assert c.post(f"/collections/{map_id}/import", json=fc).status_code == 201
            first = c.get("/collections/old/items").json()["features"][0]
            assert c.delete(f"/collections/old/items/{first['id']}").status_code == 204
            deleted_at = time.monotonic()
            at = c.get("/collections/old").json()["revision"]
            assert c.get("/collections/old/changes", params={"since": 1}).json()["removed"] == [
                {"id": first["id"], "revision": at}]
            deadline = time.monotonic() + 30
            while c.get("/collections/old").json()["changesSince"] != at:
                assert time.monotonic() < deadline, server.log()
                time.sleep(0.1)
            assert time.monotonic() - deleted_at > retention_s - 0.2  # not before its time
            r = c.get("/collections/old/changes", params={"since": 1})
            assert r.status_code == 409 and r.json()["type"].endswith("stale-revision")
            assert c.get("/collections/old/changes", params={"since": at}).status_code == 200
            # a deletion made now is kept until it too is older than the retention
            second = c.get("/collections/new/items").json()["features"][0]
            assert c.delete(f"/collections/new/items/{second['id']}").status_code == 204
            time.sleep(0.5)
            assert c.get("/collections/new").json()["changesSince"] == 0
        assert "deletions older than" in server.log()
    finally:
        server.stop()


def test_json_log_lines_carry_the_request_and_its_access_fields(tmp_path):
    """``LANEMAP_LOG_FORMAT=json``: every line the server writes, in its parent and in both
    server processes, is a JSON object; access lines carry method, path, status and the
    request's ID, and so do the lines the localization thread logs for that request."""
    # Without the indexes built at start: a process that starts after the map is made
    # (the second, under load) would build it then, for no request.
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data",
                          env={"LANEMAP_LOG_FORMAT": "json", "LANEMAP_INDEX_PRELOAD": "0"},
                          args=("--workers", "2"))  # fmt: skip
    try:
        map_id = server.new_map()
        lon, lat = 8.4280, 49.0071
        feats = [feature(lon + 1e-5 * k, lat, kind="dash") for k in range(30)]
        r = httpx.post(f"{server.base_url}/collections/{map_id}/import", headers=server.auth, timeout=60,
                       json={"type": "FeatureCollection", "features": feats})  # fmt: skip
        assert r.status_code == 201, r.text
        body = {"gps": {"lat": lat, "lon": lon, "heading_deg": 90.0}, "observations": [{"x": 10.0, "y": 0.0}]}
        for k in range(4):  # both processes build their index of the map; each logs it
            r = httpx.post(f"{server.base_url}/collections/{map_id}/localize", json=body, timeout=60,
                           headers={"X-Request-ID": f"json-{k}"})  # fmt: skip
            assert r.status_code == 200
        assert httpx.get(f"{server.base_url}/collections/no-such-map", timeout=30,
                         headers={"X-Request-ID": "json-404"}).status_code == 404  # fmt: skip
        assert httpx.get(f"{server.base_url}/collections/{map_id}", timeout=30,
                         headers={"X-Request-ID": "json-token", **server.auth}).status_code == 200  # fmt: skip
    finally:
        server.stop()
    records = []
    for line in server.log().splitlines():
        if line.strip():
            record = json.loads(line)  # fails on any line that is not JSON
            assert {"time", "level", "logger", "pid", "request_id", "message"} <= record.keys(), record
            assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", record["time"]), record
            records.append(record)
    access = {r["request_id"]: r for r in records if r["logger"] == "uvicorn.access"}
    assert access["json-404"]["method"] == "GET" and access["json-404"]["status"] == 404
    assert access["json-404"]["path"] == "/collections/no-such-map"
    assert access["json-0"]["method"] == "POST" and access["json-0"]["status"] == 200
    assert access["json-0"]["token"] == "-" and access["json-token"]["token"] == "api"  # the token's name
    built = [r for r in records if f"map {map_id}: spatial index" in r["message"]]
    assert built and all(r["request_id"].startswith("json-") for r in built), built
    assert any(r["message"].startswith("lanemap API:") for r in records)
    ready = [r for r in records if "localizer kernels ready" in r["message"]]
    assert len(ready) == 2 and ready[0]["pid"] != ready[1]["pid"], ready

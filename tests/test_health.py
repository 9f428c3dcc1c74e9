"""``/health`` on real servers: the database probe, the schema revision, no token needed,
and the Docker image's HEALTHCHECK command run against it."""

from __future__ import annotations

import json
import re
import shlex
import sqlite3
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import httpx
import pytest

from mapbuilder import migrate, synth
from tests._api_helpers import REPO, free_port, shared_server, start_server

PROBLEM = "application/problem+json"


def healthcheck_command(port: int) -> list[str]:
    """The Dockerfile's HEALTHCHECK command, pointed at ``port`` and this interpreter."""
    text = (REPO / "docker" / "Dockerfile").read_text()
    m = re.search(r"^HEALTHCHECK\b.*?\bCMD\s+(.+?)(?<!\\)$", text, re.M | re.S)
    assert m, "the Dockerfile has no HEALTHCHECK ... CMD"
    cmd = m.group(1).replace("\\\n", " ").strip()
    assert "/health" in cmd
    args = json.loads(cmd) if cmd.startswith("[") else shlex.split(cmd)
    assert args[0] in ("python", "python3"), args
    return [sys.executable, *[a.replace(":8000/", f":{port}/") for a in args[1:]]]


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_health_reports_database_revision_and_version(kind):
    server = shared_server(kind)
    r = httpx.get(f"{server.base_url}/health", timeout=10)
    assert r.status_code == 200, r.text
    assert r.headers["cache-control"] == "no-store"
    body = r.json()
    assert body["status"] == "ok"
    assert body["version"] == metadata.version("lanemap")
    db = body["database"]
    assert db["ok"] is True and db["dialect"] == kind and db["error"] is None
    assert db["revision"] == db["expected_revision"] == migrate.head_revision()
    assert 0 < db["latency_ms"] < 2000
    assert "dask_scheduler" not in body
    assert httpx.head(f"{server.base_url}/health", timeout=10).status_code == 200


def test_health_needs_no_token_and_fails_on_a_foreign_schema(tmp_path):
    db = tmp_path / "db.sqlite"
    dead_scheduler = f"tcp://127.0.0.1:{free_port()}"
    server = start_server(f"sqlite:///{db}", tmp_path / "data",
                          env={"LANEMAP_READ_TOKEN_REQUIRED": "1", "LANEMAP_DASK_SCHEDULER": dead_scheduler,
                               "LANEMAP_DASK_TIMEOUT_S": "2"})  # fmt: skip
    try:
        assert httpx.get(f"{server.base_url}/collections").status_code == 401
        r = httpx.get(f"{server.base_url}/health")
        assert r.status_code == 200, r.text
        # The scheduler is reported, not judged: reads and edits do not need it.
        assert r.json()["dask_scheduler"] == {"address": dead_scheduler, "reachable": False}
        # A build needs the cluster: its job fails and says why; the server stays healthy.
        with server.client(headers=server.auth) as c:
            map_id = server.new_map()
            img = synth.render(synth.procedural_scene(size_m=(20.0, 20.0), origin=(456000.0, 5430000.0), seed=3),
                               tmp_path / "s.tif", 0.1, seed=3).path  # fmt: skip
            up = c.post(f"/collections/{map_id}/imagery", content=Path(img).read_bytes(),
                        headers={"Content-Type": "image/tiff"})  # fmt: skip
            assert up.status_code == 201, up.text
            job = c.post(f"/collections/{map_id}/builds", json={"imagery": up.json()["id"]}).json()
            deadline = time.monotonic() + 60
            while job["status"] in ("accepted", "running") and time.monotonic() < deadline:
                time.sleep(0.3)
                job = c.get(f"/jobs/{job['jobID']}").json()
        assert job["status"] == "failed" and "Dask scheduler" in job["message"], job
        assert httpx.get(f"{server.base_url}/health").status_code == 200
        check = healthcheck_command(int(server.base_url.rsplit(":", 1)[1]))
        assert subprocess.run(check, capture_output=True, timeout=30).returncode == 0

        # A newer lanemap upgraded the database under this server.
        con = sqlite3.connect(db)
        head = con.execute("SELECT version_num FROM alembic_version").fetchone()[0]
        con.execute("UPDATE alembic_version SET version_num = 'ffffffffffff'")
        con.commit()
        r = httpx.get(f"{server.base_url}/health")
        assert r.status_code == 503, r.text
        assert r.headers["content-type"].startswith(PROBLEM)
        assert int(r.headers["retry-after"]) > 0
        body = r.json()
        assert body["type"].endswith(":schema-mismatch") and body["status"] == 503
        assert "ffffffffffff" in body["detail"] and head in body["detail"]
        assert body["database"]["ok"] is False and body["instance"] == "/health"
        assert subprocess.run(check, capture_output=True, timeout=30).returncode != 0

        con.execute("UPDATE alembic_version SET version_num = ?", (head,))
        con.commit()
        con.close()
        assert httpx.get(f"{server.base_url}/health").status_code == 200
    finally:
        server.stop()

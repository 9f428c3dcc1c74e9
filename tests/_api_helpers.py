"""A real lanemap server for the API tests: ``lanemap serve`` in a subprocess on a free port.

One server per database kind is started per test process and shared by the
API test modules (starting one takes a few seconds); each test creates maps
of its own with unique ids. :func:`start_server` starts a separate one where a
test needs its own settings.
"""

from __future__ import annotations

import atexit
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from sqlalchemy import create_engine, text

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
USGS_DIR = SHARED_DATA / "usgs-hro-colorado"
POSTGRES_ADMIN_URL = os.environ.get(
    "LANEMAP_TEST_POSTGRES_URL", "postgresql://postgres:postgres@127.0.0.1:5432/postgres"
)
TOKEN = "test-token-" + uuid.uuid4().hex


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class ApiServer:
    base_url: str
    data_dir: Path
    proc: subprocess.Popen
    log_path: Path
    token: str | None
    db_url: str
    dropped: list = field(default_factory=list)

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def client(self, **kw) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=kw.pop("timeout", 60.0), **kw)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def new_map(self, crs: str | None = "EPSG:25832", prefix: str = "m") -> str:
        map_id = f"{prefix}-{uuid.uuid4().hex[:10]}"
        body = {"id": map_id, "title": "test map"}
        if crs:
            body["crs"] = crs
        r = httpx.post(f"{self.base_url}/collections", json=body, headers=self.auth, timeout=30)
        assert r.status_code == 201, r.text
        return map_id

    def kill_hard(self) -> None:
        """SIGKILL the server and its worker processes, as a crash would."""
        import signal

        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc.poll() is None:
            import signal

            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        for drop in self.dropped:
            drop()
        self.dropped.clear()


def start_server(db_url: str, data_dir: Path, *, token: str | None = TOKEN, env: dict | None = None,
                 args: tuple[str, ...] = (), timeout: float = 120.0) -> ApiServer:  # fmt: skip
    """Start ``lanemap serve`` and wait until it answers."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    full_env.update(LANEMAP_DATABASE_URL=db_url, LANEMAP_DATA_DIR=str(data_dir), PYTHONUNBUFFERED="1")
    if token is not None:
        full_env["LANEMAP_API_TOKENS"] = token
    full_env.update(env or {})
    log_path = data_dir / f"server-{port}.log"
    fh = open(log_path, "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port), *args],
        cwd=data_dir, env=full_env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    fh.close()
    base = f"http://127.0.0.1:{port}"
    server = ApiServer(base, data_dir, proc, log_path, token, db_url)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"lanemap serve exited with {proc.returncode}:\n{server.log()}")
        try:
            if httpx.get(f"{base}/conformance", timeout=2).status_code in (200, 401):
                return server
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    server.stop()
    raise RuntimeError(f"lanemap serve did not answer within {timeout} s:\n{server.log()}")


def fresh_postgres_db() -> tuple[str, callable]:
    """Create an empty PostgreSQL database; returns its URL and a function that drops it."""
    admin = create_engine(POSTGRES_ADMIN_URL.replace("postgresql://", "postgresql+psycopg://", 1),
                          isolation_level="AUTOCOMMIT")  # fmt: skip
    name = f"lanemap_api_{uuid.uuid4().hex[:12]}"
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))

    def drop():
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()

    return f"{POSTGRES_ADMIN_URL.rsplit('/', 1)[0]}/{name}", drop


_SERVERS: dict[str, ApiServer] = {}


def shared_server(kind: str) -> ApiServer:
    """The test process's server on ``sqlite`` or ``postgresql`` (started on first use)."""
    if kind not in _SERVERS:
        tmp = Path(tempfile.mkdtemp(prefix=f"lanemap-api-{kind}-"))
        if kind == "sqlite":
            server = start_server(f"sqlite:///{tmp / 'lanemap.sqlite'}", tmp / "data")
        else:
            url, drop = fresh_postgres_db()
            server = start_server(url, tmp / "data")
            server.dropped.append(drop)
        _SERVERS[kind] = server

        def cleanup(server=server, tmp=tmp):
            server.stop()
            shutil.rmtree(tmp, ignore_errors=True)

        atexit.register(cleanup)
    return _SERVERS[kind]


def feature(lon: float, lat: float, **props) -> dict:
    props.setdefault("weight", 100.0)
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon, lat]}, "properties": props}

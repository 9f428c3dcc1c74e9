"""Faults, with real processes: the database going away under requests, the server killed
in the middle of a changeset, and imagery storage that is full or cannot be written.

PostgreSQL is stopped and started only in a private cluster on a port of its
own (the shared server at 127.0.0.1:5432 serves other tests meanwhile).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from tests._api_helpers import feature, fresh_postgres_db, start_server
from tests._deploy_helpers import PrivatePostgres, can_mount, tmpfs, wait_for

PROBLEM = "application/problem+json"
LON, LAT = 8.4280, 49.0071


def _is_problem(r: httpx.Response, status: int) -> bool:
    return r.status_code == status and r.headers.get("content-type", "").startswith(PROBLEM)


# --------------------------------------------------------------------------- database outage


@pytest.mark.parametrize("mode", ["fast", "immediate"])  # a clean restart, and a crash
def test_postgres_down_under_requests_is_503_and_recovers_by_itself(mode, tmp_path):
    pg = PrivatePostgres()
    pg.start()
    server = None
    stop = threading.Event()
    try:
        server = start_server(pg.url, tmp_path / "data")
        map_id = server.new_map()
        with server.client(headers=server.auth) as c:
            fid = c.post(f"/collections/{map_id}/items", json=feature(LON, LAT)).json()["id"]

        phase = ["up"]
        seen: list[tuple[str, str, int, str, str | None, dict | None]] = []
        reads = [f"/collections/{map_id}/items?limit=5", f"/collections/{map_id}/items/{fid}",
                 f"/collections/{map_id}", f"/collections/{map_id}/history", "/jobs", "/health"]  # fmt: skip

        errors: list[str] = []

        def hammer() -> None:
            try:
                _hammer()
            except Exception as exc:  # a thread that dies would read as a server that never recovered
                errors.append(f"{phase[0]}: {exc!r}")
                raise

        def _hammer() -> None:
            with httpx.Client(base_url=server.base_url, headers=server.auth, timeout=30) as c:
                i = 0
                while not stop.is_set():
                    i += 1
                    p = phase[0]
                    if i % 4 == 0:
                        r = c.post(f"/collections/{map_id}/items", json=feature(LON + i * 1e-6, LAT))
                        path = "POST items"
                    else:
                        path = reads[i % len(reads)]
                        r = c.get(path)
                    body = r.json() if "json" in r.headers.get("content-type", "") else None
                    seen.append((p, path, r.status_code, r.headers.get("content-type", ""),
                                 r.headers.get("retry-after"), body))  # fmt: skip
                    # The server's own pages need no database and stay up.
                    conf = c.get("/conformance")
                    seen.append((p, "/conformance", conf.status_code, "", None, None))

        threads = [threading.Thread(target=hammer, daemon=True) for _ in range(2)]
        for t in threads:
            t.start()
        wait_for(lambda: sum(s[0] == "up" for s in seen) >= 20, 30, what="requests before the outage")
        phase[0] = "stopping"
        pg.stop(mode)
        # A stop that did not happen would read as answers that should have failed.
        assert not pg.running(), "pg_ctl stop returned with PostgreSQL still running"
        phase[0] = "down"
        # Count what the assertions below count: requests sent while down, beyond
        # the server's own pages (half of what is seen, less those begun before).
        wait_for(lambda: sum(s[0] == "down" and s[1] != "/conformance" for s in seen) >= 30, 30,
                 what="requests during the outage")
        phase[0] = "starting"
        pg.start()
        phase[0] = "back"

        def recovered() -> bool:
            last = [s for s in seen[-24:] if s[0] == "back"]
            return len(last) >= 16 and all(s[2] in (200, 201) for s in last)

        try:
            wait_for(recovered, 30, what="recovery after PostgreSQL came back")
        except AssertionError as exc:
            tail = [(s[0], s[1], s[2], (s[5] or {}).get("detail")) for s in seen[-24:]]
            raise AssertionError(f"{exc}; the last answers: {tail}; the clients' errors: {errors}\nserver: {server.log()[-3000:]}\n"
                                 f"PostgreSQL: {pg.server_log()[-2000:]}") from None
        stop.set()
        for t in threads:
            t.join(30)
        log = server.log()
        # The same server process answered all along: it was never restarted.
        assert server.proc.poll() is None
    finally:
        stop.set()
        if server is not None:
            server.stop()
        pg.destroy()

    assert not [s for s in seen if s[2] >= 500 and s[2] != 503], [s[:3] for s in seen if s[2] >= 500][:5]
    assert "Traceback" not in log, log[-3000:]
    down = [s for s in seen if s[0] == "down" and s[1] != "/conformance"]
    assert len(down) >= 30
    # Every request that needs the database failed cleanly and said when to retry.
    for p, path, status, ctype, retry, body in down:
        assert status == 503, (path, status, body)
        assert ctype.startswith(PROBLEM) and int(retry) > 0, (path, ctype, retry)
        assert body["status"] == 503 and body["type"].endswith((":store-unavailable",)), body
    assert {s[1] for s in down} >= {"POST items", "/health", f"/collections/{map_id}"}
    assert all(s[2] == 200 for s in seen if s[1] == "/conformance")
    back = [s for s in seen if s[0] == "back"]
    assert back and back[-1][2] in (200, 201)


def test_postgres_lost_while_a_tile_is_stored_is_store_unavailable_and_stores_nothing(
        monkeypatch):
    """A tile's markings go to PostgreSQL by COPY, outside SQLAlchemy's own error
    handling: a server lost in the middle is still the store's 'unavailable'."""
    from mapbuilder import store as st

    pg = PrivatePostgres()
    pg.start()
    try:
        store = st.Store(pg.url)
        store.create_map("m", crs="EPSG:25832")
        marks = [st.Marking(x=456000.0 + i, y=5430000.0, weight=1.0) for i in range(50)]
        assert store.replace_detected("m", "t0", marks) == 50
        copy_rows = st._insert_many

        def server_dies_first(conn, table, rows):
            # a shutdown that ends every session (the test cluster commits
            # asynchronously, so a crash could take the earlier tile with it)
            pg.stop("fast")
            return copy_rows(conn, table, rows)

        monkeypatch.setattr(st, "_insert_many", server_dies_first)
        with pytest.raises(st.StoreUnavailableError, match="unavailable"):
            store.replace_detected("m", "t1", marks)
        monkeypatch.undo()
        pg.start()
        wait_for(lambda: _answers(store), 30, what="the store after PostgreSQL came back")
        # the tile in flight left nothing; the one before is whole
        assert {m.tile_key for m in store.iter_markings("m")} == {"t0"}
        assert store.replace_detected("m", "t1", marks) == 50
    finally:
        pg.destroy()


def _answers(store) -> bool:
    try:
        store.get_map("m")
        return True
    except Exception:  # noqa: BLE001 - still coming back
        return False


def test_a_database_that_never_answers_fails_within_the_connect_timeout():
    """A PostgreSQL host that accepts TCP and then stays silent (a hung server, a
    firewall) fails in seconds, not after the operating system's TCP timeout."""
    import socket

    from mapbuilder import store as st

    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)  # the kernel completes the handshake; nobody ever answers
        port = silent.getsockname()[1]
        for query, limit in (("?connect_timeout=1", 1.0), ("", st.PG_CONNECT_TIMEOUT_S)):
            t0 = time.monotonic()
            with pytest.raises(st.StoreUnavailableError, match="timeout"):
                st.Store(f"postgresql://postgres@127.0.0.1:{port}/lanemap{query}")
            assert limit * 0.9 <= time.monotonic() - t0 < limit + 5


def test_serve_with_the_database_down_exits_with_one_clear_line(tmp_path):

    from tests._api_helpers import free_port

    env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    env.update(LANEMAP_DATABASE_URL=f"postgresql://postgres@127.0.0.1:{free_port()}/lanemap",
               LANEMAP_DATA_DIR=str(tmp_path / "data"), LANEMAP_API_TOKENS="t")  # fmt: skip
    out = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--port", str(free_port())],
                         capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert out.returncode != 0
    assert out.stderr.startswith("error: database unavailable") and "Traceback" not in out.stderr, out.stderr


# --------------------------------------------------------------------------- kill -9 mid-changeset


def _writer_holds_lock(kind: str, db_url: str, admin) -> bool:
    """Whether the server has a write transaction open in the database right now."""
    if kind == "sqlite":
        import sqlite3

        con = sqlite3.connect(db_url.removeprefix("sqlite:///"), timeout=0, isolation_level=None)
        try:
            con.execute("BEGIN IMMEDIATE")
            con.execute("ROLLBACK")
            return False
        except sqlite3.OperationalError:  # "database is locked": a writer is inside
            return True
        finally:
            con.close()
    from sqlalchemy import text

    name = db_url.rsplit("/", 1)[1]
    with admin.connect() as conn:
        n = conn.execute(text(
            "SELECT count(*) FROM pg_stat_activity WHERE datname = :d AND pid <> pg_backend_pid() "
            "AND backend_xid IS NOT NULL"), {"d": name}).scalar()  # fmt: skip
    return n > 0


def _map_state(server, map_id: str) -> tuple[dict, list, int, set]:
    """Markings (id -> version, kind, status), changesets, number of edits, comments of the latest edits."""
    with server.client() as c:
        items = c.get(f"/collections/{map_id}/items", params={"limit": 10000})
        changesets = c.get(f"/collections/{map_id}/changesets", params={"limit": 100})
        history = c.get(f"/collections/{map_id}/history", params={"limit": 1000})
    for r in (items, changesets, history):
        assert r.status_code == 200, r.text
    items = items.json()
    assert items["numberReturned"] == items["numberMatched"]
    feats = {f["id"]: (f["properties"]["version"], f["properties"].get("kind"), f["properties"]["status"])
             for f in items["features"]}  # fmt: skip
    history = history.json()
    return feats, changesets.json()["changesets"], history["numberMatched"], {e["comment"] for e in history["edits"]}


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path):
    """A new database of each kind: (kind, its URL, an AUTOCOMMIT engine on the server's admin
    database, None for SQLite); dropped afterwards."""
    if request.param == "sqlite":
        yield "sqlite", f"sqlite:///{tmp_path / 'db.sqlite'}", None
        return
    from sqlalchemy import create_engine

    from tests._api_helpers import POSTGRES_ADMIN_URL

    db_url, drop = fresh_postgres_db()
    admin = create_engine(POSTGRES_ADMIN_URL.replace("postgresql://", "postgresql+psycopg://", 1),
                          isolation_level="AUTOCOMMIT")  # fmt: skip
    yield "postgresql", db_url, admin
    drop()
    admin.dispose()


def _grid(n: int, per_row: int, **props) -> dict:
    """A FeatureCollection of ``n`` markings on a grid of 2 m cells, ``per_row`` a row."""
    return {"type": "FeatureCollection", "features": [
        feature(LON + (i % per_row) * 2e-5, LAT + (i // per_row) * 2e-5, **props) for i in range(n)]}


def test_server_killed_inside_a_changeset_leaves_none_of_it(database, tmp_path):
    kind, db_url, admin = database
    server = start_server(db_url, tmp_path / "data")
    try:
        map_id = server.new_map()
        n = 1000
        fc = _grid(n, 50, kind="dash")
        with server.client(headers=server.auth) as c:
            assert c.post(f"/collections/{map_id}/import", json=fc).status_code == 201
        before = _map_state(server, map_id)
        assert len(before[0]) == n
        ids = sorted(before[0], key=int)
        # Delete half, update a quarter, create as many: one large changeset.
        changes = [{"op": "delete", "id": i, "version": "1"} for i in ids[: n // 2]]
        changes += [{"op": "update", "id": i, "version": "1", "patch": {"properties": {"kind": "doomed"}}}
                    for i in ids[n // 2: 3 * n // 4]]  # fmt: skip
        changes += [{"op": "create", "feature": feature(LON - 0.01 + i * 1e-5, LAT, kind="doomed")}
                    for i in range(n)]  # fmt: skip
        body = {"comment": "doomed", "changes": changes}

        outcome: list = []

        def send() -> None:
            try:
                with httpx.Client(base_url=server.base_url, headers=server.auth, timeout=120) as c:
                    outcome.append(c.post(f"/collections/{map_id}/changesets", json=body))
            except httpx.HTTPError as exc:
                outcome.append(exc)

        t = threading.Thread(target=send, daemon=True)
        t.start()
        wait_for(lambda: outcome or _writer_holds_lock(kind, db_url, admin), 60, period=0.01,
                 what="the changeset's transaction")  # fmt: skip
        assert not outcome, "the changeset finished before the server could be killed"
        server.kill_hard()
        t.join(30)
        assert outcome and isinstance(outcome[0], httpx.HTTPError), outcome

        server = start_server(db_url, tmp_path / "data")
        after = _map_state(server, map_id)
        assert after[0] == before[0]  # every marking as it was, same versions
        assert [cs["comment"] for cs in after[1]] == [cs["comment"] for cs in before[1]]
        assert after[2] == before[2] and "doomed" not in after[3]

        # The database is sound: the same changeset now applies in full.
        with server.client(headers=server.auth) as c:
            r = c.post(f"/collections/{map_id}/changesets", json=body)
        assert r.status_code == 201, r.text
        feats, css, n_edits, comments = _map_state(server, map_id)
        assert n_edits == before[2] + len(changes) and "doomed" in comments
        assert len(feats) == n - n // 2 + n
        assert sum(k == "doomed" for _, k, _ in feats.values()) == n // 4 + n
        assert css[0]["comment"] == "doomed"
    finally:
        server.stop()


def test_server_killed_inside_an_import_job_imports_it_once_after_restart(database, tmp_path):
    """An import job's markings and its success are one transaction: killed while it writes,
    the job imported nothing, and the restarted server runs it again from the body it kept,
    which leaves every marking once, one changeset, and no body behind."""
    kind, db_url, admin = database
    server = start_server(db_url, tmp_path / "data")
    try:
        map_id = server.new_map()
        n = 150_000
        fc = _grid(n, 400)
        headers = {**server.auth, "Prefer": "respond-async"}
        with server.client(headers=headers, timeout=120) as c:
            r = c.post(f"/collections/{map_id}/import", json=fc)
            assert r.status_code == 202, r.text
            job_url = "/jobs/" + r.headers["location"].rsplit("/", 1)[1]  # the restarted server has another port
            # Its writing shows progress past the reading's 30 %, on SQLite too (from a file).
            wait_for(lambda: c.get(job_url).json()["progress"] > 30 and _writer_holds_lock(kind, db_url, admin),
                     60, period=0.01, what="the import's transaction, its progress moving")  # fmt: skip
        server.kill_hard()
        assert len(list((tmp_path / "data" / "imports").glob("*.geojson"))) == 1  # kept for the restart
        assert list((tmp_path / "data" / "imports").glob("*.progress")) or kind == "postgresql"

        server = start_server(db_url, tmp_path / "data")
        with server.client(headers=server.auth) as c:
            job = wait_for(lambda: (j := c.get(job_url).json())["status"] not in ("accepted", "running") and j,
                           120, what="the import job after the restart")  # fmt: skip
            assert job["status"] == "successful" and job["result"]["imported"] == n, job
            assert c.get(f"/collections/{map_id}/items?limit=1").json()["numberMatched"] == n
            changesets = c.get(f"/collections/{map_id}/changesets").json()["changesets"]
            assert [cs["created"] for cs in changesets] == [n]
        wait_for(lambda: not list((tmp_path / "data" / "imports").glob("*")), 10, what="the body removed")
        assert "Traceback" not in server.log()
    finally:
        server.stop()


# --------------------------------------------------------------------------- storage faults


def _noise_geotiff(path: Path, px: int) -> bytes:
    """An uncompressed RGB GeoTIFF of noise (incompressible), ``px`` x ``px`` at 10 cm in Karlsruhe."""
    rgb = np.random.default_rng(px).integers(0, 256, (3, px, px), dtype=np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=px, height=px, count=3, dtype="uint8",
                       crs="EPSG:25832", transform=from_origin(456000.0, 5430000.0, 0.1, 0.1)) as ds:  # fmt: skip
        ds.write(rgb)
    return path.read_bytes()


def _files_under(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()]


def _upload(server, map_id: str, data: bytes) -> httpx.Response:
    with server.client(headers={**server.auth, "Content-Type": "image/tiff"}) as c:
        return c.post(f"/collections/{map_id}/imagery", content=data)


def _check_full(server, map_id: str, imagery: Path, big: bytes, medium: bytes, small: bytes) -> None:
    """A full store refuses both the streamed upload and the COG, keeps nothing, then recovers."""
    for data, phase in ((big, "while streaming"), (medium, "while writing the COG")):
        r = _upload(server, map_id, data)
        assert _is_problem(r, 507), (phase, r.status_code, r.text)
        body = r.json()
        assert body["type"].endswith(":insufficient-storage") and body["title"] == "Insufficient storage", body
        assert "storage is full" in body["detail"]
        assert _files_under(imagery) == [], (phase, _files_under(imagery))
    with server.client() as c:
        assert c.get(f"/collections/{map_id}/imagery").json()["imagery"] == []
    # The failed uploads freed their space: a small image still fits, with no restart.
    r = _upload(server, map_id, small)
    assert r.status_code == 201, r.text
    assert len(_files_under(imagery)) == 1
    assert "Traceback" not in server.log()


@pytest.fixture
def images(tmp_path):
    return (_noise_geotiff(tmp_path / "big.tif", 900),      # 2.4 MB: over the limit while streaming
            _noise_geotiff(tmp_path / "medium.tif", 700),   # 1.5 MB: fits raw, its COG (+overviews) does not
            _noise_geotiff(tmp_path / "small.tif", 64))  # fmt: skip

LIMIT = 1536 * 1024


def test_upload_over_a_file_size_limit_is_507_and_leaves_no_file(tmp_path, images):
    # RLIMIT_FSIZE on the server process: every write past it fails with EFBIG.
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data")
    try:
        resource.prlimit(server.proc.pid, resource.RLIMIT_FSIZE, (LIMIT, LIMIT))
        map_id = server.new_map()
        _check_full(server, map_id, tmp_path / "data" / "imagery", *images)
    finally:
        server.stop()


def _need_mount(why: str) -> None:
    """Fail, naming what is missing, where this run cannot mount a tmpfs.

    ``scripts/test.sh`` (the README's test command, what CI runs) installs
    Debian packages as root or through sudo, the rights a tmpfs mount needs,
    so a missing mount is a failure, never a silent skip. A user without
    those rights deselects these tests (``-k "not full_disk and not
    unwritable"``).
    """
    if not can_mount():
        pytest.fail(f"{why}; mount(8) is not available to this run", pytrace=False)


def test_upload_to_a_full_disk_is_507_and_leaves_no_file(tmp_path, images):
    _need_mount("a full disk is simulated with a small tmpfs, which needs mount as root or through sudo")
    imagery = tmp_path / "data" / "imagery"
    with tmpfs(imagery, LIMIT):
        server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data")
        try:
            map_id = server.new_map()
            _check_full(server, map_id, imagery, *images)
        finally:
            server.stop()


def test_upload_to_an_unwritable_folder_is_a_clear_500_and_leaves_no_file(tmp_path, images):
    imagery = tmp_path / "data" / "imagery"
    imagery.mkdir(parents=True)
    server = start_server(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path / "data")
    try:
        map_id = server.new_map()
        if os.geteuid() == 0:
            # Root writes through file modes: make the folder a read-only mount instead.
            _need_mount("root without mount: no folder can be made unwritable to this server")
            ctx = tmpfs(imagery, LIMIT, read_only=True)
        else:
            imagery.chmod(0o555)
            ctx = None
        try:
            if ctx is not None:
                ctx.__enter__()
            r = _upload(server, map_id, images[2])
            assert _is_problem(r, 500), r.text
            body = r.json()
            assert body["type"].endswith(":storage-not-writable") and body["title"] == "Storage not writable"
            assert "cannot write" in body["detail"] and str(tmp_path) not in body["detail"]
            assert _files_under(imagery) == []
        finally:
            if ctx is not None:
                ctx.__exit__(None, None, None)
            else:
                imagery.chmod(0o755)
        # Writable again: the same server takes the upload.
        r = _upload(server, map_id, images[2])
        assert r.status_code == 201, r.text
        assert "Traceback" not in server.log()
    finally:
        server.stop()


def test_export_to_a_full_disk_is_one_line_and_keeps_the_earlier_file(tmp_path):
    """An export that runs out of space names the file, leaves no partial file and
    keeps what an earlier export wrote there."""
    _need_mount("a full disk is simulated with a small tmpfs, which needs mount as root or through sudo")
    import json

    rng = np.random.default_rng(0)
    features = [{"type": "Feature", "properties": {"kind": "dash", "weight": 40},
                 "geometry": {"type": "Point", "coordinates": [LON + dx, LAT + dy]}}
                for dx, dy in rng.uniform(-0.01, 0.01, (3000, 2))]  # fmt: skip
    src = tmp_path / "in.geojson"
    src.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    env = dict(os.environ, LANEMAP_DATABASE_URL=f"sqlite:///{tmp_path / 'db.sqlite'}",
               LANEMAP_DATA_DIR=str(tmp_path / "data"))  # fmt: skip
    env.pop("LANEMAP_DEBUG", None)

    def lanemap(*args):
        return subprocess.run([sys.executable, "-m", "service.cli", *args], env=env, cwd=tmp_path,
                              capture_output=True, text=True, timeout=120)  # fmt: skip

    assert lanemap("import", "m", str(src), "--create").returncode == 0
    out = tmp_path / "out"
    with tmpfs(out, 256 * 1024):
        for name in ("m.geojson", "m.gpkg"):
            earlier = b"an earlier export\n"
            (out / name).write_bytes(earlier)
            proc = lanemap("export", "m", str(out / name))
            assert proc.returncode == 1, proc.stdout
            lines = proc.stderr.strip().splitlines()
            assert lines == [f"error: cannot write {out / name}: No space left on device"] or (
                name.endswith(".gpkg") and len(lines) == 1
                and lines[0].startswith(f"error: cannot write {out / name}: No space left on device (")
            ), lines  # fmt: skip
            assert "Traceback" not in proc.stderr and ".part" not in proc.stderr
            assert sorted(p.name for p in out.iterdir()) == [name], "a partial file was left"
            assert (out / name).read_bytes() == earlier
            (out / name).unlink()


def test_a_database_copy_to_a_full_disk_is_one_line_and_leaves_no_map(tmp_path):
    """``lanemap db copy`` into an SQLite file on a small tmpfs: the disk fills mid-copy; one
    error line, and the target holds none of the copy (its one transaction rolled back)."""
    _need_mount("a full disk is simulated with a small tmpfs, which needs mount as root or through sudo")
    from mapbuilder.model import Marking
    from mapbuilder.store import Store

    live = f"sqlite:///{tmp_path / 'live.sqlite'}"
    store = Store(live)
    store.create_map("big", crs="EPSG:25832")
    store.bulk_load("big", (Marking(x=457000.0 + k * 0.5, y=5428000.0, length_m=3.0, weight=40.0,
                                    extra={"note": "x" * 200}) for k in range(5000)))  # fmt: skip
    store.close()
    env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    env.update(LANEMAP_DATABASE_URL=live, LANEMAP_DATA_DIR=str(tmp_path / "data"))
    small = tmp_path / "small"
    with tmpfs(small, 512 * 1024):
        target = f"sqlite:///{small / 'copy.sqlite'}"
        proc = subprocess.run([sys.executable, "-m", "service.cli", "db", "copy", target], env=env, cwd=tmp_path,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert proc.returncode == 1, proc.stdout
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: the copy to {target} failed and wrote nothing: "), lines
        assert "full" in lines[0] and "Traceback" not in proc.stderr
        left = Store(target)
        assert left.list_maps() == []
        left.close()

"""The production topology without containers: PostgreSQL, a Dask scheduler with two
workers, and two ``lanemap serve`` processes sharing the database, the imagery
folder and the scheduler — all real processes, as ``docker/compose.yaml`` runs them.

A build started through one server is watched and read through the other; an
edit made on one is seen, with the same ETag, on the other; a Dask worker
killed mid-build costs nothing: the map equals that of an uninterrupted build.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from mapbuilder import synth
from tests._api_helpers import ApiServer, fresh_postgres_db, start_server
from tests._deploy_helpers import DaskProcesses, start_dask, wait_for

pytestmark = pytest.mark.postgres


@dataclass
class Topology:
    a: ApiServer
    b: ApiServer
    dask: DaskProcesses
    image: Path
    #: The marking set of an uninterrupted build of ``image`` (set by the first test).
    reference: list | None = None


@pytest.fixture(scope="module")
def topology(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("topology")
    scene = synth.procedural_scene(size_m=(120.0, 60.0), origin=(456000.0, 5430000.0), seed=11)
    image = Path(synth.render(scene, tmp / "scene.tif", 0.1, seed=11).path)
    with contextlib.ExitStack() as stack:
        db_url, drop = fresh_postgres_db()
        stack.callback(drop)
        dask = start_dask(tmp / "dask", n_workers=2)
        stack.callback(dask.stop)
        env = {"LANEMAP_DASK_SCHEDULER": dask.address}
        data = tmp / "data"  # the imagery volume every server and worker sees
        a = start_server(db_url, data, env=env)
        stack.callback(a.stop)
        b = start_server(db_url, data, env=env)
        stack.callback(b.stop)
        yield Topology(a, b, dask, image)


def _upload(server: ApiServer, map_id: str, image: Path) -> str:
    with server.client(headers={**server.auth, "Content-Type": "image/tiff"}) as c:
        r = c.post(f"/collections/{map_id}/imagery", content=image.read_bytes())
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _start_build(server: ApiServer, map_id: str, imagery_id: str) -> str:
    with server.client(headers=server.auth) as c:
        r = c.post(f"/collections/{map_id}/builds", json={"imagery": imagery_id, "tile_px": 128})
    assert r.status_code == 202, r.text
    return r.json()["jobID"]


def _wait_job(server: ApiServer, job_id: str, timeout: float = 60.0) -> dict:
    def done():
        job = httpx.get(f"{server.base_url}/jobs/{job_id}", timeout=10).json()
        return job if job["status"] in ("successful", "failed", "dismissed") else None

    return wait_for(done, timeout, period=0.2, what=f"job {job_id}")


def _markings(server: ApiServer, map_id: str) -> list[dict]:
    r = httpx.get(f"{server.base_url}/collections/{map_id}/items", params={"limit": 10000}, timeout=30)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["numberReturned"] == body["numberMatched"]
    return body["features"]


def _reference(topology: Topology) -> list[tuple]:
    """The marking set of an uninterrupted build (built here when a test runs alone)."""
    if topology.reference is None:
        a, b = topology.a, topology.b
        map_id = a.new_map()
        job = _wait_job(b, _start_build(a, map_id, _upload(a, map_id, topology.image)))
        assert job["status"] == "successful", job
        topology.reference = _marking_set(_markings(b, map_id))
    return topology.reference


def _marking_set(features: list[dict]) -> list[tuple]:
    """What a build decides about each marking, independent of ids and map."""
    return sorted(
        (round(f["geometry"]["coordinates"][0], 9), round(f["geometry"]["coordinates"][1], 9),
         f["properties"]["weight"], round(f["properties"]["length_m"], 6), round(f["properties"]["bearing_deg"], 6))
        for f in features
    )  # fmt: skip


def test_build_on_dask_through_a_watched_through_b_and_edits_agree(topology):
    a, b = topology.a, topology.b
    map_id = a.new_map()
    imagery_id = _upload(a, map_id, topology.image)
    # The imagery is listed by the other server: one database, one imagery folder.
    assert [i["id"] for i in httpx.get(f"{b.base_url}/collections/{map_id}/imagery").json()["imagery"]] == [imagery_id]
    tasks_before = topology.dask.tasks_done("process_tiles")
    job_id = _start_build(a, map_id, imagery_id)
    job = _wait_job(b, job_id)
    assert job["status"] == "successful", job
    assert job["progress"] == 100
    feats = _markings(b, map_id)
    assert len(feats) > 50
    assert {f["properties"]["source"] for f in feats} == {"detected"}
    # The tiles ran on the Dask workers, not in the servers' build processes.
    assert topology.dask.tasks_done("process_tiles") > tasks_before

    # An edit through A is what B serves, with the same ETag.
    fid = feats[0]["id"]
    with a.client(headers=a.auth) as ca, b.client(headers=b.auth) as cb:
        r0 = cb.get(f"/collections/{map_id}/items/{fid}")
        etag0 = r0.headers["etag"]
        assert ca.get(f"/collections/{map_id}/items/{fid}").headers["etag"] == etag0
        r = ca.patch(f"/collections/{map_id}/items/{fid}", headers={"If-Match": etag0,
                     "Content-Type": "application/merge-patch+json"}, json={"properties": {"status": "accepted"}})  # fmt: skip
        assert r.status_code == 200, r.text
        etag1 = r.headers["etag"]
        assert etag1 != etag0
        rb = cb.get(f"/collections/{map_id}/items/{fid}")
        assert rb.headers["etag"] == etag1
        assert rb.json()["properties"]["status"] == "accepted"
        # B refuses a write based on the version A replaced.
        stale = cb.patch(f"/collections/{map_id}/items/{fid}", headers={"If-Match": etag0,
                         "Content-Type": "application/merge-patch+json"}, json={"properties": {"status": "rejected"}})  # fmt: skip
        assert stale.status_code == 412, stale.text
        hist = cb.get(f"/collections/{map_id}/history", params={"feature": fid}).json()["edits"]
        assert hist[0]["op"] == "update" and hist[0]["after"]["status"] == "accepted"
    topology.reference = _marking_set(feats)


def test_a_worker_killed_mid_build_costs_nothing(topology):
    from distributed import Client

    a, b, dask = topology.a, topology.b, topology.dask
    reference = _reference(topology)
    map_id = a.new_map()
    imagery_id = _upload(a, map_id, topology.image)
    before = dask.task_counts("process_tiles")
    with Client(dask.address, timeout="10s") as client:
        names = {addr: w["name"] for addr, w in client.scheduler_info(n_workers=-1)["workers"].items()}
        job_id = _start_build(a, map_id, imagery_id)

        def busy_worker():
            held = {addr: len(keys) for addr, keys in client.processing().items() if keys}
            return max(held, key=held.get) if held else None

        # Killed at once: a request in between gave the worker time to finish the tile in its hands.
        victim = wait_for(busy_worker, 60, period=0.005, what="a worker running the build's tiles")
        dask.kill_worker(int(str(names[victim]).lstrip("w")))
        status = httpx.get(f"{b.base_url}/jobs/{job_id}").json()["status"]
        assert status in ("accepted", "running"), "the build ended before a worker could be killed"
        t0 = time.monotonic()
        wait_for(lambda: victim not in client.scheduler_info(n_workers=-1)["workers"], 30,
                 what="the scheduler to notice the lost worker")  # fmt: skip
    job = _wait_job(b, job_id)
    assert job["status"] == "successful", (job, dask.log()[-3000:])
    assert time.monotonic() - t0 < 60
    after = dask.task_counts("process_tiles")
    delta = {k: after.get(k, 0) - before.get(k, 0) for k in after}
    # The worker died with tiles in hand: the scheduler released them and ran them again
    # elsewhere. A run that had already finished on the dead worker may be released and run
    # again too, so up to all of them reach memory; the stored markings must not care.
    assert delta.get("released", 0) >= 1, delta
    assert delta["processing"] - delta["released"] <= delta["memory"] <= delta["processing"], delta
    feats = _markings(b, map_id)
    got = _marking_set(feats)
    assert len({f["id"] for f in feats}) == len(feats)
    assert len(set(got)) == len(got), "a marking was stored twice"
    assert got == reference


def _runner_pid(data_dir: Path) -> int:
    """The process holding the build-job lock of ``data_dir`` (from /proc/locks)."""
    inode = (data_dir / "job-runner.lock").stat().st_ino
    for line in Path("/proc/locks").read_text().splitlines():
        parts = line.split()  # "1: FLOCK  ADVISORY  WRITE <pid> <major>:<minor>:<inode> 0 EOF"
        if len(parts) >= 6 and parts[1] == "FLOCK" and parts[5].rsplit(":", 1)[-1] == str(inode):
            return int(parts[4])
    raise AssertionError("no process holds the build-job lock")


def test_the_build_survives_its_server_killed_and_resumes_on_the_other(topology):
    from mapbuilder.store import Store

    a, b = topology.a, topology.b
    reference = _reference(topology)
    map_id = a.new_map()
    imagery_id = _upload(a, map_id, topology.image)
    owner_pid = _runner_pid(a.data_dir)
    runner, other = (a, b) if owner_pid == a.proc.pid else (b, a)
    assert owner_pid == runner.proc.pid
    job_id = _start_build(other, map_id, imagery_id)  # recorded by one server, run by the other
    store = Store(a.db_url)
    try:
        total = 50  # 120 m x 60 m at 10 cm in 128 px tiles
        done = wait_for(lambda: len(store.done_tiles(int(job_id))) or None, 60, period=0.01,
                        what="the first tiles of the build")  # fmt: skip
        runner.kill_hard()  # the server and its build process, as a crash would
        assert 0 < done < total, done
        # The surviving server takes the runner over and resumes the job where it stopped.
        job = _wait_job(other, job_id, timeout=90)
        assert job["status"] == "successful", (job, other.log()[-3000:])
        assert len(store.done_tiles(int(job_id))) == total
    finally:
        store.close()
    feats = _markings(other, map_id)
    got = _marking_set(feats)
    assert len(set(got)) == len(got) == len(feats), "a marking was stored twice"
    assert got == reference
    assert "takes over" in other.log()

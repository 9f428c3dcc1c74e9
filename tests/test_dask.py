"""The build on a real Dask distributed cluster gives the same map as a local build."""

from __future__ import annotations

import pytest
from distributed import LocalCluster

from mapbuilder import synth
from mapbuilder.build import BuildError, BuildParams, build_map
from mapbuilder.store import Store
from tests._build_helpers import pipeline_model


def _rows(store, map_id):
    return sorted(
        (round(m.x, 6), round(m.y, 6), m.weight, round(m.bearing_deg, 6), m.tile_key)
        for m in store.iter_markings(map_id)
    )


def test_dask_cluster_build_matches_local(tmp_path, sqlite_url):
    scene = synth.procedural_scene(size_m=(50.0, 40.0), origin=(456000.0, 5430000.0), seed=11)
    image = synth.render(scene, tmp_path / "scene.tif", 0.1, seed=11).path
    params = BuildParams(tile_px=128, model=pipeline_model())
    store = Store(sqlite_url)
    local = build_map(store, "local", [image], params, workers=1, progress=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        remote = build_map(store, "dask", [image], params, dask_address=cluster.scheduler_address,
                           progress=False)
    assert remote.tiles_run == local.tiles_run == local.tiles_total > 4
    assert remote.markings == local.markings > 10
    assert _rows(store, "dask") == _rows(store, "local")
    assert store.imaged_footprint("dask").equals(store.imaged_footprint("local"))  # the workers' ground
    assert store.get_job(remote.job_id).status == "successful"
    store.close()


def test_unreachable_scheduler_is_a_clear_error(tmp_path, sqlite_url):
    scene = synth.procedural_scene(size_m=(20.0, 20.0), seed=1)
    image = synth.render(scene, tmp_path / "s.tif", 0.1, seed=1).path
    store = Store(sqlite_url)
    with pytest.raises(BuildError, match="Dask scheduler"):
        build_map(store, "m", [image], BuildParams(model=pipeline_model()),
                  dask_address="tcp://127.0.0.1:9", dask_timeout_s=2, progress=False)
    job = store.find_jobs(kind="build")[0]
    assert job.status == "failed"
    store.close()


_FAULTS = """
import resource, sys
import numpy as np
from mapbuilder.build import process_tile, _restore_malloc_thresholds
if sys.argv[1] == "tile worker":
    _restore_malloc_thresholds()  # what process_tile does first
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(2_000_000); del a
f0 = faults()
for _ in range(20):
    a = np.ones(2_000_000); del a  # a tile-sized array, 16 MB, made and dropped
print(faults() - f0)
"""


def test_tile_workers_undo_the_malloc_trim_threshold_dask_sets():
    """Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which makes glibc
    map every large array afresh; the tile function restores the thresholds, so a
    worker reuses freed memory instead of faulting its pages in again."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    faults = {}
    for mode in ("plain", "tile worker"):
        out = subprocess.run([sys.executable, "-c", _FAULTS, mode], env=env, capture_output=True,
                             text=True, timeout=120, check=True)
        faults[mode] = int(out.stdout.strip().splitlines()[-1])
    assert faults["plain"] > 5000, faults  # the variable's effect, as Dask workers see it
    assert faults["tile worker"] < faults["plain"] / 10, faults

"""The tile grid: cores partition the image, halos are clipped, ownership is exclusive."""

from __future__ import annotations

import numpy as np
import pytest

from mapbuilder.tiling import image_tag, tile_grid, tile_key


@pytest.mark.parametrize("width, height, tile_px, halo", [(1000, 700, 256, 40), (256, 256, 256, 8),
                                                          (1, 3000, 512, 64)])
def test_cores_partition_the_image(width, height, tile_px, halo):
    grid = tile_grid(width, height, tile_px, halo)
    cover = np.zeros((height, width), np.int32)
    for t in grid:
        c0, r0, w, h = t.core
        cover[r0:r0 + h, c0:c0 + w] += 1
    assert (cover == 1).all()
    assert len(grid) == grid.shape[0] * grid.shape[1]


def test_halo_surrounds_the_core_and_is_clipped():
    grid = tile_grid(1000, 700, 256, 40)
    for t in grid:
        c0, r0, w, h = t.core
        rc0, rr0, rw, rh = t.read
        assert rc0 == max(0, c0 - 40) and rr0 == max(0, r0 - 40)
        assert rc0 + rw == min(1000, c0 + w + 40) and rr0 + rh == min(700, r0 + h + 40)
    corner = grid.tiles[0]
    assert corner.read == (0, 0, 296, 296)
    last = grid.tiles[-1]
    assert last.core == (768, 512, 232, 188)


def test_every_point_is_owned_by_exactly_one_tile():
    grid = tile_grid(1000, 700, 256, 40)
    rng = np.random.default_rng(0)
    col = rng.uniform(0, 1000, 5000)
    row = rng.uniform(0, 700, 5000)
    # Points exactly on core borders too.
    col = np.concatenate([col, [256.0, 512.0, 0.0, 999.999]])
    row = np.concatenate([row, [256.0, 0.0, 512.0, 699.999]])
    owners = np.sum([t.owns(col, row) for t in grid], axis=0)
    assert (owners == 1).all()


def test_bad_grids_are_rejected():
    with pytest.raises(ValueError, match="tile_px"):
        tile_grid(100, 100, 4, 0)
    with pytest.raises(ValueError, match="halo"):
        tile_grid(100, 100, 64, -1)
    with pytest.raises(ValueError, match="positive"):
        tile_grid(0, 100, 64, 0)


def test_tile_keys_are_unique_and_stable(tmp_path):
    a = tmp_path / "a b.tif"
    other = tmp_path / "sub" / "a b.tif"
    tag = image_tag(a)
    assert tag == image_tag(str(a)) and tag != image_tag(other)
    assert tag.startswith("a_b-")
    grid = tile_grid(1000, 700, 256, 40)
    keys = [tile_key(tag, grid, t) for t in grid]
    assert len(set(keys)) == len(keys)
    assert keys[1] == f"{tag}/256/0/1"


def test_runs_group_row_neighbours_of_one_image():
    from mapbuilder.build import TileTask, group_runs
    from mapbuilder.cluster import ClusterParams
    from mapbuilder.raster import PixelGrid

    grid = tile_grid(1000, 700, 256, 40)
    pg = PixelGrid("EPSG:25832", (0.1, 0, 0, 0, -0.1, 0), 1000, 700)
    tasks = [TileTask(p, pg, f"{p}{t.row}{t.col}", t.core, t.read, None, ClusterParams())
             for p in ("a.tif", "b.tif") for t in grid]
    runs = group_runs(tasks, 3)
    assert [len(r) for r in runs] == [3, 1] * 3 * 2
    assert [t for r in runs for t in r] == tasks
    for r in runs:
        assert len({(t.path, t.core[1]) for t in r}) == 1
        assert all(a.core[0] + a.core[2] == b.core[0] for a, b in zip(r, r[1:]))
    assert [len(r) for r in group_runs(tasks, 1)] == [1] * len(tasks)


@pytest.mark.parametrize("n_exec", [1, 2, 16])
def test_runs_keep_every_executor_busy_to_the_end(n_exec):
    """Every executor (a pool process or a Dask worker thread) gets many runs of tiles."""
    from mapbuilder.build import TileTask, _run_length, group_runs
    from mapbuilder.cluster import ClusterParams
    from mapbuilder.raster import PixelGrid

    grid = tile_grid(64 * 256, 16 * 256, 256, 40)  # 1024 tiles in rows of 64
    pg = PixelGrid("EPSG:25832", (0.1, 0, 0, 0, -0.1, 0), 64 * 256, 16 * 256)
    tasks = [TileTask("a.tif", pg, f"{t.row}/{t.col}", t.core, t.read, None, ClusterParams()) for t in grid]
    runs = group_runs(tasks, _run_length(len(tasks), n_exec))
    assert len(runs) >= 16 * n_exec
    assert max(len(r) for r in runs) > 1 or n_exec == 16  # neighbours still share a run when they can

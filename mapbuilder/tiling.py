"""A tile grid with halo and core ownership.

The image is cut into square *cores* that partition it exactly; each tile is
read with a *halo* around its core so that a marking near the border is seen
whole and the classifier has context. A marking belongs to the one tile whose
core holds its centroid, so a marking crossing a core border is kept by
exactly one tile.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.windows import Window


@dataclass(frozen=True)
class Tile:
    """One tile of a grid, in pixel coordinates of the image grid.

    Attributes
    ----------
    row, col : int
        Index of the tile in the grid.
    core : (col_off, row_off, width, height)
        The pixels this tile owns.
    read : (col_off, row_off, width, height)
        Core plus halo, clipped to the image.
    """

    row: int
    col: int
    core: tuple[int, int, int, int]
    read: tuple[int, int, int, int]

    @property
    def core_window(self) -> Window:
        return Window(*self.core)

    @property
    def read_window(self) -> Window:
        return Window(*self.read)

    def owns(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Whether points at image pixel coordinates (col, row) fall in this core.

        Coordinates are continuous (pixel (0, 0) spans [0, 1) x [0, 1)); cores
        are half-open so that neighbouring cores never both own a point.
        """
        c0, r0, w, h = self.core
        col = np.asarray(col, float)
        row = np.asarray(row, float)
        return (col >= c0) & (col < c0 + w) & (row >= r0) & (row < r0 + h)


@dataclass(frozen=True)
class TileGrid:
    """A grid of tiles over a ``width`` x ``height`` image."""

    width: int
    height: int
    tile_px: int
    halo_px: int
    tiles: tuple[Tile, ...]

    def __len__(self) -> int:
        return len(self.tiles)

    def __iter__(self):
        return iter(self.tiles)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of tiles."""
        return (math.ceil(self.height / self.tile_px), math.ceil(self.width / self.tile_px))


def tile_grid(width: int, height: int, tile_px: int = 1024, halo_px: int = 40) -> TileGrid:
    """Cut a ``width`` x ``height`` image into tiles with cores of ``tile_px`` pixels.

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    tile_px : int
        Core size, pixels (last row/column of cores may be smaller).
    halo_px : int
        Halo added on every side of the core, pixels, clipped at the image edge.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width} x {height}")
    if tile_px < 16:
        raise ValueError(f"tile_px must be at least 16 pixels, got {tile_px}")
    if halo_px < 0:
        raise ValueError(f"halo_px must be >= 0, got {halo_px}")
    tiles = []
    for r, r0 in enumerate(range(0, height, tile_px)):
        h = min(tile_px, height - r0)
        for c, c0 in enumerate(range(0, width, tile_px)):
            w = min(tile_px, width - c0)
            rc0, rr0 = max(0, c0 - halo_px), max(0, r0 - halo_px)
            rc1, rr1 = min(width, c0 + w + halo_px), min(height, r0 + h + halo_px)
            tiles.append(Tile(r, c, (c0, r0, w, h), (rc0, rr0, rc1 - rc0, rr1 - rr0)))
    return TileGrid(width, height, tile_px, halo_px, tuple(tiles))


def image_tag(path: str | Path) -> str:
    """A short, stable name for an image file: its stem plus a hash of its absolute path.

    Tile keys start with this tag, so that a rebuild of the same file replaces
    its own tiles and two files with the same name do not collide.
    """
    p = Path(path).resolve()
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", p.stem)[:32]
    digest = hashlib.sha1(str(p).encode()).hexdigest()[:8]
    return f"{stem}-{digest}"


def tile_key(tag: str, grid: TileGrid, tile: Tile) -> str:
    """The key stored with every marking of a tile: ``TAG/TILEPX/ROW/COL``."""
    return f"{tag}/{grid.tile_px}/{tile.row}/{tile.col}"

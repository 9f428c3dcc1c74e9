"""The demo map of ``lanemap serve --demo``: Karlsruhe from the Lanelet2 example.

On first start the map ``karlsruhe`` (EPSG:25832) is created from the
Lanelet2 HD map shipped in ``service/demo_data/`` (BSD-3, see the LICENSE
there): its lane markings are laid out as dashes, solid-line pieces and stop
lines and imported, and a window of synthetic aerial imagery is rendered for
the busiest part of the map so that the editor has a basemap. Later starts
find the map and do nothing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapbuilder.store import Store, UnknownMapError

log = logging.getLogger(__name__)

DEMO_MAP = "karlsruhe"
DEMO_CRS = "EPSG:25832"
DEMO_DATA = Path(__file__).resolve().parent / "demo_data"
#: Side of the rendered imagery window (metres) and its ground resolution.
IMAGERY_SIZE_M = (480.0, 320.0)
IMAGERY_RESOLUTION_M = 0.2


@dataclass
class DemoInfo:
    map_id: str
    markings: int
    imagery_id: int | None
    created: bool


def demo_osm() -> Path:
    return DEMO_DATA / "mapping_example.osm"


def busiest_window(x: np.ndarray, y: np.ndarray, size: tuple[float, float]) -> tuple[float, float, float, float]:
    """The window of ``size`` (metres) holding the most points, on a grid of half-window steps."""
    w, h = size
    best, best_n = None, -1
    for x0 in np.arange(x.min() - w / 2, x.max(), w / 4):
        for y0 in np.arange(y.min() - h / 2, y.max(), h / 4):
            n = int(np.count_nonzero((x >= x0) & (x < x0 + w) & (y >= y0) & (y < y0 + h)))
            if n > best_n:
                best, best_n = (float(x0), float(y0), float(x0 + w), float(y0 + h)), n
    return best


def ensure_demo(store: Store, data_dir: Path, *, imagery: bool = True, progress: bool = True) -> DemoInfo:
    """Create the demo map (markings and imagery) unless it exists."""
    from mapbuilder.lanelet2 import layout_markings, read_lanelet2

    try:
        info = store.get_map(DEMO_MAP, with_count=True)
        images = store.list_imagery(DEMO_MAP)
        return DemoInfo(DEMO_MAP, info.count or 0, images[0].id if images else None, False)
    except UnknownMapError:
        pass
    lmap = read_lanelet2(demo_osm(), crs=DEMO_CRS)
    items = layout_markings(lmap)
    store.create_map(DEMO_MAP, "Karlsruhe (Lanelet2 example map)", DEMO_CRS)
    ids = store.add_markings(DEMO_MAP, items, who="demo", comment="Karlsruhe Lanelet2 example, laid out")
    log.info("demo map %s: %d markings", DEMO_MAP, len(ids))
    imagery_id = None
    if imagery:
        imagery_id = render_imagery(store, lmap, items, Path(data_dir), progress=progress)
    return DemoInfo(DEMO_MAP, len(ids), imagery_id, True)


def render_imagery(store: Store, lmap, items, data_dir: Path, *, progress: bool = True) -> int:
    """Render synthetic imagery of the busiest window of the map, store it as a COG, register it."""
    from mapbuilder.raster import inspect_imagery
    from mapbuilder.synth import render

    from .routers.imagery import convert_to_cog

    x = np.array([m.x for m in items])
    y = np.array([m.y for m in items])
    bounds = busiest_window(x, y, IMAGERY_SIZE_M)
    folder = data_dir / "imagery" / DEMO_MAP
    folder.mkdir(parents=True, exist_ok=True)
    raw = folder / "demo-render.tif"
    cog = folder / "demo.cog.tif"
    render(lmap, raw, resolution_m=IMAGERY_RESOLUTION_M, seed=7, bounds=bounds, progress=progress)
    try:
        info = convert_to_cog(raw, cog, DEMO_CRS)
    finally:
        for f in folder.glob("demo-render*"):  # the raw render and its truth file
            f.unlink(missing_ok=True)
    grid = inspect_imagery(cog, DEMO_CRS).grid if info is None else info.grid
    return store.add_imagery(DEMO_MAP, str(cog.resolve()), grid.crs, grid.bounds, grid.resolution_m)

"""Karlsruhe map geometry for the localizer's tests and benchmarks."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from localizer import GeoFrame, MapIndex
from localizer.simulate import SceneMap

CRS = "EPSG:25832"
KARLSRUHE_OSM = (
    Path(__file__).resolve().parents[1].parent
    / "shared" / "data" / "karlsruhe-lanelet2" / "mapping_example.osm"
)


@lru_cache(maxsize=4)
def karlsruhe(path: str = str(KARLSRUHE_OSM), kinds: bool = True) -> tuple[MapIndex, SceneMap]:
    """The Karlsruhe Lanelet2 map as a MapIndex and as simulator geometry.

    The index is built like the service builds it from the store after a
    Lanelet2 import (centroids, weights, bearings, lengths and the imported
    kinds). ``kinds=False`` leaves the kinds out, as for a map detected from
    imagery: the index then infers the pieces of solid lines from their
    geometry.
    """
    from mapbuilder.lanelet2 import layout_markings, read_lanelet2

    lmap = read_lanelet2(path, crs=CRS)
    marks = layout_markings(lmap)
    x = np.array([m.x for m in marks])
    y = np.array([m.y for m in marks])
    # Marking bearings are from true north; the index wants grid bearings.
    frame = GeoFrame(CRS)
    conv = frame.convergence_deg(*frame.to_lonlat(float(x.mean()), float(y.mean())))
    index = MapIndex.from_arrays(
        x, y, np.array([m.weight for m in marks]), CRS,
        bearing_deg=np.array([m.bearing_deg for m in marks]) - conv,
        length_m=[m.length_m for m in marks],
        kind=[m.kind for m in marks] if kinds else None,
    )
    point_like = np.array([m.kind != "solid" for m in marks])
    solid_lines = [
        ln.xy for ln in lmap.lines_of("line_thin", "line_thick")
        if ln.subtype not in ("dashed",)
    ]
    scene_map = SceneMap(
        marking_xy=np.column_stack([x, y])[point_like],
        marking_kind=np.array([m.kind for m in marks], object)[point_like],
        solid_lines=solid_lines,
        curbs=[ln.xy for ln in lmap.lines_of("curbstone", "road_border")],
        centerlines=lmap.centerlines,
    )
    return index, scene_map


def karlsruhe_store(directory: Path) -> str:
    """A SQLite store in ``directory`` holding map ``ka``: the Karlsruhe map as
    ``lanemap from-lanelet2`` lays it out and ``lanemap import`` stores it. Its URL."""
    from mapbuilder.lanelet2 import layout_markings, read_lanelet2
    from mapbuilder.store import Store

    url = f"sqlite:///{directory / 'lanemap.sqlite'}"
    store = Store(url)
    store.create_map("ka", "Karlsruhe", CRS)
    store.add_markings("ka", layout_markings(read_lanelet2(KARLSRUHE_OSM, crs=CRS)))
    store.close()
    return url


class KarlsruheMarkings:
    """The Karlsruhe markings as ``lanemap from-lanelet2`` lays them out, to index any part of
    them, in any grid: a map cut at an edge, or stored in another CRS."""

    def __init__(self):
        from mapbuilder.lanelet2 import layout_markings, read_lanelet2

        marks = layout_markings(read_lanelet2(KARLSRUHE_OSM, crs=CRS))
        self.xy = np.array([(m.x, m.y) for m in marks])  # in CRS
        self.weight = np.array([m.weight for m in marks])
        self.bearing_true = np.array([m.bearing_deg for m in marks])  # clockwise from true north
        self.length = np.array([m.length_m for m in marks])
        self.kind = np.array([m.kind for m in marks], object)

    def index(self, keep=None, crs: str = CRS, extent: str = "hull", extent_area=None) -> MapIndex:
        """The index of the markings ``keep`` (a boolean mask; all when None), stored in ``crs``
        (each moved through WGS84, its bearing turned by the grid's convergence there), its
        extent drawn by ``extent`` (and ``extent_area``, in ``CRS``: only with ``crs`` the same)."""
        keep = np.ones(len(self.xy), bool) if keep is None else np.asarray(keep, bool)
        lon, lat = GeoFrame(CRS).to_lonlat(self.xy[keep, 0], self.xy[keep, 1])
        frame = GeoFrame(crs)
        x, y = frame.to_xy(lon, lat)
        return MapIndex.from_arrays(x, y, self.weight[keep], crs,
                                    bearing_deg=self.bearing_true[keep] - frame.convergence_deg(lon, lat),
                                    length_m=self.length[keep], kind=self.kind[keep], extent=extent,
                                    extent_area=extent_area)  # fmt: skip

    def cut(self, pose, ends_m: float = np.inf, begins_m: float = -np.inf) -> MapIndex:
        """The index of the markings between ``begins_m`` and ``ends_m`` along the heading of
        ``pose`` (metres ahead of it; negative: behind it): a map whose edge the vehicle nears."""
        d = np.array([np.cos(pose[2]), np.sin(pose[2])])
        along = (self.xy - np.asarray(pose[:2])) @ d
        return self.index((along <= ends_m) & (along >= begins_m))

    def imaged(self, without=None):
        """Imagery of the whole map (its markings' bounding box grown by 100 m), less the
        polygon ``without``: the ground a build from it imaged (shapely, in ``CRS``)."""
        import shapely

        (x0, y0), (x1, y1) = self.xy.min(axis=0) - 100.0, self.xy.max(axis=0) + 100.0
        ground = shapely.box(x0, y0, x1, y1)
        return ground if without is None else ground.difference(without)

    def gap(self, pose, from_m: float, length_m: float = 60.0, half_width_m: float = 40.0,
            extent: str = "hull") -> MapIndex:  # fmt: skip
        """The index of the markings less a stretch of ground ``from_m`` to ``from_m + length_m``
        ahead of ``pose`` and ``half_width_m`` either side of its heading: a map with a stretch of
        road left out, inside the hull of what it holds, whose world goes on there. ``extent``
        ``"imagery"``: built from imagery of the whole map but that stretch (:meth:`imaged`), the
        extent the markings' joined to the imagery's ground, as a server draws it."""
        import shapely

        d = np.array([np.cos(pose[2]), np.sin(pose[2])])
        n = np.array([-d[1], d[0]])
        rel = self.xy - np.asarray(pose[:2])
        along, across = rel @ d, rel @ n
        out = (along > from_m) & (along < from_m + length_m) & (np.abs(across) < half_width_m)
        if extent != "imagery":
            return self.index(~out, extent=extent)
        corners = [np.asarray(pose[:2]) + a * d + c * n for a, c in
                   ((from_m, -half_width_m), (from_m + length_m, -half_width_m),
                    (from_m + length_m, half_width_m), (from_m, half_width_m))]
        return self.index(~out, extent="markings", extent_area=self.imaged(shapely.Polygon(corners)))

"""Synthetic aerial imagery with known lane markings.

A :class:`Scene` is a stack of painted layers (ground cover, road surface,
sidewalks and curbs, lane markings, cars, trees, buildings, shadows) in a
metric CRS, plus the true markings. :func:`render` draws a scene into a
georeferenced GeoTIFF strip by strip, so memory stays bounded whatever the
image size, and writes the true markings beside it as GeoJSON (WGS84).

Scenes come from the Karlsruhe Lanelet2 map (:func:`lanelet_scene`), from a
list of markings (:func:`markings_scene`) or from a procedural road network
with parking lots (:func:`procedural_scene`). Textures are value noise keyed
to world coordinates, so a scene looks the same whatever window, CRS or
resolution it is drawn at; only the sensor noise changes with the seed.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import rasterio
import shapely
from pyproj import CRS, Transformer
from rasterio.features import rasterize
from rasterio.transform import Affine, from_origin
from scipy import ndimage
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import substring

from .crs import meridian_convergence_deg, to_wgs84
from .lanelet2 import MARKING_TYPES, LaneletMap, layout_markings
from .model import Marking

log = logging.getLogger(__name__)


class SynthError(ValueError):
    """Bad parameters for a synthetic render."""


# --------------------------------------------------------------------------- noise


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic uniform [0, 1) values for integer lattice points."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (seed * 83492791)
    h = h & 0xFFFFFFFF
    h = (h ^ (h >> 16)) * 0x45D9F3B & 0xFFFFFFFF
    h = (h ^ (h >> 16)) * 0x45D9F3B & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float32) / np.float32(0x1000000)


def value_noise(x: np.ndarray, y: np.ndarray, cell_m: float, seed: int) -> np.ndarray:
    """Smooth noise in [-1, 1] at world coordinates ``x``, ``y`` (metres), feature size ``cell_m``.

    Deterministic in the world coordinates, so adjacent strips join seamlessly.
    """
    gx = np.asarray(x, np.float64) / cell_m
    gy = np.asarray(y, np.float64) / cell_m
    if gx.size == 0:
        return np.zeros(gx.shape, np.float32)
    ix = np.floor(gx)
    iy = np.floor(gy)
    x0, y0 = ix.min(), iy.min()
    nx = int(ix.max() - x0) + 2
    ny = int(iy.max() - y0) + 2
    if nx * ny > gx.size:
        # lattice finer than the pixels: the nearest lattice value is as good as any
        return _hash01(np.round(gx), np.round(gy), seed) * 2.0 - 1.0
    lx = np.arange(nx, dtype=np.int64) + int(x0)
    ly = np.arange(ny, dtype=np.int64) + int(y0)
    table = _hash01(lx[None, :], ly[:, None], seed).ravel()
    fx = (gx - ix).astype(np.float32)
    fy = (gy - iy).astype(np.float32)
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    k = (iy - y0).astype(np.int64) * nx + (ix - x0).astype(np.int64)
    v00 = table[k]
    v10 = table[k + 1]
    v01 = table[k + nx]
    v11 = table[k + nx + 1]
    top = v00 + (v10 - v00) * fx
    bot = v01 + (v11 - v01) * fx
    return (top + (bot - top) * fy) * 2.0 - 1.0


def fractal_noise(x, y, cell_m: float, seed: int, octaves: int = 3) -> np.ndarray:
    """Sum of value-noise octaves, roughly in [-1, 1]."""
    out = np.zeros(np.broadcast_shapes(np.shape(x), np.shape(y)), np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        out += amp * value_noise(x, y, cell_m / 2**k, seed + 101 * k)
        total += amp
        amp *= 0.5
    return out / total


# --------------------------------------------------------------------------- scene


@dataclass
class Paint:
    """One polygon of a layer: colour (RGB 0–255) and opacity."""

    geom: Polygon
    rgb: tuple[float, float, float]
    alpha: float = 1.0
    texture: float = 1.0  # strength of the layer's texture on this polygon


#: Drawing order; later layers cover earlier ones.
LAYERS = (
    "ground",
    "lot",
    "sidewalk",
    "road",
    "patch",
    "verge",
    "curb",
    "crack",
    "marking",
    "building",
    "car_shadow",
    "car",
    "car_glass",
    "tree_shadow",
    "tree",
    "shadow",
)

#: Per-layer texture: (fine noise amplitude, cell size m, coarse amplitude, coarse cell m).
_TEXTURE = {
    "ground": (22.0, 0.25, 25.0, 4.0),
    "lot": (9.0, 0.08, 10.0, 6.0),
    "sidewalk": (7.0, 0.1, 8.0, 3.0),
    "road": (9.0, 0.08, 10.0, 6.0),
    "patch": (8.0, 0.08, 6.0, 2.0),
    "verge": (7.0, 0.1, 8.0, 3.0),
    "curb": (6.0, 0.1, 6.0, 2.0),
    "crack": (4.0, 0.1, 0.0, 1.0),
    "marking": (8.0, 0.05, 10.0, 0.6),
    "building": (6.0, 0.3, 8.0, 5.0),
    "car_shadow": (0.0, 1.0, 0.0, 1.0),
    "car": (6.0, 0.3, 8.0, 1.0),
    "car_glass": (4.0, 0.3, 4.0, 1.0),
    "tree_shadow": (0.0, 1.0, 0.0, 1.0),
    "tree": (30.0, 0.3, 20.0, 1.2),
    "shadow": (0.0, 1.0, 0.0, 1.0),
}
_SHADOW_LAYERS = {"car_shadow", "tree_shadow", "shadow"}
#: Layers that hide the markings under them.
_OCCLUDERS = {"building", "car", "car_glass", "tree"}


@dataclass
class Scene:
    """Layered vector scene in a metric CRS, with its true markings.

    Attributes
    ----------
    crs : str
        Metric CRS of every geometry.
    bounds : tuple of float
        (xmin, ymin, xmax, ymax) of the scene, metres.
    layers : dict
        Layer name (see :data:`LAYERS`) → list of :class:`Paint`.
    markings : list of Marking
        True markings; ``bearing_deg`` clockwise from grid north of ``crs``.
    marking_polygons : list of Polygon
        Painted area of each true marking, same order.
    seed : int
        Seed of the scene's textures.
    """

    crs: str
    bounds: tuple[float, float, float, float]
    layers: dict[str, list[Paint]] = field(default_factory=lambda: {k: [] for k in LAYERS})
    markings: list[Marking] = field(default_factory=list)
    marking_polygons: list[Polygon] = field(default_factory=list)
    seed: int = 0

    def add(self, layer: str, geom, rgb, alpha: float = 1.0, texture: float = 1.0) -> None:
        if geom is None or geom.is_empty:
            return
        for part in getattr(geom, "geoms", [geom]):
            if part.geom_type == "Polygon" and not part.is_empty:
                self.layers[layer].append(Paint(part, tuple(map(float, rgb)), alpha, texture))

    def add_marking(self, marking: Marking, poly: Polygon, rgb, alpha: float) -> None:
        self.markings.append(marking)
        self.marking_polygons.append(poly)
        self.add("marking", poly, rgb, alpha)


def marking_polygon(m: Marking) -> Polygon:
    """Rectangle of a marking from its end points and width (flat caps)."""
    if m.x0 is None:
        h = math.radians(m.bearing_deg)
        dx, dy = 0.5 * m.length_m * math.sin(h), 0.5 * m.length_m * math.cos(h)
        line = LineString([(m.x - dx, m.y - dy), (m.x + dx, m.y + dy)])
    else:
        line = LineString([(m.x0, m.y0), (m.x1, m.y1)])
    return line.buffer(m.width_m / 2.0, cap_style="flat", join_style="mitre")


def _marking_from_polygon(poly: Polygon, line: LineString, width: float, kind: str) -> Marking:
    c = poly.centroid
    (x0, y0), (x1, y1) = line.coords[0], line.coords[-1]
    bearing = math.degrees(math.atan2(x1 - x0, y1 - y0)) % 180.0
    length = float(line.length)
    return Marking(
        x=float(c.x), y=float(c.y), length_m=length, width_m=width, bearing_deg=bearing,
        weight=max(1.0, round(poly.area / 0.01)), kind=kind,
        x0=float(x0), y0=float(y0), x1=float(x1), y1=float(y1),
    )


def _pieces(line: LineString, piece_m: float) -> list[LineString]:
    n = max(1, math.ceil(line.length / piece_m - 1e-9))
    edges = np.linspace(0.0, line.length, n + 1)
    return [substring(line, a, b) for a, b in zip(edges[:-1], edges[1:])]


class _Palette:
    """Random but plausible colours for one scene."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        a = rng.uniform(55, 115)
        self.asphalt = np.array([a - rng.uniform(0, 6), a, a + rng.uniform(0, 10)])
        self.concrete = np.array([1.0, 1.0, 0.97]) * rng.uniform(140, 205)
        self.grass = np.array(
            [rng.uniform(55, 110), rng.uniform(85, 135), rng.uniform(40, 80)]
        )

    def paint(self) -> np.ndarray:
        v = self.rng.uniform(195, 250)
        return np.array([v, v, v * self.rng.uniform(0.94, 1.0)])

    def car(self) -> np.ndarray:
        r = self.rng
        kind = r.choice(["white", "silver", "black", "red", "blue", "grey", "dark"],
                        p=[0.3, 0.2, 0.15, 0.08, 0.1, 0.1, 0.07])
        base = {
            "white": [235, 236, 238], "silver": [185, 188, 192], "black": [28, 30, 34],
            "red": [160, 35, 35], "blue": [40, 60, 150], "grey": [110, 112, 115],
            "dark": [55, 60, 75],
        }[kind]
        return np.clip(np.array(base, float) + r.normal(0, 8, 3), 0, 255)

    def roof(self) -> np.ndarray:
        r = self.rng
        base = [[150, 80, 65], [120, 110, 105], [170, 165, 160], [95, 85, 80], [200, 198, 195]]
        return np.clip(np.array(base[r.integers(len(base))], float) + r.normal(0, 10, 3), 0, 255)

    def tree(self) -> np.ndarray:
        return np.array([self.rng.uniform(25, 60), self.rng.uniform(45, 85), self.rng.uniform(25, 50)])

    def ground(self) -> np.ndarray:
        if self.rng.random() < 0.25:  # soil, mulch
            return np.array([self.rng.uniform(110, 150), self.rng.uniform(90, 120), self.rng.uniform(70, 95)])
        return self.grass + self.rng.normal(0, 8, 3)


def _car(scene: Scene, pal: _Palette, cx, cy, heading_rad, sun, length=None, width=None):
    r = pal.rng
    length = length or r.uniform(3.9, 5.0)
    width = width or r.uniform(1.7, 1.95)
    body = shapely.affinity.rotate(
        box(-length / 2, -width / 2, length / 2, width / 2).buffer(0.25, join_style="round")
        .buffer(-0.25), heading_rad, use_radians=True, origin=(0, 0))
    body = shapely.affinity.translate(body, cx, cy)
    scene.add("car_shadow", shapely.affinity.translate(body, *sun * 1.2), (0, 0, 0), 0.55)
    colour = pal.car()
    scene.add("car", body, colour)
    # windscreen and rear window: dark bands across the body
    for off, ln in ((0.18, 0.22), (-0.3, 0.15)):
        g = box((off - ln / 2) * length, -width * 0.42, (off + ln / 2) * length, width * 0.42)
        g = shapely.affinity.translate(
            shapely.affinity.rotate(g, heading_rad, use_radians=True, origin=(0, 0)), cx, cy)
        scene.add("car_glass", g, (30, 35, 45))
    # roof highlight
    if colour.mean() > 150 and r.random() < 0.5:
        g = box(-0.2 * length, -width * 0.3, 0.05 * length, width * 0.3)
        g = shapely.affinity.translate(
            shapely.affinity.rotate(g, heading_rad, use_radians=True, origin=(0, 0)), cx, cy)
        scene.add("car_glass", g, np.minimum(colour + 15, 255), 0.8)


def _tree(scene: Scene, pal: _Palette, x, y, radius, sun):
    blob = Point(x, y).buffer(radius, 12)
    for _ in range(3):
        a = pal.rng.uniform(0, 2 * np.pi)
        blob = blob.union(Point(x + 0.6 * radius * math.cos(a), y + 0.6 * radius * math.sin(a))
                          .buffer(radius * pal.rng.uniform(0.4, 0.7), 8))
    scene.add("tree_shadow", shapely.affinity.translate(blob, *sun * 4.0), (0, 0, 0), 0.6)
    scene.add("tree", blob, pal.tree())


def _stripe_line(scene: Scene, pal: _Palette, line: LineString, width: float, kind: str,
                 dash_m: float | None, gap_m: float, piece_m: float, wear: float,
                 avoid=None) -> None:
    """Paint a line marking (dashed when ``dash_m``) and record its true pieces."""
    if line.length < 0.5:
        return
    if dash_m:
        segs = []
        s = pal.rng.uniform(0, dash_m + gap_m)
        while s + 0.5 < line.length:
            segs.append(substring(line, s, min(s + dash_m, line.length)))
            s += dash_m + gap_m
    else:
        segs = [line]
    colour = pal.paint()
    for seg in segs:
        if avoid is not None:
            parts = seg.difference(avoid)
            parts = [p for p in getattr(parts, "geoms", [parts]) if p.geom_type == "LineString"]
        else:
            parts = [seg]
        for part in parts:
            if part.length < 0.5:
                continue
            pieces = _pieces(part, piece_m)
            continuous = len(pieces) > 1 or kind == "solid"
            for piece in pieces:
                poly = piece.buffer(width / 2, cap_style="flat", join_style="mitre")
                if poly.is_empty or poly.geom_type != "Polygon":
                    continue
                alpha = float(np.clip(1.0 - wear * pal.rng.uniform(0.3, 1.0), 0.5, 1.0))
                m = _marking_from_polygon(poly, piece, width, kind)
                m.extra["continuous"] = continuous
                scene.add_marking(m, poly, colour, alpha)


def _road(scene, pal, centre: LineString, n_lanes: int, lane_w: float, sun, wear, avoid,
          piece_m: float, sidewalk: bool = True):
    half = n_lanes * lane_w / 2
    surface = centre.buffer(half, cap_style="flat")
    if sidewalk:
        curb_w = pal.rng.uniform(0.15, 0.3)
        walk = centre.buffer(half + curb_w + pal.rng.uniform(1.5, 3.0), cap_style="flat")
        scene.add("sidewalk", walk, pal.concrete * pal.rng.uniform(0.9, 1.05))
        curb = centre.buffer(half + curb_w, cap_style="flat").difference(surface)
        if avoid is not None:
            # not across another road: drawn over its asphalt a curb is a white stripe
            # that looks like paint and is in no truth
            curb = curb.difference(avoid)
        scene.add("curb", curb, np.minimum(pal.concrete * pal.rng.uniform(1.0, 1.2), 250))
    scene.add("road", surface, pal.asphalt * pal.rng.uniform(0.92, 1.08))
    edge_w = pal.rng.choice([0.12, 0.15, 0.25])
    for side in (-1, 1):
        if pal.rng.random() < 0.7:
            off = centre.offset_curve(side * (half - 0.25 - edge_w / 2))
            if off.geom_type == "LineString":
                _stripe_line(scene, pal, off, edge_w, "solid", None, 0, piece_m, wear, avoid)
    for k in range(1, n_lanes):
        off_m = -half + k * lane_w
        off = centre.offset_curve(off_m) if abs(off_m) > 1e-6 else centre
        if off.geom_type != "LineString":
            continue
        middle = abs(off_m) < 1e-6
        w = 0.12 if pal.rng.random() < 0.7 else 0.15
        if middle and pal.rng.random() < 0.3:
            for s in (-1, 1):
                o2 = centre.offset_curve(s * (w / 2 + 0.06))
                if o2.geom_type == "LineString":
                    _stripe_line(scene, pal, o2, w, "solid", None, 0, piece_m, wear, avoid)
        else:
            dash = None if (middle and pal.rng.random() < 0.3) else pal.rng.choice([3.0, 3.0, 6.0])
            gap = 2 * dash if dash else 0
            _stripe_line(scene, pal, off, w, "dash" if dash else "solid", dash, gap, piece_m, wear, avoid)
    # moving cars on the lanes
    for k in range(n_lanes):
        lane_c = -half + (k + 0.5) * lane_w
        lane = centre.offset_curve(lane_c)
        if lane.geom_type != "LineString":
            continue
        s = pal.rng.uniform(0, 30)
        while s < lane.length:
            if pal.rng.random() < 0.35:
                p = lane.interpolate(s)
                q = lane.interpolate(min(s + 1, lane.length))
                _car(scene, pal, p.x, p.y, math.atan2(q.y - p.y, q.x - p.x), sun)
            s += pal.rng.uniform(10, 40)
    # asphalt patches and cracks
    for _ in range(int(centre.length / 15)):
        p = centre.interpolate(pal.rng.uniform(0, centre.length))
        w, h = pal.rng.uniform(0.5, 4), pal.rng.uniform(0.5, 3)
        g = shapely.affinity.rotate(box(p.x - w, p.y - h, p.x + w, p.y + h), pal.rng.uniform(0, 180))
        scene.add("patch", g.intersection(surface), pal.asphalt * pal.rng.uniform(0.75, 1.25))
    for _ in range(int(centre.length / 10)):
        _crack(scene, pal, surface)
    return surface


def _crack(scene, pal, area):
    minx, miny, maxx, maxy = area.bounds
    x, y = pal.rng.uniform(minx, maxx), pal.rng.uniform(miny, maxy)
    pts = [(x, y)]
    a = pal.rng.uniform(0, 2 * np.pi)
    for _ in range(pal.rng.integers(3, 10)):
        a += pal.rng.normal(0, 0.5)
        step = pal.rng.uniform(0.3, 1.5)
        x, y = x + step * math.cos(a), y + step * math.sin(a)
        pts.append((x, y))
    g = LineString(pts).buffer(pal.rng.uniform(0.02, 0.06)).intersection(area)
    dark = pal.rng.random() < 0.8  # sealed cracks are dark, a few are light dust
    scene.add("crack", g, pal.asphalt * (0.45 if dark else 1.35), 0.8)


def _parking_lot(scene, pal, cx, cy, angle_deg, n_stalls, rows, sun, wear, piece_m,
                 occupancy: float = 0.6, car_w=(1.7, 1.95), stall_w_range=(2.4, 2.9),
                 curb: bool = True):
    """Rows of stalls with parked cars; returns the lot's area.

    ``occupancy`` is the share of stalls with a car, ``car_w`` the range of car
    widths, ``curb`` whether a curb surrounds the lot; the random draws do not
    depend on them, so a scene keeps its layout.
    """
    stall_w = pal.rng.uniform(*stall_w_range)
    stall_l = pal.rng.uniform(4.8, 5.6)
    line_w = pal.rng.choice([0.1, 0.12, 0.15])
    aisle = pal.rng.uniform(6.0, 7.5)
    width = n_stalls * stall_w
    depth = rows * stall_l + (rows - 1) * aisle if rows > 1 else stall_l
    lot = box(-width / 2 - 3, -depth / 2 - 3, width / 2 + 3, depth / 2 + 3)
    rot = lambda g: shapely.affinity.translate(  # noqa: E731
        shapely.affinity.rotate(g, angle_deg, origin=(0, 0)), cx, cy)
    lot_g = rot(lot)
    scene.add("lot", lot_g, pal.asphalt * pal.rng.uniform(0.85, 1.2))
    curb_rgb = np.minimum(pal.concrete * pal.rng.uniform(1.0, 1.2), 250)
    if curb:
        scene.add("curb", lot_g.buffer(0.25).difference(lot_g), curb_rgb)
    colour = pal.paint()
    for r in range(rows):
        y0 = -depth / 2 + r * (stall_l + aisle)
        for i in range(n_stalls + 1):
            x = -width / 2 + i * stall_w
            line = rot(LineString([(x, y0), (x, y0 + stall_l)]))
            pieces = _pieces(line, piece_m)
            for piece in pieces:
                poly = piece.buffer(line_w / 2, cap_style="flat", join_style="mitre")
                alpha = float(np.clip(1.0 - wear * pal.rng.uniform(0.3, 1.0), 0.5, 1.0))
                m = _marking_from_polygon(poly, piece, line_w, "stall")
                m.extra["continuous"] = len(pieces) > 1
                scene.add_marking(m, poly, colour, alpha)
            if i < n_stalls and pal.rng.random() < occupancy:
                # parked anywhere in the stall, sometimes right beside the line
                cw = min(pal.rng.uniform(*car_w), stall_w - 0.12)
                dx = pal.rng.uniform(-1, 1) * max(0.0, (stall_w - cw) / 2 - 0.05)
                c = rot(Point(x + stall_w / 2 + dx, y0 + stall_l / 2 + pal.rng.normal(0, 0.2)))
                _car(scene, pal, c.x, c.y, math.radians(angle_deg + 90 + pal.rng.normal(0, 2)), sun,
                     width=cw)
        if pal.rng.random() < 0.5:
            # a planted island with a curb where the stalls end (grass, mulch)
            end = y0 + stall_l if r == rows - 1 else y0
            isl = box(-width / 2 - 1, end, width / 2 + 1, end + pal.rng.uniform(1.5, 4.0)) \
                if r == rows - 1 else box(-width / 2 - 1, end - pal.rng.uniform(1.5, 4.0), width / 2 + 1, end)
            isl = rot(isl)
            scene.add("sidewalk", isl, pal.ground(), texture=2.5)
            scene.add("curb", isl.buffer(0.2).difference(isl),
                      np.minimum(pal.concrete * pal.rng.uniform(0.95, 1.2), 250))
    for _ in range(int(width * depth / 40)):
        _crack(scene, pal, lot_g)
    return lot_g.buffer(0.3)


def _decorate(scene, pal, free, sun, density: float = 1.0):
    """Buildings and trees where nothing else is."""
    minx, miny, maxx, maxy = scene.bounds
    area = (maxx - minx) * (maxy - miny)
    taken = free
    for _ in range(int(area / 900 * density)):
        x, y = pal.rng.uniform(minx, maxx), pal.rng.uniform(miny, maxy)
        w, h = pal.rng.uniform(6, 18), pal.rng.uniform(6, 14)
        g = shapely.affinity.rotate(box(x - w / 2, y - h / 2, x + w / 2, y + h / 2), pal.rng.uniform(0, 90))
        if taken is not None and g.buffer(2).intersects(taken):
            continue
        scene.add("shadow", shapely.affinity.translate(g, *sun * 6), (0, 0, 0), 0.6)
        scene.add("building", g, pal.roof())
        taken = g if taken is None else taken.union(g)
    for _ in range(int(area / 150 * density)):
        x, y = pal.rng.uniform(minx, maxx), pal.rng.uniform(miny, maxy)
        r = pal.rng.uniform(1.5, 4.5)
        p = Point(x, y)
        # trees may overhang roads a little, as in real imagery
        if taken is not None and p.buffer(r * 0.3).intersects(taken) and pal.rng.random() < 0.8:
            continue
        _tree(scene, pal, x, y, r, sun)


def _ground(scene, pal):
    minx, miny, maxx, maxy = scene.bounds
    scene.add("ground", box(minx - 50, miny - 50, maxx + 50, maxy + 50), pal.ground())
    for _ in range(int((maxx - minx) * (maxy - miny) / 400)):
        x, y = pal.rng.uniform(minx, maxx), pal.rng.uniform(miny, maxy)
        g = Point(x, y).buffer(pal.rng.uniform(2, 10), 8)
        scene.add("ground", g, pal.ground())
        if pal.rng.random() < 0.15:  # concrete yards, driveways: bright, grey, large
            scene.add("sidewalk", shapely.affinity.rotate(
                box(x, y, x + pal.rng.uniform(3, 12), y + pal.rng.uniform(3, 8)), pal.rng.uniform(0, 90)),
                pal.concrete * pal.rng.uniform(0.9, 1.15))


def _sun(rng) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    return np.array([math.cos(a), math.sin(a)]) * rng.uniform(0.3, 0.8)


def _new_scene(size_m, origin, crs: str, seed: int, max_wear: float):
    """An empty scene with its ground, and the scene's random state.

    Returns ``(scene, rng, palette, sun, wear)``; the random numbers are drawn
    in a fixed order, so a seed gives the same scene whatever comes after.
    """
    w, h = size_m
    if w <= 0 or h <= 0:
        raise SynthError(f"size_m must be positive, got {size_m}")
    rng = np.random.default_rng(seed)
    pal = _Palette(rng)
    x0, y0 = origin
    scene = Scene(crs=crs, bounds=(x0, y0, x0 + w, y0 + h), seed=seed)
    sun = _sun(rng)
    wear = rng.uniform(0.0, max_wear)
    _ground(scene, pal)
    return scene, rng, pal, sun, wear


def procedural_scene(
    size_m: tuple[float, float] = (60.0, 60.0),
    origin: tuple[float, float] = (500000.0, 5400000.0),
    crs: str = "EPSG:25832",
    seed: int = 0,
    piece_m: float = 3.0,
    road_spacing_m: float = 110.0,
) -> Scene:
    """A procedural scene: roads with lane markings, sidewalks, parking lots, cars, trees.

    Parameters
    ----------
    size_m : (float, float)
        Width and height of the scene, metres.
    origin : (float, float)
        Lower-left corner in ``crs``, metres.
    crs : str
        Metric CRS of the scene.
    seed : int
        Seed of the layout and textures.
    piece_m : float
        Longest true marking piece of a solid line, metres.
    road_spacing_m : float
        Spacing of the road grid for scenes larger than one block.
    """
    w, h = size_m
    x0, y0 = origin
    scene, rng, pal, sun, wear = _new_scene(size_m, origin, crs, seed, max_wear=0.45)
    centres: list[tuple[LineString, int, float]] = []
    if max(w, h) < 1.5 * road_spacing_m:
        n_roads = 1 if rng.random() < 0.6 else 2
        for k in range(n_roads):
            a = rng.uniform(0, np.pi) if k == 0 else a + np.pi / 2 + rng.normal(0, 0.2)  # noqa: F821
            cx, cy = x0 + w * rng.uniform(0.3, 0.7), y0 + h * rng.uniform(0.3, 0.7)
            L = 2 * math.hypot(w, h)
            t = np.linspace(-L / 2, L / 2, 200)
            bend = rng.uniform(-1, 1) * (rng.random() < 0.5) / 150.0  # curvature 1/m
            px = cx + t * math.cos(a) - (bend * t**2 / 2) * math.sin(a)
            py = cy + t * math.sin(a) + (bend * t**2 / 2) * math.cos(a)
            centres.append((LineString(np.column_stack([px, py])), int(rng.integers(1, 5)), rng.uniform(2.9, 3.6)))
    else:
        angle = rng.uniform(-0.3, 0.3)
        for axis in (0, 1):
            span = w if axis == 0 else h
            other = h if axis == 0 else w
            for pos in np.arange(rng.uniform(20, road_spacing_m), span, road_spacing_m):
                t = np.linspace(-60, other + 60, max(int(other / 5), 20))
                wig = rng.uniform(0, 8) * np.sin(t / rng.uniform(80, 300) + rng.uniform(0, 6))
                if axis == 0:  # north-south road at x = pos
                    px, py = x0 + pos + wig + t * math.sin(angle), y0 + t
                else:
                    px, py = x0 + t, y0 + pos + wig + t * math.sin(angle)
                centres.append((LineString(np.column_stack([px, py])), int(rng.integers(2, 5)), rng.uniform(3.0, 3.5)))
    surfaces = [c.buffer(n * lw / 2 + 0.5) for c, n, lw in centres]
    occupied = None
    for i, (c, n, lw) in enumerate(centres):
        others = [s for j, s in enumerate(surfaces) if j != i]
        avoid = shapely.union_all(others).buffer(1.0) if others else None
        _road(scene, pal, c, n, lw, sun, wear, avoid, piece_m)
        g = c.buffer(n * lw / 2 + 3.5)
        occupied = g if occupied is None else occupied.union(g)
    # stop lines before intersections
    for i, (c, n, lw) in enumerate(centres):
        for j, s in enumerate(surfaces):
            if j == i:
                continue
            inter = c.intersection(s)
            for seg in getattr(inter, "geoms", [inter]):
                if seg.is_empty or seg.geom_type != "LineString":
                    continue
                for end in (0.0, 1.0):
                    d = c.project(seg.interpolate(end, normalized=True))
                    d = d - 2.5 if end == 0.0 else d + 2.5
                    if not (1 < d < c.length - 1):
                        continue
                    p, q = c.interpolate(d), c.interpolate(min(d + 0.5, c.length))
                    ang = math.atan2(q.y - p.y, q.x - p.x)
                    nx, ny = -math.sin(ang), math.cos(ang)
                    side = -1 if end == 0.0 else 1
                    hw = n * lw / 2
                    line = LineString([(p.x, p.y), (p.x + side * nx * (hw - 0.3), p.y + side * ny * (hw - 0.3))])
                    _stripe_line(scene, pal, line, 0.5, "stop_line", None, 0, 100.0, wear * 0.5)
    # parking lots in the free space
    n_lots = max(1, int(w * h / 3000))
    tries = 0
    while n_lots > 0 and tries < 60:
        tries += 1
        n_st, rows = int(rng.integers(3, 12)), int(rng.integers(1, 3))
        cx, cy = x0 + rng.uniform(0.1, 0.9) * w, y0 + rng.uniform(0.1, 0.9) * h
        ang = rng.uniform(0, 180) if rng.random() < 0.5 else 0.0
        probe = shapely.affinity.rotate(
            box(cx - n_st * 1.4 - 3, cy - rows * 5.5 - 3, cx + n_st * 1.4 + 3, cy + rows * 5.5 + 3),
            ang, origin=(cx, cy))
        if occupied is not None and probe.intersects(occupied):
            continue
        lot = _parking_lot(scene, pal, cx, cy, ang, n_st, rows, sun, wear, piece_m)
        occupied = lot if occupied is None else occupied.union(lot)
        n_lots -= 1
    _decorate(scene, pal, occupied, sun)
    return scene


def parking_scene(
    size_m: tuple[float, float] = (45.0, 45.0),
    origin: tuple[float, float] = (500000.0, 5400000.0),
    crs: str = "EPSG:25832",
    seed: int = 0,
    piece_m: float = 3.0,
) -> Scene:
    """A scene that is mostly a parking lot: full rows of stalls between cars.

    Short stall lines (thin, often worn) with cars parked close beside them on
    both sides, rows ending at planted islands with curbs, an access road
    around the lot, trees overhanging it. Procedural scenes hold smaller,
    emptier lots; real imagery of residential and commercial lots looks like
    this one.

    Parameters
    ----------
    size_m, origin, crs, seed, piece_m
        As :func:`procedural_scene`.
    """
    w, h = size_m
    x0, y0 = origin
    scene, rng, pal, sun, wear = _new_scene(size_m, origin, crs, seed, max_wear=0.5)
    cx, cy = x0 + w / 2 + rng.uniform(-0.1, 0.1) * w, y0 + h / 2 + rng.uniform(-0.1, 0.1) * h
    ang = rng.uniform(0, 180) if rng.random() < 0.6 else float(rng.choice([0.0, 90.0]))
    # the asphalt all round the lot, as the loop road of a residential court
    apron = shapely.affinity.rotate(box(cx - w, cy - h, cx + w, cy + h), ang, origin=(cx, cy))
    scene.add("road", apron, pal.asphalt * rng.uniform(0.9, 1.1))
    n_lots = int(rng.integers(1, 3))
    occupied = None
    for k in range(n_lots):
        n_st = int(rng.integers(3, 10))
        rows = int(rng.integers(1, 3))
        dx, dy = rng.uniform(-0.15, 0.15) * w, (k - (n_lots - 1) / 2) * 21.0
        px = cx + dx * math.cos(math.radians(ang)) - dy * math.sin(math.radians(ang))
        py = cy + dx * math.sin(math.radians(ang)) + dy * math.cos(math.radians(ang))
        lot = _parking_lot(scene, pal, px, py, ang, n_st, rows, sun, wear, piece_m,
                           occupancy=rng.uniform(0.7, 1.0), car_w=(1.75, 2.2),
                           stall_w_range=(2.4, 3.1), curb=False)
        occupied = lot if occupied is None else occupied.union(lot)
    for _ in range(int(rng.integers(0, 4))):
        # cars driving or parked on the access road
        p = Point(rng.uniform(x0, x0 + w), rng.uniform(y0, y0 + h))
        if occupied is None or not p.buffer(3).intersects(occupied):
            _car(scene, pal, p.x, p.y, math.radians(ang + rng.choice([0.0, 90.0])), sun)
    for _ in range(int(w * h / 60)):
        _crack(scene, pal, apron)
    _decorate(scene, pal, occupied.buffer(-1.0) if occupied is not None else None, sun,
              density=0.5)
    return scene


def markings_scene(markings: Sequence[Marking], crs: str, seed: int = 0,
                   bounds: tuple[float, float, float, float] | None = None) -> Scene:
    """A scene painting the given markings on asphalt around them (no other context)."""
    rng = np.random.default_rng(seed)
    pal = _Palette(rng)
    polys = [marking_polygon(m) for m in markings]
    if bounds is None:
        if not polys:
            raise SynthError("no markings and no bounds")
        bounds = tuple(shapely.union_all(polys).buffer(10).bounds)
    scene = Scene(crs=crs, bounds=bounds, seed=seed)
    _ground(scene, pal)
    scene.add("road", shapely.union_all(polys).buffer(4.0), pal.asphalt)
    for m, p in zip(markings, polys):
        scene.add_marking(m, p, pal.paint(), float(np.clip(1 - rng.uniform(0, 0.4), 0.4, 1)))
    return scene


def lanelet_scene(lmap: LaneletMap, seed: int = 0,
                  bounds: tuple[float, float, float, float] | None = None,
                  phase_m: float | None = None) -> Scene:
    """A scene from a Lanelet2 map: lanes, curbs, sidewalks, markings, cars, trees.

    Parameters
    ----------
    lmap : LaneletMap
        Map from :func:`mapbuilder.lanelet2.read_lanelet2` (its CRS is the scene's).
    seed : int
        Seed of textures, cars and trees.
    bounds : tuple, optional
        (xmin, ymin, xmax, ymax) to keep, metres; default the whole map.
    phase_m : float, optional
        Phase of the dash pattern; random by default.
    """
    rng = np.random.default_rng(seed)
    pal = _Palette(rng)
    sun = _sun(rng)
    wear = rng.uniform(0.0, 0.45)
    if bounds is None:
        xy = np.vstack([ln.xy for ln in lmap.lines])
        bounds = (*xy.min(0), *xy.max(0))
    bb = box(*bounds).buffer(20)
    scene = Scene(crs=lmap.crs, bounds=tuple(map(float, bounds)), seed=seed)
    _ground(scene, pal)
    lanes = [LineString(c) for c in lmap.centerlines if len(c) >= 2]
    lanes = [c for c in lanes if c.intersects(bb)]
    curbs = [LineString(ln.xy) for ln in lmap.lines_of("curbstone", "road_border") if LineString(ln.xy).intersects(bb)]
    # Lane surface: around the centrelines, and around every painted line so that no
    # marking ends up on a sidewalk where lanes are wider than usual.
    paint_lines = [LineString(ln.xy) for ln in lmap.lines_of(*MARKING_TYPES)
                   if LineString(ln.xy).intersects(bb)]
    road_parts = [c.buffer(2.0, cap_style="flat") for c in lanes] + [p.buffer(1.0) for p in paint_lines]
    road = shapely.union_all(road_parts) if road_parts else None
    if curbs:
        # the sidewalk lies on the side of a curb away from the lanes, and covers the
        # road surface there: the curb then separates asphalt from pavement, as it does
        lanes_u = shapely.union_all(lanes) if lanes else None
        walks = []
        for c in curbs:
            wdt = rng.uniform(1.5, 3.0)
            if lanes_u is None:
                walks.append(c.buffer(wdt))
                continue
            probe = [c.offset_curve(s * 1.0) for s in (1, -1)]
            dist = [lanes_u.distance(p.interpolate(0.5, normalized=True)) if not p.is_empty else 0
                    for p in probe]
            side = 1 if dist[0] > dist[1] else -1
            walks.append(c.buffer(side * wdt, single_sided=True))
        walk = shapely.union_all(walks)
        # never over a lane or a painted line (curbs between carriageways, odd geometry)
        keep_clear = [c.buffer(1.5, cap_style="flat") for c in lanes] + [p.buffer(0.8) for p in paint_lines]
        if keep_clear:
            walk = walk.difference(shapely.union_all(keep_clear))
            # and no slivers: a strip of pavement a few decimetres wide left between
            # the cleared zones of a lane and a line looks exactly like a painted line
            walk = walk.buffer(-0.3).buffer(0.3)
        scene.add("verge", walk, pal.concrete)
    else:
        walk = None
    if road is not None:
        scene.add("road", road, pal.asphalt)
        for _ in range(int(road.area / 40)):
            _crack(scene, pal, road.intersection(bb))
    if curbs:
        # only where a sidewalk lies beside it: where the sidewalk had to give way
        # to lanes, a curb alone on asphalt would look like a painted line
        curb = shapely.union_all([c.buffer(0.12) for c in curbs]).intersection(walk.buffer(0.15))
        scene.add("curb", curb, np.minimum(pal.concrete * 1.1, 250))
    ph = rng.uniform(0, 9) if phase_m is None else phase_m
    colour = pal.paint()
    for m in layout_markings(lmap, phase_m=ph):
        if not bb.contains(Point(m.x, m.y)):
            continue
        poly = marking_polygon(m)
        alpha = float(np.clip(1.0 - wear * rng.uniform(0.3, 1.0), 0.5, 1.0))
        m.extra["continuous"] = m.kind == "solid"
        scene.add_marking(m, poly, colour, alpha)
    for c in lanes:
        s = rng.uniform(0, 20)
        while s < c.length:
            if rng.random() < 0.3:
                p, q = c.interpolate(s), c.interpolate(min(s + 1, c.length))
                _car(scene, pal, p.x, p.y, math.atan2(q.y - p.y, q.x - p.x), sun)
            s += rng.uniform(15, 50)
    occupied = road.buffer(4) if road is not None else None
    _decorate(scene, pal, occupied, sun, density=0.6)
    return scene


# --------------------------------------------------------------------------- rendering


@dataclass
class RenderResult:
    """What :func:`render` wrote."""

    path: Path
    truth_path: Path
    markings: list[Marking]  # in the image CRS; bearing_deg clockwise from TRUE north
    crs: str
    transform: Affine
    shape: tuple[int, int]
    resolution_m: float


@dataclass
class _Prepared:
    layers: list[tuple[str, list, np.ndarray, np.ndarray, np.ndarray, shapely.STRtree]]
    marks: list
    mark_tree: shapely.STRtree | None


def _to_crs(geoms: list, src: str, dst: str) -> list:
    if CRS.from_user_input(src) == CRS.from_user_input(dst):
        return geoms
    t = Transformer.from_crs(src, dst, always_xy=True)
    return list(shapely.transform(np.asarray(geoms, dtype=object),
                                  lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1]))))


def _prepare(scene: Scene, crs: str) -> _Prepared:
    layers = []
    for name in LAYERS:
        paints = scene.layers[name]
        if not paints:
            continue
        geoms = _to_crs([p.geom for p in paints], scene.crs, crs)
        rgb = np.array([p.rgb for p in paints], np.float32)
        alpha = np.array([p.alpha for p in paints], np.float32)
        tex = np.array([p.texture for p in paints], np.float32)
        layers.append((name, geoms, rgb, alpha, tex, shapely.STRtree(geoms)))
    marks = _to_crs(scene.marking_polygons, scene.crs, crs)
    return _Prepared(layers, marks, shapely.STRtree(marks) if marks else None)


def _window_xy(transform: Affine, row0: int, col0: int, h: int, w: int, scene_crs: str, crs: str):
    """World coordinates (in the scene CRS) of pixel centres of a window."""
    cols = np.arange(col0, col0 + w) + 0.5
    rows = np.arange(row0, row0 + h) + 0.5
    c, r = np.meshgrid(cols, rows)
    x = transform.c + c * transform.a + r * transform.b
    y = transform.f + c * transform.d + r * transform.e
    if CRS.from_user_input(scene_crs) != CRS.from_user_input(crs):
        t = Transformer.from_crs(crs, scene_crs, always_xy=True)
        x, y = t.transform(x, y)
    return x, y


def _draw(scene: Scene, prep: _Prepared, transform: Affine, row0: int, col0: int, h: int,
          w: int, crs: str, look: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Composite one window.

    Returns float RGB (h, w, 3) before sensor effects, the index + 1 of the true
    marking painted at each pixel (0: none) and the mask of pixels hidden by
    cars, trees and buildings.
    """
    win_t = transform * Affine.translation(col0, row0)
    xs, ys = _window_xy(transform, row0, col0, h, w, scene.crs, crs)
    x0w, y0w = win_t @ (0, 0)
    x1w, y1w = win_t @ (w, h)
    qbox = box(min(x0w, x1w), min(y0w, y1w), max(x0w, x1w), max(y0w, y1w))
    img = np.zeros((h, w, 3), np.float32)
    occ = np.zeros((h, w), bool)
    for name, geoms, rgb, alpha, tex, tree in prep.layers:
        idx = tree.query(qbox)
        if len(idx) == 0:
            continue
        ids = rasterize(((geoms[i], k + 1) for k, i in enumerate(idx)), out_shape=(h, w),
                        transform=win_t, fill=0, dtype="uint16" if len(idx) < 65000 else "uint32")
        m = ids > 0
        if not m.any():
            continue
        if name in _OCCLUDERS:
            occ |= m
        sel = ids[m] - 1
        a = alpha[idx][sel][:, None]
        xm, ym = xs[m], ys[m]
        seed = scene.seed * 31 + LAYERS.index(name)
        if name in _SHADOW_LAYERS:
            dark = look["shadow"] * (0.85 + 0.15 * value_noise(xm, ym, 0.7, seed))
            tint = np.array([0.9, 0.95, 1.15], np.float32)  # skylight makes shadows blue
            k = a * dark[:, None]
            img[m] = img[m] * (1 - k) * (1 + (tint - 1) * k)
            continue
        fine_a, fine_c, coarse_a, coarse_c = _TEXTURE[name]
        t = tex[idx][sel]
        shade = (fine_a * value_noise(xm, ym, fine_c, seed) * t
                 + coarse_a * fractal_noise(xm, ym, coarse_c, seed + 7, 2) * t)
        colour = rgb[idx][sel] + shade[:, None]
        if name == "marking":
            # worn paint: holes where the noise is low, more of them when alpha is low
            wearn = fractal_noise(xm, ym, 0.25, seed + 13, 3)
            a = np.clip(a + 0.5 * wearn[:, None] * (1.0 - a) * 2.0, 0.1, 1.0)
        img[m] = img[m] * (1 - a) + colour * a
    ids = np.zeros((h, w), np.int32)
    if prep.mark_tree is not None:
        idx = prep.mark_tree.query(qbox)
        if len(idx):
            ids = rasterize(((prep.marks[i], int(i) + 1) for i in idx), out_shape=(h, w),
                            transform=win_t, fill=0, dtype="int32")
    return img, ids, occ


def _sensor(img: np.ndarray, look: dict, rng: np.random.Generator) -> np.ndarray:
    """Optics and sensor: blur, colour balance, gamma, noise; returns uint8.

    A look with the keys of :func:`camera_artefacts` also gets the processing
    of real orthophotos after the noise: colour channels out of register,
    colour at a lower resolution than brightness, and sharpening.
    """
    out = ndimage.gaussian_filter(img, sigma=(look["blur_px"], look["blur_px"], 0), mode="nearest")
    out = out * look["gain"] + look["offset"]
    out = 255.0 * np.clip(out / 255.0, 0, 1) ** look["gamma"]
    out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(look["noise"])
    if "channel_shift_px" in look:
        out = _processing(out, look)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _processing(img: np.ndarray, look: dict) -> np.ndarray:
    """Misregistered channels, low-resolution colour and unsharp masking (float (H, W, 3))."""
    out = np.empty_like(img)
    for k, (dr, dc) in enumerate(look["channel_shift_px"]):
        out[..., k] = ndimage.shift(img[..., k], (float(dr), float(dc)), order=1, mode="nearest")
    sigma = float(look["chroma_blur_px"])
    if sigma > 0:
        y = out.mean(axis=2, keepdims=True)
        chroma = ndimage.gaussian_filter(out - y, sigma=(sigma, sigma, 0), mode="nearest")
        out = y + chroma
    amount = float(look["sharpen"])
    if amount > 0:
        s = float(look["sharpen_px"])
        out += amount * (out - ndimage.gaussian_filter(out, sigma=(s, s, 0), mode="nearest"))
    return out


def camera_artefacts(rng: np.random.Generator, strength: float = 1.0) -> dict:
    """Random processing artefacts of real aerial orthophotos, to add to a look.

    Real survey imagery (e.g. the USGS 15 cm orthophotos) is sharpened, which
    puts dark rims beside bright lines, and its colour channels are slightly
    out of register or of lower resolution than its brightness (pan-sharpened,
    demosaiced, JPEG with subsampled colour), which puts coloured fringes on
    both edges of a white line on asphalt. :func:`random_look` draws none of
    this; renders made with ``look | camera_artefacts(rng)`` have it.

    Parameters
    ----------
    rng : numpy.random.Generator
    strength : float
        Scales the channel offsets and the sharpening (1: up to about a pixel
        of misregistration and an unsharp mask of amount 1.5).

    Returns
    -------
    dict
        ``channel_shift_px`` (3, 2) offsets (rows, columns) of R, G, B in
        pixels, ``chroma_blur_px``, ``sharpen`` (amount) and ``sharpen_px``
        (radius of the unsharp mask).
    """
    shift = rng.uniform(-1.0, 1.0, (3, 2)) * strength * rng.uniform(0.2, 1.0)
    shift -= shift.mean(axis=0)  # brightness stays where the scene puts it
    return {
        "channel_shift_px": shift.astype(np.float32),
        "chroma_blur_px": float(rng.uniform(0.0, 1.5) if rng.random() < 0.5 else 0.0),
        "sharpen": float(rng.uniform(0.3, 1.5) * strength),
        "sharpen_px": float(rng.uniform(0.8, 2.0)),
    }


def random_look(rng: np.random.Generator, resolution_m: float) -> dict:
    """Random optics and exposure of one image."""
    return {
        "blur_px": float(rng.uniform(0.4, 1.1) * min(1.5, 0.1 / resolution_m) ** 0.5),
        # colour cast and exposure: aerial surveys are often bluish or warm
        "gain": rng.uniform(0.88, 1.12, 3).astype(np.float32) * np.float32(rng.uniform(0.8, 1.2)),
        "offset": (rng.uniform(-10, 15) + rng.uniform(-6, 6, 3)).astype(np.float32),
        "gamma": float(rng.uniform(0.8, 1.2)),
        "noise": float(rng.uniform(1.5, 5.0)),
        "shadow": float(rng.uniform(0.4, 0.65)),
    }


def _jpeg_roundtrip(rgb: np.ndarray, quality: int) -> np.ndarray:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    return np.asarray(Image.open(buf).convert("RGB"))


def _grid(scene: Scene, resolution_m: float, crs: str, bounds=None):
    """Output transform and shape for a scene drawn in ``crs`` at ``resolution_m``."""
    b = bounds or scene.bounds
    out = CRS.from_user_input(crs)
    if CRS.from_user_input(scene.crs) != out:
        t = Transformer.from_crs(scene.crs, crs, always_xy=True)
        b = t.transform_bounds(*b, densify_pts=21)
    if out.is_geographic:
        lat = math.radians(0.5 * (b[1] + b[3]))
        res_x = resolution_m / (111320.0 * math.cos(lat))
        res_y = resolution_m / 110574.0
    else:
        res_x = res_y = resolution_m
    width = int(math.ceil((b[2] - b[0]) / res_x))
    height = int(math.ceil((b[3] - b[1]) / res_y))
    if width < 1 or height < 1:
        raise SynthError("render area is empty")
    return from_origin(b[0], b[3], res_x, res_y), (height, width)


def render_array(scene: Scene, resolution_m: float = 0.1, seed: int = 0,
                 jpeg_quality: int | None = None, look: dict | None = None):
    """Draw a (small) scene in memory in its own CRS.

    Returns
    -------
    rgb : (H, W, 3) uint8
    label : (H, W) bool
        True on visible painted marking pixels (not under cars, trees, roofs).
    transform : Affine
    """
    if not 0.02 <= resolution_m <= 1.0:
        raise SynthError(f"resolution_m must be within [0.02, 1] m, got {resolution_m}")
    rng = np.random.default_rng(seed)
    look = look or random_look(rng, resolution_m)
    transform, (h, w) = _grid(scene, resolution_m, scene.crs)
    prep = _prepare(scene, scene.crs)
    img, ids, occ = _draw(scene, prep, transform, 0, 0, h, w, scene.crs, look, rng)
    label = (ids > 0) & ~occ
    rgb = _sensor(img, look, rng)
    if jpeg_quality:
        rgb = _jpeg_roundtrip(rgb, jpeg_quality)
    return rgb, label, transform


def render(
    scene: Scene | LaneletMap | Sequence[Marking],
    out_tif: str | Path,
    resolution_m: float = 0.1,
    crs: str | None = None,
    seed: int = 0,
    *,
    bounds: tuple[float, float, float, float] | None = None,
    jpeg_quality: int | None = None,
    labels_tif: str | Path | None = None,
    alpha: bool = False,
    nodata: int | None = None,
    strip_rows: int = 256,
    progress: bool = False,
    markings_crs: str | None = None,
) -> RenderResult:
    """Draw a scene into a tiled GeoTIFF, strip by strip, and write its truth as GeoJSON.

    Parameters
    ----------
    scene : Scene, LaneletMap or sequence of Marking
        What to draw. A Lanelet2 map becomes :func:`lanelet_scene`; bare markings
        (in ``markings_crs``) become :func:`markings_scene`.
    out_tif : path
        GeoTIFF to write (RGB uint8, tiled 256 px).
    resolution_m : float
        Ground sampling distance, metres per pixel (0.02–1).
    crs : str, optional
        CRS of the image; default the scene's. Geographic CRSs get square-metre
        pixels at the scene centre.
    seed : int
        Seed of the sensor look (exposure, blur, noise).
    bounds : tuple, optional
        Part of the scene to draw, in the scene CRS.
    jpeg_quality : int, optional
        Write JPEG-compressed (lossy) tiles at this quality; default lossless DEFLATE.
    labels_tif : path, optional
        Also write a uint8 label GeoTIFF (1 on painted marking pixels).
    alpha : bool
        Write a fourth, alpha band that masks out a border region (as orthophoto
        edges are), leaving those pixels black.
    nodata : int, optional
        Write a nodata value; with it the same border region is filled with nodata.
    strip_rows : int
        Rows drawn at once; bounds memory (about 60 bytes per pixel of a strip).
    progress : bool
        Show a progress bar.
    markings_crs : str, optional
        CRS of bare markings; default ``crs``.

    Returns
    -------
    RenderResult
        The truth: markings inside the image whose painted area is visible, in the
        image CRS (geographic CRS: lon/lat), bearings clockwise from true north.
    """
    if isinstance(scene, LaneletMap):
        scene = lanelet_scene(scene, seed=seed, bounds=bounds)
    elif not isinstance(scene, Scene):
        mcrs = markings_crs or crs
        if mcrs is None:
            raise SynthError("markings need markings_crs (or crs)")
        scene = markings_scene(list(scene), mcrs, seed=seed, bounds=bounds)
    if not 0.02 <= resolution_m <= 1.0:
        raise SynthError(f"resolution_m must be within [0.02, 1] m, got {resolution_m}")
    crs = crs or scene.crs
    try:
        out_crs = CRS.from_user_input(crs)
    except Exception as exc:
        raise SynthError(f"unknown CRS {crs!r}") from exc
    out_tif = Path(out_tif)
    rng = np.random.default_rng(seed)
    look = random_look(rng, resolution_m)
    transform, (height, width) = _grid(scene, resolution_m, crs, bounds)
    prep = _prepare(scene, crs)
    mask_poly = None
    if alpha or nodata is not None:
        # a slanted image edge: the last ~15 % of the image along one corner is empty
        (x0, y0), (x1, y1) = transform @ (0, 0), transform @ (width, height)
        xa, ya = x0 + 0.7 * (x1 - x0), y1
        mask_poly = Polygon([(xa, ya), (x1, ya), (x1, y0 + 0.5 * (y1 - y0))])
    profile = dict(
        driver="GTiff", width=width, height=height, count=4 if alpha else 3, dtype="uint8",
        crs=out_crs, transform=transform, tiled=True, blockxsize=256, blockysize=256,
        BIGTIFF="IF_SAFER",
    )
    if jpeg_quality:
        profile.update(compress="JPEG", jpeg_quality=int(jpeg_quality))
        if not alpha:
            profile.update(photometric="YCBCR")
    else:
        profile.update(compress="DEFLATE", predictor=2)
    if nodata is not None:
        profile["nodata"] = nodata
    if alpha:
        profile["photometric"] = "RGB"
        profile["alpha"] = "YES"
    lab_ds = None
    out_tif.parent.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    halo = 6
    n_vis = np.zeros(len(scene.markings) + 1, np.int64)
    with rasterio.open(out_tif, "w", **profile) as ds:
        if labels_tif is not None:
            lab_ds = rasterio.open(
                labels_tif, "w", driver="GTiff", width=width, height=height, count=1, dtype="uint8",
                crs=out_crs, transform=transform, tiled=True, blockxsize=256, blockysize=256,
                compress="DEFLATE")
        try:
            strip_rows = max(16, (strip_rows // 16) * 16)
            bar = tqdm(total=height, unit="row", disable=not progress, desc="render")
            for r0 in range(0, height, strip_rows):
                h = min(strip_rows, height - r0)
                ra, rb = max(0, r0 - halo), min(height, r0 + h + halo)
                img, ids, occ = _draw(scene, prep, transform, ra, 0, rb - ra, width, crs, look, rng)
                rgb = _sensor(img, look, rng)[r0 - ra: r0 - ra + h]
                ids = ids[r0 - ra: r0 - ra + h]
                occ = occ[r0 - ra: r0 - ra + h]
                label = (ids > 0) & ~occ
                win = rasterio.windows.Window(0, r0, width, h)
                valid = None
                if mask_poly is not None:
                    valid = rasterize([(mask_poly, 1)], out_shape=(h, width),
                                      transform=transform * Affine.translation(0, r0),
                                      fill=0, dtype="uint8") == 0
                    rgb[~valid] = 0 if nodata is None else nodata
                    if nodata is not None:
                        # keep real pixels off the nodata value
                        real = np.all(rgb == nodata, axis=-1) & valid
                        rgb[real] = np.clip(int(nodata) + 1, 0, 255)
                seen = ~occ if valid is None else (~occ & valid)
                label &= seen
                n_vis += np.bincount(ids[seen].ravel(), minlength=n_vis.size)[: n_vis.size]
                ds.write(np.moveaxis(rgb, -1, 0), indexes=[1, 2, 3], window=win)
                if alpha:
                    ds.write((valid * 255).astype(np.uint8), 4, window=win)
                if lab_ds is not None:
                    lab_ds.write(label.astype(np.uint8), 1, window=win)
                bar.update(h)
            bar.close()
        finally:
            if lab_ds is not None:
                lab_ds.close()

    # truth: markings whose centroid is inside the valid image area
    truth = []
    pts_x = np.array([m.x for m in scene.markings])
    pts_y = np.array([m.y for m in scene.markings])
    if len(pts_x):
        same = CRS.from_user_input(scene.crs) == out_crs
        if same:
            ix, iy = pts_x, pts_y
        else:
            ix, iy = Transformer.from_crs(scene.crs, crs, always_xy=True).transform(pts_x, pts_y)
        inv = ~transform
        for i, (m, x, y) in enumerate(zip(scene.markings, ix, iy)):
            c, r = inv @ (x, y)
            if not (0 <= c < width and 0 <= r < height):
                continue
            if mask_poly is not None and mask_poly.contains(Point(x, y)):
                continue
            px_area = scene.marking_polygons[i].area / (resolution_m * resolution_m)
            visible = min(1.0, n_vis[i + 1] / max(px_area, 1e-9))
            truth.append((m, float(x), float(y), round(float(visible), 3)))
    markings = _truth_markings(truth, scene.crs, crs)
    truth_path = out_tif.with_suffix(".truth.geojson")
    write_truth_geojson(markings, crs, truth_path)
    log.info("rendered %s: %dx%d px, %d true markings", out_tif, width, height, len(markings))
    return RenderResult(out_tif, truth_path, markings, str(crs), transform, (height, width), resolution_m)


def _truth_markings(items, scene_crs: str, crs: str) -> list[Marking]:
    """Markings in the image CRS with true-north bearings."""
    if not items:
        return []
    sc = scene_crs
    lon, lat = to_wgs84(sc).transform(np.array([it[0].x for it in items]),
                                      np.array([it[0].y for it in items]))
    conv = np.atleast_1d(meridian_convergence_deg(sc, lon, lat))
    t = None
    if CRS.from_user_input(scene_crs) != CRS.from_user_input(crs):
        t = Transformer.from_crs(scene_crs, crs, always_xy=True)
    out = []
    for (m, x, y, visible), cv in zip(items, conv):
        e = [m.x0, m.y0, m.x1, m.y1]
        if t is not None and m.x0 is not None:
            a = t.transform(m.x0, m.y0)
            b = t.transform(m.x1, m.y1)
            e = [a[0], a[1], b[0], b[1]]
        out.append(Marking(
            x=x, y=y, length_m=m.length_m, width_m=m.width_m,
            bearing_deg=float((m.bearing_deg + cv) % 180.0), weight=m.weight, kind=m.kind,
            source="imported", x0=e[0], y0=e[1], x1=e[2], y1=e[3],
            extra={**m.extra, "visible": visible},
        ))
    return out


def write_truth_geojson(markings: Iterable[Marking], crs: str, path: str | Path) -> Path:
    """Write markings as a GeoJSON FeatureCollection of WGS84 points.

    Properties: ``length_m``, ``width_m``, ``bearing_deg`` (clockwise from true
    north), ``kind``, ``x``/``y`` in ``crs``, and ``visible`` (share of the painted
    area not hidden by cars, trees, roofs or no-data) when known.
    """
    markings = list(markings)
    path = Path(path)
    feats = []
    if markings:
        lon, lat = to_wgs84(str(crs)).transform(
            np.array([m.x for m in markings]), np.array([m.y for m in markings]))
        for m, lo, la in zip(markings, np.atleast_1d(lon), np.atleast_1d(lat)):
            feats.append({
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [round(float(lo), 9), round(float(la), 9)]},
                "properties": {
                    "length_m": round(m.length_m, 4), "width_m": round(m.width_m, 4),
                    "bearing_deg": round(m.bearing_deg, 3), "kind": m.kind,
                    "x": m.x, "y": m.y, **m.extra,
                },
            })
    path.write_text(json.dumps({"type": "FeatureCollection", "crs_of_xy": str(crs), "features": feats}))
    return path


def read_truth_geojson(path: str | Path) -> list[dict]:
    """Read a truth GeoJSON written by :func:`render`: list of feature property dicts with lon/lat."""
    data = json.loads(Path(path).read_text())
    out = []
    for f in data.get("features", []):
        p = dict(f.get("properties") or {})
        p["lon"], p["lat"] = f["geometry"]["coordinates"][:2]
        out.append(p)
    return out

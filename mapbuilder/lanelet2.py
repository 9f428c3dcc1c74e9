"""Read a Lanelet2 HD map (OSM XML) and lay its lane markings out as centroid markings.

Lanelet2 stores a dashed line as one polyline; a camera and an aerial image see
its individual dashes. :func:`layout_markings` turns the map's lines into the
markings lanemap works with: dashes laid out with a dash/gap pattern, stop
lines as single markings, and solid lines cut into short pieces so that every
centroid is local. A painted dashed line often spans several line strings (a
map splits it wherever a lanelet ends); its pattern runs on across such joins
(:func:`dashed_chains`).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .crs import from_wgs84, meridian_convergence_deg, to_wgs84
from .model import Marking

#: Painted line widths by Lanelet2 line type, metres (German urban practice).
LINE_WIDTH_M = {"line_thin": 0.12, "line_thick": 0.25, "stop_line": 0.50}

#: Lanelet2 types that are lane markings; everything else (curbs, walls...) is context.
MARKING_TYPES = frozenset(LINE_WIDTH_M)


class Lanelet2Error(ValueError):
    """The file is not a readable Lanelet2 OSM map."""


@dataclass(frozen=True)
class Line:
    """One OSM way of the map, projected to the map's metric CRS."""

    id: int
    type: str
    subtype: str | None
    xy: np.ndarray  # (N, 2) metres in the map CRS

    @property
    def length_m(self) -> float:
        return float(np.sum(np.hypot(*np.diff(self.xy, axis=0).T)))


@dataclass
class LaneletMap:
    """The geometry of a Lanelet2 map in a metric CRS."""

    crs: str
    lines: list[Line]
    #: Lanelet centrelines, (N, 2) metres, ordered in the lanelet's direction.
    centerlines: list[np.ndarray] = field(default_factory=list)

    def lines_of(self, *types: str) -> list[Line]:
        return [line for line in self.lines if line.type in types]


def read_lanelet2(path: str | Path, crs: str = "EPSG:25832") -> LaneletMap:
    """Parse a Lanelet2 OSM XML file and project it to ``crs``.

    Parameters
    ----------
    path : path
        The ``.osm`` file.
    crs : str
        Metric CRS to project into (ETRS89 / UTM 32N suits Karlsruhe).
    """
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise Lanelet2Error(f"cannot read Lanelet2 map {path}: {exc}") from exc
    lonlat: dict[int, tuple[float, float]] = {}
    for node in root.iter("node"):
        lonlat[int(node.get("id"))] = (float(node.get("lon")), float(node.get("lat")))
    if not lonlat:
        raise Lanelet2Error(f"{path} holds no OSM nodes")
    ids = np.fromiter(lonlat.keys(), dtype=np.int64)
    lon, lat = np.array(list(lonlat.values())).T
    x, y = from_wgs84(crs).transform(lon, lat)
    node_xy = {int(i): (float(a), float(b)) for i, a, b in zip(ids, x, y)}

    lines: dict[int, Line] = {}
    for way in root.iter("way"):
        tags = {t.get("k"): t.get("v") for t in way.iter("tag")}
        refs = [int(nd.get("ref")) for nd in way.iter("nd")]
        pts = [node_xy[r] for r in refs if r in node_xy]
        if len(pts) < 2:
            continue
        wid = int(way.get("id"))
        lines[wid] = Line(wid, tags.get("type", ""), tags.get("subtype"), np.array(pts))

    centerlines = []
    for rel in root.iter("relation"):
        tags = {t.get("k"): t.get("v") for t in rel.iter("tag")}
        if tags.get("type") != "lanelet":
            continue
        bounds = {m.get("role"): int(m.get("ref")) for m in rel.iter("member")}
        left, right = lines.get(bounds.get("left")), lines.get(bounds.get("right"))
        if left is None or right is None:
            continue
        centerlines.append(_centerline(left.xy, right.xy))
    return LaneletMap(crs=crs, lines=list(lines.values()), centerlines=centerlines)


def _arc_length(xy: np.ndarray) -> np.ndarray:
    """Distance along the polyline ``xy`` at each of its vertices, metres (0 at the first)."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])


def _resample(xy: np.ndarray, n: int) -> np.ndarray:
    s = _arc_length(xy)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])])


def _centerline(left: np.ndarray, right: np.ndarray, step_m: float = 1.0) -> np.ndarray:
    # Lanelet2 lets a bound run against the lanelet; orient the left bound like the right.
    if np.hypot(*(left[0] - right[0])) > np.hypot(*(left[-1] - right[0])):
        left = left[::-1]
    length = max(np.sum(np.hypot(*np.diff(right, axis=0).T)), step_m)
    n = max(int(math.ceil(length / step_m)) + 1, 2)
    return 0.5 * (_resample(left, n) + _resample(right, n))


def _point_at(xy: np.ndarray, s_cum: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, s_cum, xy[:, 0]), np.interp(s, s_cum, xy[:, 1])])


def _segment_marking(
    xy: np.ndarray, s_cum: np.ndarray, s0: float, s1: float, width: float, kind: str
) -> Marking:
    """A marking covering arc length [s0, s1] of a polyline."""
    inner = s_cum[(s_cum > s0) & (s_cum < s1)]
    ss = np.concatenate([[s0], inner, [s1]])
    pts = np.array([_point_at(xy, s_cum, s) for s in ss])
    seg = np.hypot(*np.diff(pts, axis=0).T)
    mids = 0.5 * (pts[1:] + pts[:-1])
    centroid = (mids * seg[:, None]).sum(0) / max(seg.sum(), 1e-9)
    dx, dy = pts[-1] - pts[0]
    bearing = math.degrees(math.atan2(dx, dy)) % 180.0  # grid north; made true below
    length = float(seg.sum())
    return Marking(
        x=float(centroid[0]),
        y=float(centroid[1]),
        length_m=length,
        width_m=width,
        bearing_deg=bearing,
        weight=max(1.0, round(length * width / 0.01)),  # area in 10 cm pixels
        kind=kind,
        x0=float(pts[0, 0]),
        y0=float(pts[0, 1]),
        x1=float(pts[-1, 0]),
        y1=float(pts[-1, 1]),
    )


#: Line strings of one dashed line meet end to end, turning by at most this
#: much, degrees; a sharper turn (a junction's corner) starts a new pattern.
MAX_JOIN_TURN_DEG = 30.0


def dashed_chains(lines: list[Line]) -> list[tuple[str, np.ndarray]]:
    """Dashed line strings joined into the painted lines they belong to.

    Two line strings of the same type join where an end of one is an end of
    the other (the same node, to 1 cm), no third dashed line string ends
    there, and the line runs on straight enough (:data:`MAX_JOIN_TURN_DEG`).
    Lanelet2 splits a line wherever a lanelet ends, every 15 m or so in a
    city; laid out string by string, the dash pattern would restart at each
    split and put dashes end to end or leave slivers, which no painter does.

    Parameters
    ----------
    lines : list of Line
        The dashed line strings.

    Returns
    -------
    list of (type, (N, 2) ndarray)
        Each painted line's type and polyline, metres, in the order of its
        first line string where that is unambiguous.
    """

    def key(p) -> tuple[float, float]:
        return round(float(p[0]), 2), round(float(p[1]), 2)

    def leaving(xy: np.ndarray, at_start: bool) -> np.ndarray:
        a, b = (xy[0], xy[1]) if at_start else (xy[-1], xy[-2])
        d = b - a
        return d / max(float(np.hypot(*d)), 1e-12)

    ends: dict[tuple[float, float], list[tuple[int, int]]] = {}
    for i, ln in enumerate(lines):
        ends.setdefault(key(ln.xy[0]), []).append((i, 0))
        ends.setdefault(key(ln.xy[-1]), []).append((i, -1))
    straight = -math.cos(math.radians(MAX_JOIN_TURN_DEG))
    link: dict[tuple[int, int], tuple[int, int]] = {}
    for pair in ends.values():
        if len(pair) != 2:
            continue
        (i, ei), (j, ej) = pair
        if i == j or lines[i].type != lines[j].type:
            continue
        # Both directions leave the joint: a straight join points them apart.
        if float(leaving(lines[i].xy, ei == 0) @ leaving(lines[j].xy, ej == 0)) > straight:
            continue
        link[(i, ei)] = (j, ej)
        link[(j, ej)] = (i, ei)
    done: set[int] = set()
    chains = []
    # Strings with a free end first, so that an open line is walked from its end.
    for first in sorted(range(len(lines)), key=lambda i: ((i, 0) in link) + ((i, -1) in link)):
        if first in done:
            continue
        i, e = first, 0
        while (i, e) in link:  # back to the line's start (or round a loop once)
            j, ej = link[(i, e)]
            if j == first:
                break
            i, e = j, -1 if ej == 0 else 0
        parts = []
        while i not in done:
            done.add(i)
            xy = lines[i].xy if e == 0 else lines[i].xy[::-1]
            parts.append(xy if not parts else xy[1:])
            out = (i, -1 if e == 0 else 0)
            if out not in link:
                break
            i, e = link[out][0], 0 if link[out][1] == 0 else -1
        chains.append((lines[first].type, np.vstack(parts)))
    return chains


def layout_markings(
    lmap: LaneletMap,
    dash_m: float = 3.0,
    gap_m: float = 6.0,
    piece_m: float = 3.0,
    phase_m: float = 0.0,
) -> list[Marking]:
    """Lay the map's lane markings out as individual markings.

    Parameters
    ----------
    lmap : LaneletMap
        A map from :func:`read_lanelet2`.
    dash_m, gap_m : float
        Dash and gap lengths of dashed lines, metres (3 m / 6 m: German urban guide line).
    piece_m : float
        Longest piece a solid line is cut into, metres.
    phase_m : float
        Offset of the first dash from the start of each dashed line, metres
        (of each painted line: the pattern runs on across the line strings it
        spans, :func:`dashed_chains`).

    Returns
    -------
    list of Marking
        ``source="imported"``; ``kind`` is ``dash``, ``solid`` or ``stop_line``.
        Bearings are clockwise from true north (grid bearings corrected by the
        meridian convergence), in [0, 180).
    """
    out: list[Marking] = []
    period = dash_m + gap_m
    painted = [ln for ln in lmap.lines if ln.type in MARKING_TYPES]
    dashed = [ln for ln in painted if ln.type != "stop_line" and ln.subtype == "dashed"]
    for kind, xy in dashed_chains(dashed):
        s_cum = _arc_length(xy)
        total = float(s_cum[-1])
        s = phase_m % period
        while s < total - 0.5:  # a dash shorter than 0.5 m is not painted
            out.append(_segment_marking(xy, s_cum, s, min(s + dash_m, total), LINE_WIDTH_M[kind], "dash"))
            s += period
    laid = {id(ln) for ln in dashed}
    for line in painted:
        if id(line) in laid:
            continue
        width = LINE_WIDTH_M[line.type]
        xy = line.xy
        s_cum = _arc_length(xy)
        total = float(s_cum[-1])
        if total < 0.05:
            continue
        if line.type == "stop_line":
            out.append(_segment_marking(xy, s_cum, 0.0, total, width, "stop_line"))
        else:  # solid, and the solid side of solid_dashed / dashed_solid
            n = max(1, math.ceil(total / piece_m - 1e-9))
            edges = np.linspace(0.0, total, n + 1)
            for a, b in zip(edges[:-1], edges[1:]):
                out.append(_segment_marking(xy, s_cum, a, b, width, "solid"))
    if out:
        x = np.array([m.x for m in out])
        y = np.array([m.y for m in out])
        lon, lat = to_wgs84(lmap.crs).transform(x, y)
        conv = meridian_convergence_deg(lmap.crs, lon, lat)
        for m, c in zip(out, np.atleast_1d(conv)):
            m.bearing_deg = float((m.bearing_deg + c) % 180.0)
    return out

"""A small editable map with aerial imagery, and a headless Chromium, for the editor's tests.

The map is a 120 m x 80 m window of the Karlsruhe Lanelet2 example: its
markings laid out as dashes and pieces and imported through the API (a mix of
detections, some scoring low, manual and imported markings), and imagery of
the window rendered at 10 cm and uploaded as a GeoTIFF. Rendering takes a few
seconds, once per test module; each test then makes a map of its own.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tests._api_helpers import REPO, ApiServer

WINDOW_M = (120.0, 80.0)
CRS = "EPSG:25832"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]
#: Where screenshots go; override with LANEMAP_TEST_ARTIFACTS.
ARTIFACTS = Path(os.environ.get("LANEMAP_TEST_ARTIFACTS", REPO / "test-artifacts"))


def metres_between(lon0: float, lat0: float, lon1: float, lat1: float) -> float:
    """Distance (m) between two nearby lon/lat points (local tangent plane)."""
    r = 6378137.0
    e = math.radians(lon1 - lon0) * r * math.cos(math.radians((lat0 + lat1) / 2))
    n = math.radians(lat1 - lat0) * r
    return math.hypot(e, n)


@dataclass
class Window:
    """The rendered imagery of the window and its markings as GeoJSON features."""

    tif: Path
    features: list[dict]


@dataclass
class Fixture:
    map_id: str
    features: dict[str, dict]  # id -> GeoJSON feature as the server answered it
    detected: list[str]  # ids of the unreviewed detections, lowest score first

    def lonlat(self, fid: str) -> tuple[float, float]:
        lon, lat = self.features[fid]["geometry"]["coordinates"][:2]
        return lon, lat

    def isolated(self, min_gap_m: float = 4.0, **props) -> list[str]:
        """Ids of markings with no other centroid within ``min_gap_m`` (easy to click), matching ``props``."""
        out = []
        for fid, f in self.features.items():
            if any(f["properties"].get(k) != v for k, v in props.items()):
                continue
            lon, lat = self.lonlat(fid)
            if all(metres_between(lon, lat, *self.lonlat(o)) >= min_gap_m for o in self.features if o != fid):
                out.append(fid)
        return out


def render_window(tmp: Path) -> Window:
    """Render the window's imagery (10 cm) and lay out its markings: a mix of sources, statuses, scores."""
    from mapbuilder.crs import to_wgs84
    from mapbuilder.lanelet2 import layout_markings, read_lanelet2
    from mapbuilder.synth import render
    from service.demo import busiest_window, demo_osm

    lmap = read_lanelet2(demo_osm(), crs=CRS)
    items = layout_markings(lmap)
    x = np.array([m.x for m in items])
    y = np.array([m.y for m in items])
    w, s, e, n = busiest_window(x, y, WINDOW_M)
    items = [m for m in items if w + 2 <= m.x <= e - 2 and s + 2 <= m.y <= n - 2]
    tif = tmp / "window.tif"
    render(lmap, tif, resolution_m=0.1, seed=7, bounds=(w, s, e, n))
    to_ll = to_wgs84(CRS)
    rng = np.random.default_rng(3)
    features = []
    for i, m in enumerate(items):
        lon, lat = to_ll.transform(m.x, m.y)
        props = {"weight": max(round(m.length_m * m.width_m / 0.01, 1), 10.0), "length_m": m.length_m,
                 "width_m": m.width_m, "bearing_deg": m.bearing_deg, "kind": m.kind}  # fmt: skip
        if i % 3 == 0:  # a detection, some of them doubtful
            props.update(source="detected", status="unreviewed", score=round(float(rng.uniform(0.2, 0.99)), 3))
        elif i % 7 == 1:
            props.update(source="manual", status="accepted")
        else:
            props.update(source="imported", status="accepted" if i % 2 else "unreviewed")
        features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon, lat]},
                         "properties": props})  # fmt: skip
    return Window(tif, features)


def create_map(server: ApiServer, window: Window, map_id: str) -> Fixture:
    """Create ``map_id`` on ``server`` through the API: the window's markings and its imagery."""
    with server.client(headers=server.auth) as c:
        r = c.post("/collections", json={"id": map_id, "title": "Karlsruhe window", "crs": CRS})
        assert r.status_code == 201, r.text
        r = c.post(f"/collections/{map_id}/import", params={"comment": "survey import"},
                   json={"type": "FeatureCollection", "features": window.features})  # fmt: skip
        assert r.status_code == 201, r.text
        r = c.post(f"/collections/{map_id}/imagery", content=window.tif.read_bytes(),
                   headers={"Content-Type": "image/tiff"})  # fmt: skip
        assert r.status_code == 201, r.text
        got = c.get(f"/collections/{map_id}/items", params={"limit": 10000}).json()["features"]
    det = [f for f in got
           if f["properties"]["source"] == "detected" and f["properties"]["status"] == "unreviewed"]  # fmt: skip
    det.sort(key=lambda f: (f["properties"]["score"], int(f["id"])))
    return Fixture(map_id, {f["id"]: f for f in got}, [f["id"] for f in det])


def launch(playwright):
    """Debian's Chromium, headless, as CI runs it."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)

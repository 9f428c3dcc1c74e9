"""Localize on board, against a copy of the map that ``mirror_map.py`` keeps: no server needed.

The localizer is a library of its own (numpy, scipy, pyproj, numba): a vehicle
that carries a copy of the map answers its camera frames itself, and brings
the copy up to date whenever it has a connection.

Usage (from the repository root, the demo server of the README running):

    python docs/examples/mirror_map.py http://127.0.0.1:8000 karlsruhe copy.geojson accepted,unreviewed
    python docs/examples/localize_onboard.py copy.geojson docs/examples/frame.json

The frame file is a localization request body (``gps`` and ``observations``);
prints the pose as JSON, as the server would answer it.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from pyproj import CRS
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from localizer import GeoFrame, MapIndex, Prior, localize


def load_index(path: str) -> MapIndex:
    """The localizer's index of a mirrored copy, in the map's own CRS (``storageCrs``), else in
    the UTM zone of the copy's centre."""
    with open(path) as f:
        copy = json.load(f)
    features = copy["features"]
    if not features:
        raise SystemExit(f"error: {path} holds no markings")
    lon = np.array([f["geometry"]["coordinates"][0] for f in features])
    lat = np.array([f["geometry"]["coordinates"][1] for f in features])
    props = [f["properties"] for f in features]
    lon0, lat0 = float(lon.mean()), float(lat.mean())
    crs = copy.get("storageCrs")
    if crs is not None:
        crs = CRS.from_user_input(crs).to_string()  # the feed's OGC URI as EPSG:code
    else:  # a copy taken before the feed named the CRS
        zone = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon0, lat0, lon0, lat0))[0]
        crs = f"{zone.auth_name}:{zone.code}"
    frame = GeoFrame(crs)
    x, y = frame.to_xy(lon, lat)
    # The copy's bearings are clockwise from true north; the index wants them from grid north.
    convergence = frame.convergence_deg(lon0, lat0)
    return MapIndex.from_arrays(
        x, y, np.array([p.get("weight", 1.0) for p in props]), crs,
        bearing_deg=np.array([p.get("bearing_deg", 0.0) for p in props]) - convergence,
        length_m=np.array([p.get("length_m", 0.0) for p in props]),
        kind=[p.get("kind") for p in props],
        measured=np.array([p.get("source") == "detected" for p in props]),
    )


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit("usage: localize_onboard.py COPY.geojson FRAME.json")
    index = load_index(sys.argv[1])
    with open(sys.argv[2]) as f:
        frame = json.load(f)
    gps = frame["gps"]
    prior = Prior(lat=gps["lat"], lon=gps["lon"], heading_deg=gps["heading_deg"],
                  position_sigma_m=gps.get("position_sigma_m", 5.0), heading_sigma_deg=gps.get("heading_sigma_deg", 10.0))
    obs = np.array([[o["x"], o["y"], o.get("weight", 1.0)] for o in frame["observations"]], float)
    pose = localize(index, obs, prior)
    print(json.dumps(pose.to_dict(), indent=2))


if __name__ == "__main__":
    main()

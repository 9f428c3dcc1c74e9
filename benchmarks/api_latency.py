"""Latency of the REST API over HTTP, against a real ``lanemap serve`` process.

The server (one uvicorn worker, SQLite by default or PostgreSQL with
``--postgres URL``) gets the Karlsruhe Lanelet2 layout (819 markings) and
optionally ``--copies`` shifted copies of it to make a larger map. One
client then times, sequentially:

* ``GET /collections/{id}/items?bbox=...&limit=100``: an editor viewport
  of about 150 m × 100 m;
* ``GET /collections/{id}/items/{featureId}``;
* ``PATCH`` of one marking (a status change, a new version each time);
* ``POST /collections/{id}/changesets`` of 20 updates;
* ``POST /collections/{id}/localize`` with both methods, on simulated views
  of the map (15–45 markings, GPS 2.5 m and 4° off);
* ``GET`` of 256 px imagery tiles of the demo imagery, each rendered once.

It prints p50/p95/max per request kind and the machine load, and writes a
latency histogram to ``benchmarks/out/api_latency.png``.

Usage::

    .venv/bin/python benchmarks/api_latency.py [--n 200] [--copies 0] [--postgres URL]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mapbuilder.crs import from_wgs84, to_wgs84
from mapbuilder.geojson import markings_to_feature_collection
from mapbuilder.lanelet2 import layout_markings, read_lanelet2
from tests._api_helpers import SHARED_DATA, fresh_postgres_db, start_server
from tests.test_api_localize import gps_near, scene

CRS = "EPSG:25832"


def timed(fn, n: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out[i] = (time.perf_counter() - t0) * 1000.0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="requests per kind")
    ap.add_argument("--copies", type=int, default=0, help="extra shifted copies of the map (bigger map)")
    ap.add_argument("--postgres", default=None, help="run on a fresh database of this PostgreSQL server")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="lanemap-bench-"))
    drop = None
    if args.postgres:
        os.environ["LANEMAP_TEST_POSTGRES_URL"] = args.postgres
        url, drop = fresh_postgres_db()
    else:
        url = f"sqlite:///{tmp / 'db.sqlite'}"
    server = start_server(url, tmp / "data", args=("--demo", "--log-level", "warning"), timeout=300)
    try:
        c = httpx.Client(base_url=server.base_url, headers=server.auth, timeout=60)
        map_id = "karlsruhe"
        if args.copies:
            items = layout_markings(read_lanelet2(SHARED_DATA / "karlsruhe-lanelet2" / "mapping_example.osm"))
            tr = to_wgs84(CRS)
            for k in range(1, args.copies + 1):
                for m in items:
                    m.lon, m.lat = tr.transform(m.x, m.y + 2000.0 * k)
                r = c.post(f"/collections/{map_id}/import", json=markings_to_feature_collection(items))
                assert r.status_code == 201, r.text
        feats = c.get(f"/collections/{map_id}/items?limit=10000&bbox=8.3,48.9,8.5,49.1").json()["features"]
        feats.sort(key=lambda f: int(f["id"]))
        n_total = c.get(f"/collections/{map_id}").json()["numberOfFeatures"]
        rng = np.random.default_rng(0)
        fw = from_wgs84(CRS)
        xy = np.array([fw.transform(*f["geometry"]["coordinates"]) for f in feats])
        tr = to_wgs84(CRS)

        def bbox_page(i):
            cx, cy = xy[rng.integers(len(xy))]
            w, s = tr.transform(cx - 75, cy - 50)
            e, n = tr.transform(cx + 75, cy + 50)
            r = c.get(f"/collections/{map_id}/items", params={"bbox": f"{w},{s},{e},{n}", "limit": 100})
            assert r.status_code == 200

        ids = [f["id"] for f in feats]

        def get_item(i):
            assert c.get(f"/collections/{map_id}/items/{ids[i % len(ids)]}").status_code == 200

        def patch_item(i):
            st = ("accepted", "unreviewed")[i % 2]
            r = c.patch(f"/collections/{map_id}/items/{ids[7]}", json={"properties": {"status": st}})
            assert r.status_code == 200

        def changeset(i):
            chunk = ids[100 + (i % 20) * 20: 120 + (i % 20) * 20]
            st = ("accepted", "rejected")[i % 2]
            body = {"comment": "bench", "changes": [
                {"op": "update", "id": f, "patch": {"properties": {"status": st}}} for f in chunk]}  # fmt: skip
            assert c.post(f"/collections/{map_id}/changesets", json=body).status_code == 201

        poses = []
        for idx in range(0, len(feats), max(1, len(feats) // 400)):
            p, lon, lat, heading, obs = scene(feats, idx)
            if 15 <= len(obs) <= 45:
                poses.append((gps_near(p, heading), obs))
        results: dict[str, int] = {}

        def localize(method):
            def run(i):
                gps, obs = poses[i % len(poses)]
                r = c.post(f"/collections/{map_id}/localize", json={"gps": gps, "observations": obs, "method": method})
                assert r.status_code == 200
                results[r.json()["status"]] = results.get(r.json()["status"], 0) + 1

            return run

        img = c.get(f"/collections/{map_id}/imagery").json()["imagery"][0]
        b = img["bounds"]

        def tile_xy(lon, lat, z):
            tx = int((lon + 180) / 360 * 2**z)
            ty = int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * 2**z)
            return tx, ty

        # every z20 tile inside the imagery, each rendered once (the server caches rendered tiles)
        (x0, y0), (x1, y1) = tile_xy(*tr.transform(b[0], b[3]), 20), tile_xy(*tr.transform(b[2], b[1]), 20)
        tiles = [(20, tx, ty) for tx in range(x0 + 1, x1) for ty in range(y0 + 1, y1)]
        rng.shuffle(tiles)

        def tile(i):
            z, tx, ty = tiles[(i + 1) % len(tiles)]
            assert c.get(f"/collections/{map_id}/imagery/tiles/WebMercatorQuad/{z}/{tx}/{ty}.png").status_code == 200

        # warm-up: the localizer's index and the tile reader
        localize("default")(0)
        tile(0)
        kinds = {
            "GET items bbox (viewport, limit 100)": bbox_page,
            "GET item": get_item,
            "PATCH item": patch_item,
            "POST changeset (20 updates)": changeset,
            "POST localize default": localize("default"),
            "POST localize pink2008": localize("pink2008"),
            "GET tile 256 px PNG (uncached)": tile,
        }
        load0 = os.getloadavg()[0]
        print(f"server: {'PostgreSQL' if args.postgres else 'SQLite'}, 1 uvicorn worker; map: {n_total} markings; "
              f"{args.n} sequential requests per kind over loopback")  # fmt: skip
        print(f"{'request':40s} {'p50 ms':>8s} {'p95 ms':>8s} {'max ms':>8s}")
        timings = {}
        for name, fn in kinds.items():
            t = timed(fn, args.n)
            timings[name] = t
            print(f"{name:40s} {np.percentile(t, 50):8.1f} {np.percentile(t, 95):8.1f} {t.max():8.1f}")
        print(f"localization statuses: {results}")
        print(f"load average (1 min) before / after: {load0:.2f} / {os.getloadavg()[0]:.2f}, cores: {os.cpu_count()}")
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            out = REPO / "benchmarks" / "out"
            out.mkdir(parents=True, exist_ok=True)
            fig, ax = plt.subplots(figsize=(9, 4.5))
            ax.boxplot(list(timings.values()), orientation="horizontal", tick_labels=list(timings), showfliers=False)
            ax.set_xscale("log")
            ax.set_xlabel("latency, ms (log)")
            ax.set_title(f"lanemap API latency, {n_total} markings")
            fig.tight_layout()
            fig.savefig(out / "api_latency.png", dpi=120)
            print(f"plot: {out / 'api_latency.png'}")
        except Exception as exc:  # the figures above are the result; the plot is a convenience
            print(f"no plot: {exc}")
    finally:
        server.stop()
        if drop is not None:
            drop()


if __name__ == "__main__":
    main()

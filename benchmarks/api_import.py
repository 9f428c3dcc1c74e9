"""A city's import over HTTP, answered at once or as a job (``POST /collections/{id}/import``).

Writes a GeoJSON FeatureCollection of N markings (1,000,000 by default, about 211 MB),
starts ``lanemap serve`` on a fresh database, and imports the file into an empty map:
synchronously (201 when it is written), and with ``Prefer: respond-async`` (202 at once,
then the job polled to its end). Prints, for each, when the answer came and when the
markings were in, the server's memory growth and the peak of the job's process, and the
progress the job showed.

Run: ``.venv/bin/python benchmarks/api_import.py [--n 1000000] [--url postgresql://...]``
(``--url``: an empty PostgreSQL database; a fresh SQLite file in a temporary folder by default).
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import psutil

PORT = 8765


def write_body(path: Path, n: int) -> None:
    """``n`` detections spread over Karlsruhe, as a GeoJSON FeatureCollection."""
    rng = np.random.default_rng(0)
    lon, lat = 8.35 + rng.uniform(0, 0.14, n), 48.98 + rng.uniform(0, 0.09, n)
    with open(path, "w") as fh:
        fh.write('{"type": "FeatureCollection", "features": [')
        for i in range(n):
            fh.write(("," if i else "") + '{"type": "Feature", "geometry": {"type": "Point", "coordinates": '
                     f'[{lon[i]:.8f}, {lat[i]:.8f}]}}, "properties": {{"weight": 36, "length_m": 3.0, '
                     f'"width_m": 0.12, "kind": "dash", "source": "detected", "score": {(i % 1000) / 1000}}}}}')
        fh.write("]}")


def run(mode: str, body: Path, url: str | None, folder: Path) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith("LANEMAP_")}
    env.update(LANEMAP_DATABASE_URL=url or f"sqlite:///{folder / 'db.sqlite'}", LANEMAP_DATA_DIR=str(folder / "data"),
               LANEMAP_API_TOKENS="bench")  # fmt: skip
    srv = subprocess.Popen([str(Path(sys.executable).with_name("lanemap")), "serve", "--port", str(PORT)], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    base, auth = f"http://127.0.0.1:{PORT}", {"Authorization": "Bearer bench"}
    try:
        for _ in range(600):
            try:
                if httpx.get(base + "/health").status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        map_id = f"import-{mode}"
        httpx.post(base + "/collections", json={"id": map_id}, headers=auth).raise_for_status()
        proc = psutil.Process(srv.pid)
        start_rss, peak, done = proc.memory_info().rss, {"server": 0, "job": 0}, threading.Event()

        def watch() -> None:
            while not done.is_set():
                try:
                    peak["server"] = max(peak["server"], proc.memory_info().rss)
                    for child in proc.children(recursive=True):
                        peak["job"] = max(peak["job"], child.memory_info().rss)
                except psutil.Error:
                    pass
                time.sleep(0.05)

        threading.Thread(target=watch, daemon=True).start()
        headers = {**auth, "Content-Type": "application/geo+json"}
        if mode == "job":
            headers["Prefer"] = "respond-async"
        t0 = time.perf_counter()
        with open(body, "rb") as fh:
            r = httpx.post(f"{base}/collections/{map_id}/import", content=fh, headers=headers, timeout=1200)
        answered = time.perf_counter() - t0
        r.raise_for_status()
        progress = []
        if mode == "job":
            while (job := httpx.get(r.headers["location"]).json())["status"] in ("accepted", "running"):
                progress.append(int(job["progress"]))
                time.sleep(0.5)
            assert job["status"] == "successful", job
        finished = time.perf_counter() - t0
        done.set()
        n = httpx.get(f"{base}/collections/{map_id}").json()["numberOfFeatures"]
        # Deleted, so that the next server (on the same PostgreSQL database) has no map to preload.
        httpx.delete(f"{base}/collections/{map_id}", headers=auth, timeout=120).raise_for_status()
        steps = sorted(set(progress))
        return (f"{mode:5} HTTP {r.status_code} after {answered:.1f} s, {n:,} markings in after {finished:.1f} s; "
                f"server memory +{(peak['server'] - start_rss) / 1e6:.0f} MB, job process peak "
                f"{peak['job'] / 1e6:.0f} MB" + (f"; progress seen {steps}" if mode == "job" else ""))
    finally:
        os.killpg(srv.pid, signal.SIGTERM)
        srv.wait(30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--url", default=None, help="an empty PostgreSQL database (default: a fresh SQLite file)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        body = Path(tmp) / "markings.geojson"
        write_body(body, args.n)
        print(f"machine       {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
        print(f"body          {args.n:,} markings, {body.stat().st_size / 1e6:.0f} MB; database "
              f"{'PostgreSQL' if args.url else 'SQLite'}")
        for mode in ("sync", "job"):
            print(run(mode, body, args.url, Path(tmp) / mode))


if __name__ == "__main__":
    main()

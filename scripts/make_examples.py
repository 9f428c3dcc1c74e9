"""Write the example requests in ``docs/examples/`` (run from the repository root).

A simulated camera frame and a drive of eight frames on the Karlsruhe
Lanelet2 map as ``lanemap from-lanelet2`` lays it out (the demo map), with a
GPS fix 2 m and 5° off, in the bodies ``POST /collections/{mapId}/localize``
and ``.../localize/sequence`` take; ``lanemap localize --observations`` and
``--frames`` read the same files; ``drive-start.json`` and ``drive-next.json``
split the drive in two, for a drive streamed with its state. ``truth.json`` holds the true poses (the
drive's last frame) for the tests that keep the README's examples working.

Usage: ``.venv/bin/python scripts/make_examples.py`` (needs ``../shared/data``).
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from localizer.simulate import Camera, Clutter, odometry, perturb, sample_trajectories, simulate_scene  # noqa: E402
from tests._localizer_helpers import karlsruhe  # noqa: E402

OUT = ROOT / "docs" / "examples"
SEED = 20261203


def _gps(index, pose) -> dict:
    lon, lat = index.frame.to_lonlat(pose[0], pose[1])
    heading = float(index.frame.grid_yaw_to_heading(pose[2], lon, lat))
    return {"lat": round(float(lat), 7), "lon": round(float(lon), 7), "heading_deg": round(heading, 2),
            "position_sigma_m": 3.0, "heading_sigma_deg": 8.0}


def _truth(index, pose) -> dict:
    lon, lat = index.frame.to_lonlat(pose[0], pose[1])
    return {"easting": round(float(pose[0]), 3), "northing": round(float(pose[1]), 3),
            "lat": float(lat), "lon": float(lon),
            "heading_deg": float(index.frame.grid_yaw_to_heading(pose[2], lon, lat))}


def _obs(scene) -> list[dict]:
    return [{"x": round(float(x), 3), "y": round(float(y), 3), "weight": round(float(w), 1)}
            for x, y, w in scene.observations]


def _dump(obj) -> str:
    """JSON with every innermost object (an observation, a motion, the fix) on one line."""
    text = json.dumps(obj, indent=1)
    return re.sub(r"\{[^{}\[\]]*\}", lambda m: " ".join(m.group(0).split()), text) + "\n"


def main() -> None:
    index, smap = karlsruhe()
    rng = np.random.default_rng(SEED)
    drive = sample_trajectories(smap, 1, 8, 1.5, rng, min_visible=8)[0]
    cam, clutter = Camera(), Clutter()
    scenes = [simulate_scene(smap, tuple(p), rng, cam, clutter) for p in drive]
    fix = perturb(tuple(drive[0]), 2.0, 5.0, rng)
    frames = []
    for k, sc in enumerate(scenes):
        f = {"observations": _obs(sc)}
        if k:
            dx, dy, dyaw = odometry(drive[k - 1], drive[k])
            f["motion"] = {"dx": round(dx, 3), "dy": round(dy, 3), "dyaw_deg": round(math.degrees(dyaw), 3)}
        frames.append(f)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "frame.json").write_text(_dump({"gps": _gps(index, fix), "observations": frames[0]["observations"]}))
    (OUT / "drive.json").write_text(_dump({"gps": _gps(index, fix), "frames": frames}))
    # The same drive in two requests: the first seven frames, then the eighth
    # continuing from the state the first answer returns (--state / "state").
    (OUT / "drive-start.json").write_text(_dump({"gps": _gps(index, fix), "frames": frames[:7]}))
    (OUT / "drive-next.json").write_text(_dump({"frames": frames[7:]}))
    (OUT / "truth.json").write_text(_dump({"frame": _truth(index, drive[0]), "drive_last": _truth(index, drive[-1])}))
    print(f"wrote {OUT}/frame.json ({len(frames[0]['observations'])} observations), drive.json "
          f"({len(frames)} frames), drive-start.json, drive-next.json, truth.json; GPS fix {_gps(index, fix)}")


if __name__ == "__main__":
    main()

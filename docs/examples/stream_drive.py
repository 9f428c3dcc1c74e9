"""Stream a drive to a lanemap server one frame at a time, as a vehicle would.

Each request carries one camera frame (with the odometry since the frame
before) and the ``state`` of the previous answer; the first carries the GPS
fix instead. The server keeps nothing between requests, and the poses are
those one request with all the frames would give.

Usage (the demo server of the README, from the repository root):

    python docs/examples/stream_drive.py http://127.0.0.1:8000 karlsruhe docs/examples/drive.json
    python docs/examples/stream_drive.py http://127.0.0.1:8000 - docs/examples/drive.json

With ``-`` for the map, the server picks the map where the drive's first fix
is (``POST /localize/sequence``), the state keeps it, and the server hands the
drive to the next map when it drives into one. Prints one line per frame:
status, probability, latitude, longitude, heading (and, with ``-``, the map
at the first frame and wherever the drive was handed on).
Needs ``httpx`` (installed with lanemap).
"""

from __future__ import annotations

import json
import sys

import httpx


def stream(base_url: str, map_id: str | None, drive: dict, token: str | None = None) -> list[tuple[dict, str]]:
    """Send ``drive``'s frames one per request (to the map ``map_id``, or None: the map where the
    drive is); the pose at every frame and the map it is on."""
    url = f"{base_url}/localize/sequence" if map_id is None else f"{base_url}/collections/{map_id}/localize/sequence"
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    poses, state = [], None
    with httpx.Client(headers=headers, timeout=30) as client:
        for frame in drive["frames"]:
            body = {"frames": [frame]}
            if state is None:
                body["gps"] = drive["gps"]  # the drive starts at this fix
            else:
                body["state"] = state  # exactly as the previous answer gave it
            r = client.post(url, json=body)
            if r.status_code != 200:  # a problem+json body says why
                raise SystemExit(f"error: {r.status_code} {r.json().get('detail', r.text)}")
            answer = r.json()
            state = answer["state"]
            poses.append((answer["poses"][-1], answer.get("map", map_id)))
    return poses


def main() -> None:
    if len(sys.argv) != 4:
        raise SystemExit("usage: stream_drive.py BASE_URL MAP_ID|- DRIVE.json")
    base_url, map_id, path = sys.argv[1:]
    with open(path) as f:
        drive = json.load(f)
    previous = map_id
    for k, (p, on) in enumerate(stream(base_url.rstrip("/"), None if map_id == "-" else map_id, drive)):
        where = f" map={on}" if on != previous else ""  # the map the server picked, or handed the drive to
        previous = on
        if p["status"] == "failed":
            print(f"frame {k}: failed ({p.get('reason')}){where}")
        else:
            print(f"frame {k}: {p['status']} p={p['probability']:.4f} "
                  f"lat={p['lat']:.7f} lon={p['lon']:.7f} heading={p['heading_deg']:.2f}{where}")


if __name__ == "__main__":
    main()

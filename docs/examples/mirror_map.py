"""Keep a copy of a lanemap map in a GeoJSON file, current through the change feed.

The first run reads the whole map; each later run asks only for what changed
since the revision the file is at (``GET /collections/{id}/changes?since=``)
and applies it: the markings written since replace those of the same id, the
deleted ones go. A map that was deleted and made anew on the server (409) is
read whole again. The copy also keeps the map's ``storageCrs``, the metric
CRS the server localizes in. The file is replaced in one step, so a reader
never sees half a copy.

Usage (the demo server of the README, from the repository root):

    python docs/examples/mirror_map.py http://127.0.0.1:8000 karlsruhe copy.geojson [accepted,unreviewed]

The optional last argument keeps only markings of those statuses (what the
localizer uses). A token, when the server wants one for reads, comes from
``LANEMAP_TOKEN``. Prints one line: the markings held, the revision, and what
this run changed. Needs ``httpx`` (installed with lanemap).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import httpx


def mirror(base_url: str, map_id: str, path: Path, statuses: str | None = None,
           token: str | None = None) -> tuple[int, int, int, int]:  # fmt: skip
    """Bring the copy in ``path`` up to date; (markings held, revision, written, removed)."""
    copy = json.loads(path.read_text()) if path.exists() else None
    if copy is not None and (copy.get("map") != map_id or copy.get("statuses") != statuses):
        copy = None  # a copy of something else: start afresh
    held = {f["id"]: f for f in copy["features"]} if copy else {}
    since = copy["revision"] if copy else 0
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    written = removed = 0
    with httpx.Client(headers=headers, timeout=60) as client:
        params = {"since": since, **({"status": statuses} if statuses else {})}
        url = f"{base_url}/collections/{map_id}/changes"
        while True:
            r = client.get(url, params=params)
            if r.status_code == 409 and since:  # the map was made anew: read it whole
                return mirror(base_url, map_id, _forget(path), statuses, token)
            if r.status_code != 200:  # a problem+json body says why
                raise SystemExit(f"error: {r.status_code} {r.json().get('detail', r.text)}")
            page = r.json()
            for gone in page["removed"]:
                removed += held.pop(gone["id"], None) is not None
            for f in page["features"]:
                held[f["id"]] = f
                written += 1
            nxt = [link["href"] for link in page["links"] if link["rel"] == "next"]
            if not nxt:
                break
            url, params = nxt[0], None
    # The map's metric CRS: an on-board localizer projects the markings to it, as the server does.
    out = {"type": "FeatureCollection", "map": map_id, "statuses": statuses, "revision": page["revision"],
           "storageCrs": page.get("storageCrs"), "features": sorted(held.values(), key=lambda f: int(f["id"]))}
    part = path.with_name(path.name + ".part")
    part.write_text(json.dumps(out))
    part.replace(path)
    return len(held), page["revision"], written, removed


def _forget(path: Path) -> Path:
    path.unlink(missing_ok=True)
    return path


def main() -> None:
    if len(sys.argv) not in (4, 5):
        raise SystemExit("usage: mirror_map.py BASE_URL MAP_ID COPY.geojson [STATUSES]")
    base_url, map_id, path = sys.argv[1:4]
    statuses = sys.argv[4] if len(sys.argv) == 5 else None
    n, revision, written, removed = mirror(base_url.rstrip("/"), map_id, Path(path), statuses,
                                           os.environ.get("LANEMAP_TOKEN"))  # fmt: skip
    print(f"{path}: {n} markings at revision {revision} ({written} written, {removed} removed by this run)")


if __name__ == "__main__":
    main()

"""The filters a reader of a map's markings gives as text, for the API's ``/items``
(``bbox``, ``status``) and for ``lanemap export`` (``--bbox``, ``--status``).

Both parsers raise ``ValueError`` with a message fit for the user; the API
answers it as a 400 problem, the CLI as one ``error:`` line.
"""

from __future__ import annotations

import math

from mapbuilder.model import STATUSES


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    """``minLon,minLat,maxLon,maxLat`` (WGS84 degrees; or 6 numbers with heights, which are
    dropped) as a tuple."""
    parts = text.split(",")
    if len(parts) not in (4, 6):
        raise ValueError("bbox: give 4 numbers (minLon,minLat,maxLon,maxLat) or 6 with heights")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"bbox: {text[:80]!r} has a value that is not a number") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError("bbox: values must be finite numbers")
    if len(vals) == 6:
        vals = [vals[0], vals[1], vals[3], vals[4]]
    w, s, e, n = vals
    if not (-180 <= w <= 180 and -180 <= e <= 180):
        raise ValueError("bbox: longitudes must be within [-180, 180]")
    if not (-90 <= s <= 90 and -90 <= n <= 90):
        raise ValueError("bbox: latitudes must be within [-90, 90]")
    if s > n:
        raise ValueError("bbox: minLat is greater than maxLat")
    if w > e:
        raise ValueError("bbox: minLon is greater than maxLon (boxes across the antimeridian are not supported)")
    return w, s, e, n


def parse_statuses(text: str | None) -> list[str] | None:
    """Comma-separated review statuses as a list (None: every status)."""
    if not text:
        return None
    out = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in out if s not in STATUSES]
    if bad:
        raise ValueError(f"status: {bad[0][:40]!r} is not one of {', '.join(STATUSES)}")
    return out or None

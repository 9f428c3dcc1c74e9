"""The marking record every part of lanemap exchanges.

Coordinates are in the map's metric storage CRS; ``lon``/``lat`` are WGS84 and
filled in by the store.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

Source = Literal["detected", "manual", "imported"]
Status = Literal["unreviewed", "accepted", "rejected"]

SOURCES: tuple[str, ...] = ("detected", "manual", "imported")
STATUSES: tuple[str, ...] = ("unreviewed", "accepted", "rejected")


@dataclass(slots=True)
class Marking:
    """One lane-marking centroid with its shape.

    Attributes
    ----------
    x, y : float
        Centroid in the map's storage CRS, metres.
    length_m, width_m : float
        Extent along and across the major axis, metres.
    bearing_deg : float
        Direction of the major axis, degrees clockwise from north, in [0, 180).
    weight : float
        Pixel count of the marking's cluster (the weight γ of the matching).
    score : float or None
        Mean classifier probability for detected markings.
    kind : str or None
        ``dash``, ``solid``, ``stop_line``... when known.
    x0, y0, x1, y1 : float or None
        End points of the major axis in the storage CRS, metres.
    """

    x: float
    y: float
    length_m: float = 0.0
    width_m: float = 0.0
    bearing_deg: float = 0.0
    weight: float = 1.0
    score: float | None = None
    kind: str | None = None
    source: Source = "imported"
    status: Status = "unreviewed"
    x0: float | None = None
    y0: float | None = None
    x1: float | None = None
    y1: float | None = None
    tile_key: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    # Filled by the store.
    id: int | None = None
    version: int | None = None
    lon: float | None = None
    lat: float | None = None

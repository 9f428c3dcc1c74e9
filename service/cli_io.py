"""Files named on the ``lanemap`` command line, where ``-`` means standard input or output."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from mapbuilder.model import Marking

#: The file name that stands for standard input (or output).
STDIO = "-"


def is_stdio(path: Path | str) -> bool:
    return str(path) == STDIO


def source_name(path: Path | str) -> str:
    """How messages name the file: its name, or ``standard input``."""
    return "standard input" if is_stdio(path) else Path(path).name


def read_markings(path: Path | str, progress: Callable[[int, int], None] | None = None) -> list[Marking]:
    """Markings from a GeoJSON file, or from standard input for ``-``."""
    from mapbuilder.geojson import read_geojson_file, read_geojson_stream

    if is_stdio(path):
        return read_geojson_stream(sys.stdin.buffer, source_name(path), progress)
    return read_geojson_file(path, progress)

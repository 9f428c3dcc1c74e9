"""Files named on the ``lanemap`` command line (``-`` means standard input or output), its
``--bbox``, and the progress bars of the commands that read or write many markings."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import typer

from mapbuilder.model import Marking

#: The file name that stands for standard input (or output).
STDIO = "-"


def is_stdio(path: Path | str) -> bool:
    return str(path) == STDIO


def bbox_option(text: str | None) -> tuple[float, float, float, float] | None:
    """A command's ``--bbox MINLON,MINLAT,MAXLON,MAXLAT`` as a box (None when not given), or its
    one ``error:`` line."""
    from .cli_errors import fail
    from .filters import parse_bbox

    if text is None:
        return None
    try:
        return parse_bbox(text)
    except ValueError as exc:
        fail(f"--{exc}")


def coverage_option(text: str | None, *extra: str) -> str | None:
    """A command's ``--coverage`` (None when not given): one of ``mapbuilder.store.MAP_COVERAGES``
    or of ``extra`` (``default``), or its one ``error:`` line."""
    from mapbuilder.store import MAP_COVERAGES

    from .cli_errors import fail

    if text is not None and text not in (*MAP_COVERAGES, *extra):
        fail(f"--coverage must be one of {', '.join(MAP_COVERAGES)}" + "".join(f" or {e}" for e in extra)
             + f", got {text!r}")
    return text


def kept_indexes(store):
    """Where this command keeps and finds built indexes (``LANEMAP_INDEX_DIR``,
    :mod:`service.index_files`); None: nowhere."""
    from mapbuilder.settings import Settings

    from .index_files import index_files
    from .settings import IndexDirSettings

    return index_files(IndexDirSettings(), Settings().data_dir, store.engine.url)


def command_index(store, map_id: str, crs: str, coverage: str):
    """The map's localization index for a command (``lanemap localize``, ``maps coverage``): the
    kept one at the map's revision (:func:`service.index_files.current_index`), else built and
    kept, with a ``note:`` on stderr first, since a city's takes a while."""
    from .index_files import current_index

    files = kept_indexes(store)

    def say_building(count: int) -> None:
        typer.echo(f"note: building the localization index of map {map_id} ({count:,} markings); "
                   f"it is kept in {files.directory} for the next calls", err=True)

    return current_index(store, map_id, crs, coverage, files, on_build=say_building)


def map_coverage(option: str | None, own: str | None) -> str:
    """The coverage a command draws a map's extent by: ``--coverage``, else the map's own, else
    ``LANEMAP_MAP_COVERAGE`` as the server reads it, else the server's default (``hull``)."""
    import os

    from mapbuilder.store import MAP_COVERAGES

    from .cli_errors import fail
    from .settings import ServiceSettings

    if option or own:
        return option or own
    value = os.environ.get("LANEMAP_MAP_COVERAGE", ServiceSettings.model_fields["map_coverage"].default)
    if value not in MAP_COVERAGES:
        fail(f"LANEMAP_MAP_COVERAGE must be one of {', '.join(MAP_COVERAGES)}, got {value!r}")
    return value


def source_name(path: Path | str) -> str:
    """How messages name the file: its name, or ``standard input``."""
    return "standard input" if is_stdio(path) else Path(path).name


def read_markings(path: Path | str, progress: Callable[[int, int], None] | None = None) -> list[Marking]:
    """Markings from a GeoJSON file or a GeoPackage (``.gpkg``), or GeoJSON from standard input for ``-``."""
    from mapbuilder.geojson import read_geojson_file, read_geojson_stream, read_gpkg

    if is_stdio(path):
        return read_geojson_stream(sys.stdin.buffer, source_name(path), progress)
    if Path(path).suffix.lower() == ".gpkg":
        return read_gpkg(path, progress)
    return read_geojson_file(path, progress)


#: The ``--progress/--no-progress`` option of the commands that show bars.
PROGRESS_OPTION = typer.Option(
    None, "--progress/--no-progress",
    help="Show progress bars (rate, ETA) on stderr; default: when stderr is a terminal.")


def progress_bar(progress: bool | None, total: int | None, unit: str, desc: str):
    """A tqdm bar on stderr: asked for (``--progress``), or on a terminal once the work takes 0.5 s."""
    from tqdm import tqdm

    show = sys.stderr.isatty() if progress is None else progress
    return tqdm(total=total, unit=unit, desc=desc, disable=not show, file=sys.stderr, dynamic_ncols=True,
                unit_scale=True, delay=0.5 if progress is None else 0.0)


def follow(bar) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that moves ``bar``."""

    def progress(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.update(done - bar.n)
        # Each call is a step of thousands: drawn even when it comes within tqdm's 0.1 s
        # of the last frame (a fast machine read 12,000 features in 0.08 s, start to end),
        # once the bar's delay (a terminal's half second) is past.
        if not bar.disable and bar.format_dict["elapsed"] >= bar.delay:
            bar.refresh()

    return progress


def counted(items: Iterable, bar) -> Iterator:
    """``items``, moving ``bar`` by one for each."""
    for item in items:
        yield item
        bar.update(1)

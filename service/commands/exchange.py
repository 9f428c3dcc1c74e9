"""``lanemap import``, ``lanemap export`` and ``lanemap from-lanelet2``."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from mapbuilder.geojson import write_geojson, write_geojson_stream, write_gpkg
from mapbuilder.lanelet2 import layout_markings, read_lanelet2
from mapbuilder.store import Store

from ..cli_errors import fail
from ..cli_io import (
    PROGRESS_OPTION, bbox_option, counted, follow, is_stdio, progress_bar, read_markings, source_name,
)  # fmt: skip
from ..filters import parse_statuses

def register(app: typer.Typer) -> None:
    @app.command("import")
    def import_(
        map_id: str = typer.Argument(..., metavar="MAP", help="Target map (created if --create)."),
        file: Path = typer.Argument(
            ..., help="GeoJSON FeatureCollection of marking centroids (WGS84), or a GeoPackage (.gpkg) of "
            "Points in any CRS; - reads GeoJSON from standard input."),
        create: bool = typer.Option(False, "--create", help="Create the map if it does not exist."),
        comment: str = typer.Option("", "--comment", help="Comment for the edit log."),
        progress: bool | None = PROGRESS_OPTION,
    ) -> None:
        """Import markings from GeoJSON or a GeoPackage in one transaction: all of them or none."""
        # Parse and check everything before touching the database.
        name = source_name(file)
        with progress_bar(progress, None, "feature", f"read {name}") as bar:
            items = read_markings(file, progress=follow(bar))
        store = Store()
        if create and not any(m.id == map_id for m in store.list_maps()):
            store.create_map(map_id)
        with progress_bar(progress, len(items), "marking", f"import {map_id}") as bar:
            ids = store.add_markings(map_id, items, who="cli", comment=comment or f"import {name}",
                                     lonlat=True, progress=follow(bar))  # fmt: skip
        typer.echo(f"imported {len(ids)} markings into {map_id}")

    @app.command("export")
    def export(
        map_id: str = typer.Argument(..., metavar="MAP"),
        file: Path = typer.Argument(
            ..., help="Output .geojson (WGS84) or .gpkg (storage CRS); - writes GeoJSON to standard output."),
        status: str | None = typer.Option(
            None, "--status", metavar="STATUS,...",
            help="Only markings with these review statuses (unreviewed, accepted, rejected), e.g. "
            "'accepted,unreviewed' for the markings the localizer uses."),
        bbox: str | None = typer.Option(
            None, "--bbox", metavar="MINLON,MINLAT,MAXLON,MAXLAT",
            help="Only markings whose centroid lies in this box (WGS84 degrees)."),
        progress: bool | None = PROGRESS_OPTION,
    ) -> None:
        """Export a map's markings to GeoJSON or GeoPackage: all of them, or those --status and
        --bbox select."""
        stdout = is_stdio(file)
        suffix = ".geojson" if stdout else file.suffix.lower()
        if suffix not in (".geojson", ".json", ".gpkg"):
            fail(f"cannot export to {file.name}: use a .geojson or .gpkg file name")
        try:
            statuses = parse_statuses(status)
        except ValueError as exc:
            fail(f"--{exc}")
        box = bbox_option(bbox)
        store = Store()
        info = store.get_map(map_id)
        if suffix == ".gpkg" and info.crs is None:
            fail(f"map {map_id} is empty and has no CRS yet")
        total = store.count_markings(map_id, statuses, box)
        with progress_bar(progress, total, "marking", f"export {map_id}") as bar:
            items = counted(store.iter_markings(map_id, statuses=statuses, lonlat_box=box), bar)
            if stdout:
                n = write_geojson_stream(sys.stdout, items)
            elif suffix == ".gpkg":
                n = write_gpkg(file, items, info.crs)
            else:
                n = write_geojson(file, items)
        # On standard output the GeoJSON is the output; the count goes with the messages.
        typer.echo(f"exported {n} markings to {'standard output' if stdout else file}", err=stdout)

    @app.command("from-lanelet2")
    def from_lanelet2(
        osm: Path = typer.Argument(..., help="Lanelet2 map (OSM XML)."),
        out: Path = typer.Argument(..., help="Output GeoJSON of marking centroids."),
        crs: str = typer.Option("EPSG:25832", "--crs", help="Metric CRS used to lay out dashes."),
        dash: float = typer.Option(3.0, "--dash", help="Dash length, m."),
        gap: float = typer.Option(6.0, "--gap", help="Gap length, m."),
        piece: float = typer.Option(3.0, "--piece", help="Longest solid-line piece, m."),
    ) -> None:
        """Lay a Lanelet2 map's lane markings out as centroid markings (GeoJSON)."""
        lmap = read_lanelet2(osm, crs=crs)
        items = layout_markings(lmap, dash_m=dash, gap_m=gap, piece_m=piece)
        from mapbuilder.crs import to_wgs84

        lon, lat = to_wgs84(crs).transform([m.x for m in items], [m.y for m in items])
        for m, a, b in zip(items, lon, lat):
            m.lon, m.lat = float(a), float(b)
        n = write_geojson(out, items)
        typer.echo(f"wrote {n} markings to {out}")


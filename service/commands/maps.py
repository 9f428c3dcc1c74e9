"""``lanemap maps``: create, list, show, summarise, retitle and delete maps, and prune their change feeds."""

from __future__ import annotations

import json

import typer

from mapbuilder.store import Store

COVERAGE_HELP = ("How far the map speaks for the ground, for localization at its edge: hull (everything painted "
                 "within its markings' convex hull is in it: an area mapped whole), markings (only the ground "
                 "between them: a route, or parts of a city whose streets go on unmapped) or imagery (the ground "
                 "its builds imaged, and the ground between its markings beyond it: a map built from imagery).")


def register(app: typer.Typer) -> None:
    maps = typer.Typer(help="Create, list, show, retitle and delete maps.", no_args_is_help=True)

    @maps.command("list")
    def list_(as_json: bool = typer.Option(False, "--json", help="Print JSON.")) -> None:
        """List the maps with their CRS and number of markings."""
        infos = Store().list_maps()
        if as_json:
            typer.echo(json.dumps([_info_dict(i) for i in infos], indent=2))
            return
        if not infos:
            typer.echo("no maps")
            return
        typer.echo(f"{'id':24} {'crs':12} {'markings':>9}  title")
        for i in infos:
            typer.echo(f"{i.id:24} {i.crs or '-':12} {i.count:>9}  {i.title}")

    @maps.command("create")
    def create(
        map_id: str = typer.Argument(..., metavar="MAP", help="Map id (letters, digits, . _ -)."),
        title: str = typer.Option("", "--title", help="Human-readable title."),
        crs: str = typer.Option(
            None, "--crs", help="Metric storage CRS, e.g. EPSG:25832. Default: the UTM zone of the first import."
        ),
        coverage: str = typer.Option(None, "--coverage", metavar="hull|markings|imagery",
                                     help=COVERAGE_HELP + " Default: as the server is set (LANEMAP_MAP_COVERAGE); "
                                          "imagery from the map's first build on."),
    ) -> None:
        """Create an empty map."""
        from ..cli_io import coverage_option

        coverage_option(coverage)
        info = Store().create_map(map_id, title, crs, coverage)
        typer.echo(f"created map {info.id} ({info.crs or 'CRS chosen at the first import or build'})")

    @maps.command("show")
    def show(map_id: str = typer.Argument(..., metavar="MAP")) -> None:
        """Print a map's metadata as JSON."""
        typer.echo(json.dumps(_info_dict(Store().get_map(map_id, with_count=True)), indent=2))

    @maps.command("summary")
    def summary(
        map_id: str = typer.Argument(..., metavar="MAP"),
        bbox: str = typer.Option(None, "--bbox", metavar="MINLON,MINLAT,MAXLON,MAXLAT",
                                 help="Only inside this box (WGS84 minLon,minLat,maxLon,maxLat): a district."),
        as_json: bool = typer.Option(False, "--json", help="Print JSON."),
    ) -> None:
        """Count a map's markings by status, source and kind, and say how far its review has come."""
        from ..cli_io import bbox_option

        sm = Store().summary(map_id, bbox_option(bbox))
        if as_json:
            typer.echo(json.dumps(_summary_dict(map_id, sm), indent=2))
            return
        for line in _summary_lines(map_id, sm):
            typer.echo(line)

    @maps.command("update")
    def update(
        map_id: str = typer.Argument(..., metavar="MAP"),
        title: str = typer.Option(None, "--title", help="The map's new title."),
        coverage: str = typer.Option(None, "--coverage", metavar="hull|markings|imagery|default",
                                     help=COVERAGE_HELP + " default: as the server is set again "
                                     "(LANEMAP_MAP_COVERAGE)."),
    ) -> None:
        """Change a map's title or coverage (its id, CRS and markings stay)."""
        from ..cli_errors import fail
        from ..cli_io import coverage_option

        if title is None and coverage is None:
            fail("give --title, --coverage or both")
        coverage_option(coverage, "default")
        info = Store().update_map(map_id, title=title, coverage=None if coverage == "default" else coverage,
                                  set_coverage=coverage is not None)  # fmt: skip
        if coverage is not None:
            typer.echo(f"map {info.id}: coverage {info.coverage or 'as the server is set'}")
        if title is not None:
            typer.echo(f"map {info.id} is now titled {info.title!r}")

    @maps.command("coverage")
    def coverage_of(
        map_id: str = typer.Argument(..., metavar="MAP"),
        out: str = typer.Argument("-", metavar="OUT",
                                  help="GeoJSON file to write (- or none: standard output)."),
        coverage: str = typer.Option(None, "--coverage", metavar="hull|markings|imagery",
                                     help="Draw it by this coverage instead of the map's own (else "
                                     "LANEMAP_MAP_COVERAGE, else hull)."),
    ) -> None:
        """Write the ground a map speaks for, as localization draws it, as a GeoJSON Feature (WGS84)."""
        from mapbuilder.geojson import write_geojson_object

        from ..cli_errors import fail
        from ..cli_io import command_index, coverage_option, is_stdio, map_coverage
        from ..map_index import coverage_feature

        coverage_option(coverage)
        store = Store()
        info = store.get_map(map_id)
        if info.crs is None:
            fail(f"map {map_id!r} has no markings yet")
        coverage, revision = map_coverage(coverage, info.coverage), info.revision
        feature = coverage_feature(command_index(store, map_id, info.crs, coverage), map_id, coverage, revision)
        if is_stdio(out):
            typer.echo(json.dumps(feature))
            return
        write_geojson_object(out, feature)
        props = feature["properties"]
        typer.echo(f"map {map_id} at revision {revision}: coverage {coverage}, {props['area_m2'] / 1e6:,.3f} km² "
                   f"written to {out}")

    @maps.command("delete")
    def delete(
        map_id: str = typer.Argument(..., metavar="MAP"),
        yes: bool = typer.Option(False, "--yes", "-y", help="Do not ask for confirmation."),
    ) -> None:
        """Delete a map with its markings, history, imagery records and jobs."""
        from ..cli_io import kept_indexes

        store = Store()
        info = store.get_map(map_id, with_count=True)
        if not yes and not typer.confirm(f"delete map {map_id} and its {info.count} markings?"):
            raise typer.Exit(1)
        created = store.map_head(map_id).created
        store.delete_map(map_id)
        files = kept_indexes(store)
        if files is not None:
            files.forget(map_id, created)  # they hold the map's markings too
        typer.echo(f"deleted map {map_id}")

    @maps.command("prune-feed")
    def prune_feed(
        map_id: str | None = typer.Argument(None, metavar="MAP", show_default=False),
        older_than: float = typer.Option(..., "--older-than", min=0.0, metavar="DAYS",
                                         help="Forget the deletions recorded more than DAYS days ago."),
        every: bool = typer.Option(False, "--all", help="Prune every map's feed."),
    ) -> None:
        """Forget a map's old deletions from its change feed (a copy older than them reads the map whole).

        Every deletion is kept for the change feed until pruned: a map rebuilt
        often grows a row for each detection a rebuild replaces. Run it from cron
        with a horizon longer than any fleet goes without syncing, or let the
        server do it (``LANEMAP_FEED_RETENTION_DAYS``).
        """
        from datetime import datetime, timedelta, timezone

        if (map_id is None) == (not every):
            raise typer.BadParameter("name a MAP or give --all, not both", param_hint="MAP")
        cutoff = datetime.now(timezone.utc) - timedelta(days=older_than)
        store = Store()
        pruned = store.prune_all_removed(cutoff) if every else {map_id: store.prune_removed(map_id, cutoff)}
        for mid, (n, horizon) in pruned.items():
            typer.echo(f"map {mid}: {n:,} deletions forgotten; the change feed answers copies at revision "
                       f"{horizon} or later (older ones read the map whole)")
        if every and not pruned:
            typer.echo(f"no map recorded deletions more than {older_than:g} day{'' if older_than == 1 else 's'} ago")

    app.add_typer(maps, name="maps")


def _summary_dict(map_id: str, sm) -> dict:
    return {
        "id": map_id, "revision": sm.revision, "markings": sm.count,
        "by_status": sm.by_status, "by_source": sm.by_source, "by_kind": sm.by_kind,
        "detections": sm.detections, "reviewed_share": sm.reviewed_share,
        "unreviewed_scores": sm.unreviewed_scores,
    }  # fmt: skip


def _summary_lines(map_id: str, sm) -> list[str]:
    def counts(d: dict) -> str:
        return ", ".join(f"{k} {v:,}" for k, v in d.items()) or "none"

    lines = [f"map {map_id} at revision {sm.revision}: {sm.count:,} markings",
             f"  status  {counts(sm.by_status)}",
             f"  source  {counts(sm.by_source)}",
             f"  kind    {counts(sm.by_kind)}"]  # fmt: skip
    total = sum(sm.detections.values())
    if not total:
        return lines + ["  review  no detections"]
    left = sm.detections["unreviewed"]
    lines.append(f"  review  {total - left:,} of {total:,} detections reviewed ({100 * sm.reviewed_share:.1f} %): "
                 f"{sm.detections['accepted']:,} accepted, {sm.detections['rejected']:,} rejected, {left:,} to go")
    if left:
        lines.append("  unreviewed detections by score:")
        n, top = len(sm.unreviewed_scores), max(sm.unreviewed_scores)
        for k, c in enumerate(sm.unreviewed_scores):
            bar = "#" * (round(30 * c / top) if top else 0)
            lines.append(f"    {k / n:.1f}-{(k + 1) / n:.1f} {c:>9,}  {bar}")
    return lines


def _info_dict(i) -> dict:
    return {
        "id": i.id,
        "title": i.title,
        "crs": i.crs,
        "bounds": list(i.bounds) if i.bounds else None,
        "bounds_wgs84": list(i.bounds_wgs84()) if i.bounds else None,
        "markings": i.count,
        "revision": i.revision,
        "changes_since": i.feed_since,
        "coverage": i.coverage,
        "created_at": i.created_at.isoformat(),
        "updated_at": i.updated_at.isoformat(),
    }

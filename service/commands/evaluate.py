"""``lanemap evaluate``: how well a map agrees with surveyed (or rendered) true markings."""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer

from ..cli_errors import fail
from ..cli_io import PROGRESS_OPTION, follow, progress_bar, read_markings, source_name
from ..filters import parse_statuses

#: Exit code when the map misses --min-precision or --min-recall.
BELOW_TARGET = 3


def _summary(map_id: str, source: str, ev, width_m: float, height_m: float) -> list[str]:
    def share(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{v:.3f}"

    def cm(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{100 * v:.1f} cm"

    lines = [
        f"map {map_id} against {source} ({ev.n_true} true markings counted, "
        f"{width_m:.0f} m x {height_m:.0f} m):",
        f"  precision {share(ev.precision)}  ({ev.n_correct} of {ev.n_detected} markings of the map "
        "lie on a true one)",
        f"  recall    {share(ev.recall)}  ({ev.n_found} of {ev.n_true} true markings found)",
        f"  centroid error  {cm(ev.centroid_rmse_m)} RMS over {ev.centroid_errors_m.size} matched "
        "dashes, stop lines and other discrete markings",
        f"  across lines    {cm(ev.cross_track_rmse_m)} RMS over {ev.cross_track_m.size} markings "
        "on solid lines",
    ]
    for kind, d in ev.recall_by_kind().items():
        lines.append(f"  {kind:>10}: {d['found']} of {d['true']} found")
    return lines


def evaluate(
    map_id: str = typer.Argument(..., metavar="MAP"),
    truth: Path = typer.Argument(
        ..., metavar="TRUTH",
        help="True markings as GeoJSON (Points in WGS84 with length_m and bearing_deg, as "
        "'lanemap synth' and 'lanemap export' write them) or a GeoPackage (.gpkg) of Points in any CRS; "
        "- reads GeoJSON from standard input."),
    tolerance: float = typer.Option(0.3, "--tolerance", help="Largest centroid (or axis) distance of a "
                                    "match, metres."),
    border: float = typer.Option(
        0.0, "--border", help="Leave out markings this close to the edge of the truth's extent, metres."),
    status: str = typer.Option(
        "unreviewed,accepted", "--status", metavar="STATUS,...",
        help="The map's markings to score, by review status (default: those the localizer uses)."),
    as_json: bool = typer.Option(False, "--json", help="Print the figures as JSON."),
    errors: Path | None = typer.Option(
        None, "--errors", help="Write the map's false markings and the missed true ones to this "
        "GeoJSON file (property 'error': 'false' or 'missed'), to step through them in the web "
        "editor (review a list) or QGIS."),
    min_precision: float | None = typer.Option(
        None, "--min-precision", help=f"Exit with code {BELOW_TARGET} if precision is lower."),
    min_recall: float | None = typer.Option(
        None, "--min-recall", help=f"Exit with code {BELOW_TARGET} if recall is lower."),
    progress: bool | None = PROGRESS_OPTION,
) -> None:
    """Score MAP against true markings: precision, recall and centroid errors.

    The truth is taken as complete over its extent (the box around its
    markings): every marking of the map there should match one of it. A
    dash, stop line or stall line matches when the centroids are within
    --tolerance (one to one); a solid line is cut into pieces anywhere, so a
    marking on one is right when it lies within --tolerance of its axis.
    """
    from mapbuilder.evaluate import evaluate_map
    from mapbuilder.geojson import write_geojson
    from mapbuilder.store import Store

    if not (math.isfinite(tolerance) and tolerance > 0):
        fail(f"--tolerance must be a positive number of metres, got {tolerance}")
    if not (math.isfinite(border) and border >= 0):
        fail(f"--border must be a number of metres, 0 or more, got {border}")
    for name, v in (("--min-precision", min_precision), ("--min-recall", min_recall)):
        if v is not None and not 0 <= v <= 1:
            fail(f"{name} must be within [0, 1], got {v}")
    try:
        statuses = parse_statuses(status)
    except ValueError as exc:
        fail(f"--{exc}")
    source = source_name(truth)
    with progress_bar(progress, None, "feature", f"read {source}") as bar:
        true = read_markings(truth, progress=follow(bar))
    if not true:
        fail(f"{source} holds no markings")
    store = Store()
    try:
        with progress_bar(progress, None, "marking", f"read {map_id}") as bar:
            ev, bounds = evaluate_map(store, map_id, true, tolerance_m=tolerance, border_m=border,
                                      statuses=statuses, progress=follow(bar))  # fmt: skip
    finally:
        store.close()
    if errors is not None:
        write_geojson(errors, ev.error_markings())
    if as_json:
        figures = {"map": map_id, "truth": source, "tolerance_m": tolerance, "border_m": border,
                   "statuses": statuses, **ev.to_dict()}  # fmt: skip
        typer.echo(json.dumps(figures, indent=2))
    else:
        for line in _summary(map_id, source, ev, bounds[2] - bounds[0], bounds[3] - bounds[1]):
            typer.echo(line)
    below = [f"{name} {'n/a' if math.isnan(value) else f'{value:.3f}'} is below {target}"
             for name, value, target in
             (("precision", ev.precision, min_precision), ("recall", ev.recall, min_recall))
             if target is not None and not value >= target]  # fmt: skip
    if below:
        typer.echo(f"warning: {'; '.join(below)}", err=True)
        raise typer.Exit(BELOW_TARGET)


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate)

"""``lanemap localize``: localize a vehicle against a stored map."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from localizer import METHODS, GeoFrame, LocalizationInputError, MapIndex, Prior, localize
from service.cli_errors import fail


def load_observations(path: Path):
    """Observations from a JSON file: ``{"observations": [...]}`` or a bare list."""
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        fail(f"cannot read {path}: {exc.strerror or exc}")
    except json.JSONDecodeError as exc:
        fail(f"{path} is not valid JSON: {exc.msg} (line {exc.lineno})")
    if isinstance(data, dict):
        if "observations" not in data:
            fail(f"{path}: expected a list or an object with an 'observations' list")
        data = data["observations"]
    if not isinstance(data, list):
        fail(f"{path}: 'observations' must be a list of {{x, y, weight}} objects")
    return data


def register(app: typer.Typer) -> None:
    @app.command("localize")
    def localize_cmd(
        map_id: str = typer.Argument(..., metavar="MAP", help="Map id."),
        lat: float = typer.Option(..., "--lat", help="GPS latitude, degrees (WGS84)."),
        lon: float = typer.Option(..., "--lon", help="GPS longitude, degrees (WGS84)."),
        heading: float = typer.Option(
            ..., "--heading", help="GPS heading, degrees clockwise from true north."
        ),
        observations: Path = typer.Option(
            ..., "--observations", help="JSON file: {\"observations\": [{\"x\", \"y\", \"weight\"}]} "
            "in the vehicle frame (x forward, y left, metres).",
        ),
        method: str = typer.Option("default", "--method", help=f"One of: {', '.join(METHODS)}."),
        position_sigma: float = typer.Option(5.0, "--position-sigma", help="GPS position sigma, metres."),
        heading_sigma: float = typer.Option(10.0, "--heading-sigma", help="GPS heading sigma, degrees."),
    ) -> None:
        """Localize against MAP and print the pose as JSON (status ok, ambiguous or failed)."""
        from mapbuilder.store import Store

        obs = load_observations(observations)
        if method not in METHODS:
            fail(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
        store = Store()
        info = store.get_map(map_id)
        if info.crs is None:
            fail(f"map {map_id!r} has no markings yet")
        arrays = store.marking_arrays(map_id)
        try:
            bearing = None
            if len(arrays):
                # The store keeps bearings from true north; the index wants grid bearings.
                frame = GeoFrame(info.crs)
                lon0, lat0 = frame.to_lonlat(float(np.mean(arrays.x)), float(np.mean(arrays.y)))
                bearing = np.asarray(arrays.bearing_deg) - frame.convergence_deg(lon0, lat0)
            index = MapIndex.from_arrays(
                arrays.x, arrays.y, arrays.weight, info.crs,
                bearing_deg=bearing, length_m=arrays.length_m if bearing is not None else None,
            )
            prior = Prior(
                lat=lat, lon=lon, heading_deg=heading,
                position_sigma_m=position_sigma, heading_sigma_deg=heading_sigma,
            )
            pose = localize(index, obs, prior, method=method)
        except LocalizationInputError as exc:
            fail(str(exc))
        typer.echo(json.dumps(pose.to_dict(), indent=2, allow_nan=False))

"""``lanemap synth``: render a synthetic aerial GeoTIFF with known lane markings."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..cli_errors import fail


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.replace("x", ",").split(","))
    except ValueError:
        fail(f"{what} must be {n} numbers separated by commas, got {text!r}")
    if len(vals) != n:
        fail(f"{what} must be {n} numbers separated by commas, got {text!r}")
    return vals


def synth(
    out: Path = typer.Argument(
        ..., help="GeoTIFF to write; its true markings go beside it (out.tif: out.truth.geojson)."),
    lanelet2: Optional[Path] = typer.Option(
        None, "--lanelet2", help="Draw this Lanelet2 map (.osm) instead of a procedural scene."),
    bounds: Optional[str] = typer.Option(
        None, "--bounds", help="xmin,ymin,xmax,ymax of the area to draw, in the scene CRS, metres."),
    size: str = typer.Option("60,60", "--size", help="Procedural scene width,height in metres."),
    origin: str = typer.Option("500000,5400000", "--origin",
                               help="Lower-left corner of a procedural scene in the scene CRS."),
    scene_crs: str = typer.Option("EPSG:25832", "--scene-crs", help="Metric CRS of the scene."),
    crs: Optional[str] = typer.Option(None, "--crs", help="CRS of the image (default: the scene's)."),
    resolution: float = typer.Option(0.1, "--resolution", "-r", help="Metres per pixel (0.05–0.2 typical)."),
    seed: int = typer.Option(0, "--seed", help="Seed of layout, textures and sensor look."),
    jpeg: Optional[int] = typer.Option(None, "--jpeg", help="Write lossy JPEG tiles at this quality."),
    labels: Optional[Path] = typer.Option(None, "--labels", help="Also write a label GeoTIFF."),
    alpha: bool = typer.Option(False, "--alpha", help="Add an alpha band masking one corner."),
    nodata: Optional[int] = typer.Option(None, "--nodata", help="Nodata value; masks one corner."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Render a georeferenced synthetic aerial image and its true markings."""
    from mapbuilder.lanelet2 import read_lanelet2
    from mapbuilder.synth import procedural_scene, render

    if jpeg is not None and not 1 <= jpeg <= 100:
        fail(f"--jpeg must be within 1–100, got {jpeg}")
    b = _floats(bounds, 4, "--bounds") if bounds else None
    if b is not None and (b[2] <= b[0] or b[3] <= b[1]):
        fail(f"--bounds must be xmin,ymin,xmax,ymax with xmin < xmax and ymin < ymax, got {bounds}")
    try:
        if lanelet2 is not None:
            scene = read_lanelet2(lanelet2, crs=scene_crs)
        else:
            w, h = _floats(size, 2, "--size")
            ox, oy = _floats(origin, 2, "--origin")
            if b is not None:
                ox, oy, w, h = b[0], b[1], b[2] - b[0], b[3] - b[1]
                b = None
            scene = procedural_scene((w, h), origin=(ox, oy), crs=scene_crs, seed=seed)
        result = render(scene, out, resolution, crs=crs, seed=seed, bounds=b, jpeg_quality=jpeg,
                        labels_tif=labels, alpha=alpha, nodata=nodata, progress=progress)
    except ValueError as exc:
        fail(str(exc))
    h, w = result.shape
    typer.echo(f"wrote {result.path} ({w}x{h} px, {result.crs}) and {result.truth_path} "
               f"({len(result.markings)} markings)")


def register(app: typer.Typer) -> None:
    app.command("synth")(synth)

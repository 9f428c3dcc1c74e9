"""``lanemap train``: train a marking classifier from labelled imagery."""

from __future__ import annotations

from pathlib import Path

import typer

from ..cli_errors import fail


def train(
    image: Path = typer.Argument(..., help="Georeferenced RGB GeoTIFF (0.02–0.3 m/px)."),
    labels: Path = typer.Argument(
        ..., help="Markings as GeoJSON (points with length_m/width_m/bearing_deg, lines, "
                  "polygons; WGS84) or a label GeoTIFF aligned with IMAGE (non-zero = marking)."),
    out: Path = typer.Option(..., "--out", "-o", help="ONNX model to write."),
    C: float = typer.Option(0.5, "--C", help="SVM regularisation (larger: fit the pixels harder)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the pixel sampling."),
) -> None:
    """Train a marking model on IMAGE and LABELS; use it with: lanemap build --model."""
    from mapbuilder.train import train_from_files

    if C <= 0:
        fail(f"--C must be positive, got {C}")
    try:
        r = train_from_files(image, labels, out, C=C, seed=seed)
    except ValueError as exc:
        fail(str(exc))
    typer.echo(
        f"wrote {r.path}: {r.n_pixels} pixels ({r.n_positive} marking, "
        f"{r.candidate_recall:.0%} of the labelled ones); training precision "
        f"{r.train_precision:.3f}, recall {r.train_recall:.3f}")


def register(app: typer.Typer) -> None:
    app.command("train")(train)

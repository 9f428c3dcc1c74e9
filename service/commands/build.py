"""``lanemap build``: detect lane markings in aerial imagery and store them in a map."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import typer

from mapbuilder.build import BuildParams, build_map, default_threshold, default_threshold_low
from mapbuilder.cluster import ClusterParams

from ..cli_errors import fail

log = logging.getLogger(__name__)


def build(
    images: List[Path] = typer.Argument(..., help="GeoTIFF/COG aerial images (RGB or RGBA)."),
    map_id: str = typer.Option(..., "--map", "-m", help="Map to build into (created if missing)."),
    title: str = typer.Option("", help="Title of a newly created map."),
    model: Optional[Path] = typer.Option(
        None, "--model", help="ONNX marking model (default: the one shipped with lanemap)."
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", "-j", help="Local worker processes (default: all cores)."
    ),
    dask: Optional[str] = typer.Option(
        None, "--dask", help="Run tiles on this Dask scheduler (e.g. tcp://host:8786)."
    ),
    tile_px: int = typer.Option(2048, "--tile-size", help="Tile core size, pixels."),
    halo_m: float = typer.Option(4.0, "--halo", help="Halo around each tile, metres."),
    threshold: Optional[float] = typer.Option(
        None, help="Marking probability threshold (default: 0.2 with the shipped CNN "
        "verifier, the threshold it was trained at; 0.5 with --no-verify)."),
    threshold_low: Optional[float] = typer.Option(
        None, "--threshold-low",
        help="Hysteresis: pixels above this join a marking that has pixels above --threshold, "
        "so faint stretches and ends of a line stay with it (default: 0.05 with the shipped "
        "CNN verifier; off with --no-verify)."),
    hysteresis: bool = typer.Option(
        True, "--hysteresis/--no-hysteresis",
        help="--no-hysteresis keeps only the pixels above --threshold."),
    piece_m: float = typer.Option(
        3.0, "--piece-length", help="Long markings are cut into pieces of this length, metres."
    ),
    verify: bool = typer.Option(
        True, "--verify/--no-verify",
        help="Check each detected marking with the cluster verifier, a small CNN on an "
        "oriented crop around it (drops kerbs, lot borders and car outlines). --no-verify "
        "keeps every cluster the pixel classifier finds: faster, far more false detections.",
    ),
    verifier: Optional[Path] = typer.Option(
        None, "--verifier", help="ONNX cluster verifier (default: the one shipped with lanemap)."
    ),
    verify_threshold: float = typer.Option(
        ClusterParams.verify_threshold, "--verify-threshold",
        help="Verifier probability a marking needs to be kept: lower keeps more (recall), "
        "higher drops more (precision)."),
    continuation_min: float = typer.Option(
        ClusterParams.verify_continuation_min, "--continuation-min",
        help="Verifier probability a rejected piece of a line needs to be kept because it "
        "continues a kept one: lower takes back more of what the verifier doubts, kerbs "
        "included; at or above --verify-threshold, none."),
    restart: bool = typer.Option(
        False, "--restart", help="Start afresh instead of resuming an unfinished build."
    ),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
    quicklook: Optional[Path] = typer.Option(
        None, "--quicklook", metavar="PNG",
        help="Also save the map's markings over the images, downsampled, as this PNG."),
    quicklook_px: int = typer.Option(3000, "--quicklook-size", min=64, max=20000,
                                     help="Longest side of the quicklook, pixels."),
) -> None:
    """Detect lane markings in IMAGES and store them in the map MAP.

    A rebuild replaces the map's detected, unreviewed markings of these images
    and keeps every marking a person added, accepted or rejected. A build that
    was interrupted resumes from the tiles already done when run again with
    the same map, images and parameters.
    """
    from mapbuilder.classify import ModelError
    from mapbuilder.store import Store

    try:
        if threshold is None:
            threshold = default_threshold(verify, verifier)
        if threshold_low is None and hysteresis:
            threshold_low = default_threshold_low(verify, verifier, threshold)
    except ModelError as exc:
        fail(str(exc))
    if not hysteresis and threshold_low is not None:
        fail("--threshold-low and --no-hysteresis contradict each other; drop one")
    try:
        params = BuildParams(
            tile_px=tile_px,
            halo_m=halo_m,
            model=str(model) if model is not None else None,
            cluster=ClusterParams(threshold=threshold, threshold_low=threshold_low,
                                  max_length_m=piece_m, verify=verify,
                                  verify_threshold=verify_threshold,
                                  verify_continuation_min=continuation_min),
            verifier=str(verifier) if verifier is not None else None,
        )
    except ValueError as exc:
        fail(str(exc))
    store = Store()
    try:
        result = build_map(
            store,
            map_id,
            [str(p) for p in images],
            params,
            workers=workers,
            dask_address=dask,
            progress=progress,
            resume=not restart,
            title=title,
        )
        typer.echo(result.summary())
        if quicklook is not None:
            if progress:  # seconds, for a city's imagery: say what is happening
                typer.echo(f"drawing the quicklook {quicklook} ...", err=True)
            _save_quicklook(store, map_id, [str(p) for p in images], quicklook, quicklook_px)
    except ValueError as exc:
        fail(str(exc))
    finally:
        store.close()


def _save_quicklook(store, map_id: str, images: list[str], path: Path, max_px: int) -> None:
    from mapbuilder.quicklook import map_quicklook

    try:
        look = map_quicklook(store, map_id, images, path, max_px=max_px, title=f"map {map_id}")
    except OSError as exc:
        fail(f"cannot write {path}: {exc.strerror or exc}")
    typer.echo(f"quicklook: {look.path} ({look.shape[1]} x {look.shape[0]} px, {look.resolution_m:.2f} m per pixel)")


def register(app: typer.Typer) -> None:
    app.command("build")(build)

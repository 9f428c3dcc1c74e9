"""``lanemap localize``: localize a vehicle against a stored map."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import typer

from localizer import METHODS, ErrorEllipse, LocalizationInputError, Options, Prior, localize, warm_up
from localizer.robust import along_across_sigmas
from service.cli_errors import fail
from service.cli_io import command_index, coverage_option, is_stdio, map_coverage
from service.map_index import MIN_PROBABILITY_RANGE, localize_options

#: Exit codes of ``lanemap localize`` by the answer's status (the last frame's
#: with ``--frames``). The JSON is printed whatever the status, so a script can
#: read the hypotheses or the reason; the code lets a shell script tell a sure
#: answer from one it must not act on without reading further. Bad input is 1
#: (as for every command) and a usage error 2 (Click's).
EXIT_CODES = {"ok": 0, "ambiguous": 3, "failed": 4}
#: Seconds of silence before ``lanemap localize`` says that it is compiling:
#: loading the cached kernels takes under a second on an idle machine, but
#: took over 2 s once on a machine busy with two other processes.
COMPILE_NOTE_AFTER_S = 4.0


def _ready_kernels() -> None:
    """Load the localizer's compiled kernels; on a first run, compiling them, say so.

    Compiling takes about 15 s once per installation (then numba's cache
    answers in under a second): a first run should not look hung.
    """
    import threading

    note = threading.Timer(COMPILE_NOTE_AFTER_S, lambda: typer.echo(
        "note: compiling the localizer (the first run after an installation; about 15 s, then cached)",
        err=True))  # fmt: skip
    note.daemon = True
    note.start()
    try:
        warm_up()
    finally:
        note.cancel()


def _read_json(path: Path):
    stdin = is_stdio(path)
    name = "standard input" if stdin else str(path)
    try:
        return json.load(sys.stdin) if stdin else json.loads(path.read_text())
    except OSError as exc:
        fail(f"cannot read {name}: {exc.strerror or exc}")
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        reason = f"{exc.msg} (line {exc.lineno})" if isinstance(exc, json.JSONDecodeError) else "not UTF-8 text"
        fail(f"{name} is not valid JSON: {reason}")


def load_observations(path: Path):
    """Observations from a JSON file: ``{"observations": [...]}`` or a bare list."""
    data = _read_json(path)
    if isinstance(data, dict):
        if "observations" not in data:
            fail(f"{path}: expected a list or an object with an 'observations' list")
        data = data["observations"]
    if not isinstance(data, list):
        fail(f"{path}: 'observations' must be a list of {{x, y, weight}} objects")
    return data


def parse_ellipse(text: str) -> ErrorEllipse:
    """``MAJOR,MINOR,ORIENTATION`` (metres, metres, degrees clockwise from true north)."""
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    if len(values) != 3:
        fail(f"--position-ellipse takes MAJOR,MINOR,ORIENTATION (three numbers), got {text!r}")
    return ErrorEllipse(*values)


def load_state(path: Path):
    """A drive's :class:`localizer.TrackState` from the JSON file ``--state`` wrote."""
    from localizer import TrackState

    try:
        return TrackState.from_dict(_read_json(path))
    except LocalizationInputError as exc:
        fail(f"{path}: not a drive's state: {exc}")


def save_state(path: Path, state: dict) -> None:
    """Write ``state`` to ``path`` whole or not at all (a temporary file renamed over it)."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(json.dumps(state, indent=1, allow_nan=False) + "\n")
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        fail(f"cannot write the drive's state to {path}: {exc.strerror or exc}")


def load_frames(path: Path, continuing: bool = False):
    """Frames from a JSON file: ``{"frames": [{"observations": [...], "motion": {...}}, ...]}``.

    ``motion`` is the odometry since the previous frame in the previous vehicle
    frame: ``dx`` metres forward, ``dy`` metres left, ``dyaw_deg`` degrees
    counter-clockwise (a left turn is positive); the first frame's is ignored,
    unless the frames ``continuing`` a drive (then it is the odometry since the
    drive's last frame, and required).
    """
    from localizer.track import Frame

    data = _read_json(path)
    frames = data.get("frames") if isinstance(data, dict) else data
    if not isinstance(frames, list) or not frames:
        fail(f"{path}: expected a non-empty 'frames' list")
    out = []
    for k, f in enumerate(frames):
        if not isinstance(f, dict) or not isinstance(f.get("observations"), list):
            fail(f"{path}: frames[{k}] needs an 'observations' list")
        m = f.get("motion") or {}
        if not isinstance(m, dict) or ((k > 0 or continuing) and not {"dx", "dy"} <= set(m)):
            fail(f"{path}: frames[{k}].motion needs 'dx' and 'dy' (metres) and optionally 'dyaw_deg'")
        try:
            motion = (float(m.get("dx", 0.0)), float(m.get("dy", 0.0)), np.radians(float(m.get("dyaw_deg", 0.0))))
        except (TypeError, ValueError):
            fail(f"{path}: frames[{k}].motion values must be numbers")
        out.append(Frame(f["observations"], motion))
    return out


def register(app: typer.Typer) -> None:
    @app.command("localize")
    def localize_cmd(
        map_id: str = typer.Argument(..., metavar="MAP", help="Map id."),
        lat: float | None = typer.Option(
            None, "--lat", help="GPS latitude, degrees (WGS84). --lat, --lon and --heading are "
            "required unless --state continues a drive."),
        lon: float | None = typer.Option(None, "--lon", help="GPS longitude, degrees (WGS84)."),
        heading: float | None = typer.Option(
            None, "--heading", help="GPS heading, degrees clockwise from true north."
        ),
        observations: Path = typer.Option(
            None, "--observations", help="JSON file: {\"observations\": [{\"x\", \"y\", \"weight\"}]} "
            "in the vehicle frame (x forward, y left, metres); - reads standard input.",
        ),
        frames: Path = typer.Option(
            None, "--frames", help="JSON file of consecutive frames with odometry, oldest first: "
            "{\"frames\": [{\"observations\": [...], \"motion\": {\"dx\", \"dy\", \"dyaw_deg\"}}]}; "
            "the GPS fix is the first frame's. Prints the pose of every frame. - reads standard input.",
        ),
        state_file: Path = typer.Option(
            None, "--state", help="With --frames: a file holding where the drive's filter stands. If it "
            "exists, the frames continue that drive (the first frame's motion is the odometry since its last "
            "frame; the GPS options are then optional, a newer fix); the new state is written to it.",
        ),
        method: str = typer.Option("default", "--method", help=f"One of: {', '.join(METHODS)}."),
        position_sigma: float | None = typer.Option(
            None, "--position-sigma", help=f"GPS position sigma, metres (default {Prior.position_sigma_m:g})."),
        position_ellipse: str | None = typer.Option(
            None, "--position-ellipse", metavar="MAJOR,MINOR,ORIENTATION",
            help="GPS error ellipse instead of --position-sigma: the sigmas along its major and minor axes "
            "(metres) and the major axis's direction (degrees clockwise from true north), as NMEA GST gives them.",
        ),
        heading_sigma: float = typer.Option(10.0, "--heading-sigma", help="GPS heading sigma, degrees."),
        min_probability: float | None = typer.Option(
            None, "--min-probability", help="Posterior probability an answer needs to be ok, "
            f"{MIN_PROBABILITY_RANGE[0]}-{MIN_PROBABILITY_RANGE[1]} "
            f"(default {Options().ambiguity_probability}); below it the answer is ambiguous (default method). "
            "An answer whose camera sees beyond the map's edge stays ambiguous at any threshold.",
        ),
        coverage: str | None = typer.Option(
            None, "--coverage", metavar="hull|markings|imagery",
            help="How far the map speaks for the ground, for the check at its edge: hull (its markings' convex "
            "hull: an area mapped whole), markings (the ground between them: a route, or parts of a city "
            "whose streets go on unmapped) or imagery (the ground its builds imaged, and the ground between "
            "its markings beyond it). Default: the map's own coverage, else LANEMAP_MAP_COVERAGE as "
            "for the server, else hull.",
        ),
    ) -> None:
        """Localize against MAP and print the pose as JSON (status ok, ambiguous or failed).

        Exits 0 when the answer is ok, 3 when it is ambiguous and 4 when
        localization failed (the JSON is printed in every case; with --frames
        the last frame decides), 1 on bad input.

        With --frames, a drive of several frames is localized with the
        multi-hypothesis filter of localizer.track (default method only);
        with --state, a long drive is sent a few frames at a time.
        """
        from mapbuilder.store import Store

        if (observations is None) == (frames is None):
            fail("give either --observations (one frame) or --frames (a sequence)")
        if state_file is not None and frames is None:
            fail("--state continues a drive: it works with --frames only")
        state = load_state(state_file) if state_file is not None and state_file.exists() else None
        gps_given = [v is not None for v in (lat, lon, heading)]
        if any(gps_given) and not all(gps_given):
            fail("give --lat, --lon and --heading together")
        if not all(gps_given) and state is None:
            fail("give the GPS fix: --lat, --lon and --heading"
                 + (f" (the drive's state file {state_file} does not exist yet)" if state_file else ""))
        seq = load_frames(frames, continuing=state is not None) if frames is not None else None
        obs = load_observations(observations) if observations is not None else None
        if method not in METHODS:
            fail(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
        coverage_option(coverage)
        if seq is not None and method != "default":
            fail("--frames works with the default method only")
        if min_probability is not None:
            if method != "default":
                fail("--min-probability works with the default method only (pink2008 has no probability)")
            lo, hi = MIN_PROBABILITY_RANGE
            if not lo <= min_probability <= hi:
                fail(f"--min-probability must be between {lo} and {hi}, got {min_probability}")
        ellipse = None
        if position_ellipse is not None:
            if position_sigma is not None:
                fail("give --position-sigma or --position-ellipse, not both")
            ellipse = parse_ellipse(position_ellipse)
        options = localize_options(min_probability)
        store = Store()
        info = store.get_map(map_id)
        if info.crs is None:
            fail(f"map {map_id!r} has no markings yet")
        coverage = map_coverage(coverage, info.coverage)
        _ready_kernels()
        try:
            index = command_index(store, map_id, info.crs, coverage)
            # Without --position-sigma the fix takes the library's default sigma.
            sigma = {} if position_sigma is None else {"position_sigma_m": position_sigma}
            prior = None if lat is None else Prior(
                lat=lat, lon=lon, heading_deg=heading, heading_sigma_deg=heading_sigma,
                position_ellipse=ellipse, **sigma,
            )
            if seq is not None:
                from localizer.track import localize_sequence

                result = localize_sequence(index, seq, prior, options=options, state=state)
                out = {"poses": [p.to_dict() for p in result.poses], "tracks": result.tracks,
                       "state": result.state.to_dict()}
                if state_file is not None:
                    save_state(state_file, out["state"])
                last_pose = result.poses[-1]
            else:
                last_pose = localize(index, obs, prior, method=method, options=options)
                out = last_pose.to_dict()
        except LocalizationInputError as exc:
            fail(str(exc))
        typer.echo(json.dumps(out, indent=2, allow_nan=False))
        status = last_pose.status
        if status == "failed":
            typer.echo(f"error: localization failed: {last_pose.reason or 'no reason given'}", err=True)
        elif status == "ambiguous":
            typer.echo(
                f"warning: the answer is ambiguous (probability {last_pose.probability or 0:.3f}); "
                f"{len(last_pose.hypotheses)} hypotheses in the JSON{_spread(last_pose)}"
                + (f"; {last_pose.reason}" if last_pose.reason else ""),
                err=True,
            )
        raise typer.Exit(EXIT_CODES[status])


def _spread(pose) -> str:
    """How far apart an ambiguous answer's hypotheses leave it along and across its heading."""
    if pose.mixture_covariance is None:
        return ""
    along, across = along_across_sigmas(pose.mixture_covariance, pose.yaw_grid_rad)
    return f"; with them, the position is known to ±{along:.2f} m along the heading and ±{across:.2f} m across it"

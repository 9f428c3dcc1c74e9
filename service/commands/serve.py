"""``lanemap serve``: run the HTTP API under uvicorn.

With ``--workers N`` (N > 1) on Linux, N server processes each listen on their
own ``SO_REUSEPORT`` socket on the same address, so the kernel spreads
connections over them; a parent process supervises them (see
:mod:`service.multiprocess` for what happens when one ends). Elsewhere uvicorn's
own multiprocess mode (one shared socket) is used.
"""

from __future__ import annotations

import socket

import typer

from ..cli_errors import fail


def _check_port(host: str, port: int) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            fail(f"cannot listen on {host}:{port}: {exc.strerror or exc}")


def _share_metrics(workers: int) -> None:
    """Give the server processes one directory to count metrics in (see :mod:`service.metrics`).

    Set before they start, so that each imports prometheus_client in its
    multiprocess mode. A directory the operator names in
    ``PROMETHEUS_MULTIPROC_DIR`` is made if missing and emptied of an earlier
    run's counts, whatever the number of processes; otherwise, for more than
    one, a fresh one is made and removed when the server stops.
    """
    import atexit
    import glob
    import os
    import shutil
    import tempfile

    from ..settings import PROMETHEUS_MULTIPROC_ENV as MULTIPROC_ENV

    # This runs before service.metrics is imported: its import already writes a count file.
    given = os.environ.get(MULTIPROC_ENV)
    if given:
        os.makedirs(given, exist_ok=True)
        for path in glob.glob(os.path.join(given, "*.db")):
            os.remove(path)
        return
    if workers == 1:
        return
    path = tempfile.mkdtemp(prefix="lanemap-metrics-")
    os.environ[MULTIPROC_ENV] = path
    atexit.register(shutil.rmtree, path, ignore_errors=True)


def _announcer(log_format: str, logs: dict):
    """How the server says where it listens: printed lines, or records of the JSON log
    configured by ``logs`` (so that a log collector reads every line the server writes as JSON)."""
    if log_format != "json":
        return lambda line, err=False: typer.echo(line, err=err)
    import logging.config

    logging.config.dictConfig(logs)
    log = logging.getLogger("service.serve")
    return lambda line, err=False: log.info("%s", line)


def register(app: typer.Typer) -> None:
    @app.command("serve")
    def serve(
        host: str = typer.Option("127.0.0.1", help="Address to listen on."),
        port: int = typer.Option(8000, min=0, max=65535, help="Port to listen on."),
        demo: bool = typer.Option(False, "--demo", help="Create the Karlsruhe demo map on first start."),
        workers: int = typer.Option(1, min=1, max=64, envvar="LANEMAP_WORKERS", help="Server processes."),
        log_level: str = typer.Option("info", help="uvicorn log level."),
    ) -> None:
        """Serve the REST API (OGC API Features, builds, tiles, localization)."""
        _share_metrics(workers)
        import uvicorn

        from mapbuilder.settings import Settings as StoreSettings
        from mapbuilder.store import Store

        from .. import multiprocess
        from ..app import create_app
        from ..logs import log_config
        from ..settings import ServiceSettings, ensure_token_file, parse_tokens, token_path

        settings = ServiceSettings()
        store_settings = StoreSettings()
        data_dir = store_settings.data_dir.resolve()
        _check_port(host, port)
        sockets = None
        if workers > 1 and multiprocess.reuseport_supported():
            # Bound before the demo map is made, so that a busy port fails at once.
            try:
                sockets = multiprocess.bind_reuseport(host, port, workers)
            except OSError as exc:
                fail(f"cannot listen on {host}:{port}: {exc.strerror or exc}")
            port = sockets[0].getsockname()[1]
        store = Store(store_settings.resolved_database_url())
        token_note = None
        if not parse_tokens(settings.api_tokens):
            token, created = ensure_token_file(data_dir)
            token_note = (
                f"write token ({'generated, ' if created else ''}kept in {token_path(data_dir)}): {token}"
            )
        logs = log_config(settings.log_format)
        say = _announcer(settings.log_format, logs)
        if demo:
            from ..demo import ensure_demo

            say("preparing the demo map (first start takes a little while)...", err=True)
            info = ensure_demo(store, data_dir)
            state = "created" if info.created else "found"
            say(f"demo map {info.map_id} {state}: {info.markings} markings", err=True)
        base = f"http://{'[' + host + ']' if ':' in host else host}:{port}"
        say(f"lanemap API:  {base}/")
        say(f"API docs:     {base}/docs")
        say(f"map editor:   {base}/editor/")
        if demo:
            say(f"demo map:     {base}/collections/karlsruhe/items")
            say(f"localize:     POST {base}/collections/karlsruhe/localize "
                "(an example body: docs/examples/frame.json in the repository)")
        say(token_note or "write tokens: from LANEMAP_API_TOKENS")
        if workers == 1:
            uvicorn.run(create_app(store=store, settings=settings, data_dir=data_dir), host=host, port=port,
                        log_level=log_level, log_config=logs)  # fmt: skip
        elif sockets is not None:
            store.close()
            config = uvicorn.Config("service.app:app_from_env", factory=True, host=host, port=port,
                                    log_level=log_level, log_config=logs)  # fmt: skip
            try:
                multiprocess.serve(config, sockets)
            except multiprocess.WorkerStartError as exc:
                fail(str(exc))
        else:
            store.close()
            uvicorn.run("service.app:app_from_env", factory=True, host=host, port=port, workers=workers,
                        log_level=log_level, log_config=logs)  # fmt: skip

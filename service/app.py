"""The FastAPI application: OGC API Features over the map store, builds, tiles, localization.

Create it with :func:`create_app`; ``lanemap serve`` runs it under uvicorn.
Routes are thin: every piece of work is done by :mod:`mapbuilder` and
:mod:`localizer`.
"""

from __future__ import annotations

import gc
import logging
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from mapbuilder.settings import Settings as StoreSettings
from mapbuilder.store import Store

from . import problems
from .deps import Context
from .middleware import BodyGuard, HeadAsGet
from .request_id import RequestId
from .settings import ServiceSettings, Token, resolve_tokens

log = logging.getLogger(__name__)

EDITOR_DIR = Path(__file__).resolve().parent / "static" / "editor"
#: Routes that read their own body under limits of their own (uploads, imports), past the JSON body guard.
STREAM_PATHS = r"^/collections/[^/]+/(imagery|import)/?$"

API_DESCRIPTION = """\
Lane-marking maps as OGC API Features (Part 1 Core, Part 4 editing), atomic
changesets with history and revert, imagery upload and map builds, imagery
tiles, and vehicle localization against a map.

Reads are open unless the server requires a token; every write needs
`Authorization: Bearer <token>`. Errors are RFC 9457 `application/problem+json`.
"""


def create_app(
    store: Store | None = None,
    settings: ServiceSettings | None = None,
    data_dir: Path | None = None,
    tokens: list[Token] | None = None,
    *,
    run_jobs: bool = True,
) -> FastAPI:
    """Build the application.

    Parameters
    ----------
    store : Store, optional
        Default: the store of ``LANEMAP_DATABASE_URL`` (or the SQLite file in
        the data folder).
    settings : ServiceSettings, optional
        Default: from ``LANEMAP_*`` environment variables.
    data_dir : Path, optional
        Where uploads and the token live; default ``LANEMAP_DATA_DIR``.
    tokens : list of Token, optional
        Write tokens; default ``LANEMAP_API_TOKENS`` or the stored token.
    run_jobs : bool
        Start build jobs in worker processes (off: jobs stay ``accepted``).
    """
    settings = settings or ServiceSettings()
    store_settings = StoreSettings()
    data_dir = Path(data_dir or store_settings.data_dir).resolve()
    store = store or Store(store_settings.resolved_database_url())
    tokens = tokens if tokens is not None else resolve_tokens(settings, data_dir)
    if not tokens:
        log.warning("no write token configured: every write will be refused")

    from .index_cache import IndexCache
    from .index_files import index_files
    from .jobs import JobRunner

    ctx = Context(store=store, settings=settings, data_dir=data_dir, tokens=tokens,
                  indexes=IndexCache(store, settings.map_coverage, settings.index_background_from,
                                     files=index_files(settings, data_dir, store.engine.url),
                                     process_from=settings.index_process_from))
    if run_jobs:
        ctx.jobs = JobRunner(store, data_dir, workers=settings.build_workers,
                             dask_address=settings.dask_scheduler or None,
                             dask_timeout_s=settings.dask_timeout_s)  # fmt: skip

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Compiled on first use otherwise: the first localization would wait seconds.
        import localizer

        log.info("localizer kernels ready in %.2f s", localizer.warm_up())
        # What the process holds at start (numba, the libraries, the app: some
        # 200,000 objects) lives as long as the process. Left to the collector,
        # every full collection scans it all, about 0.1 s with the GIL held,
        # and each localization waiting meanwhile waits as long. Frozen, a
        # full collection scans only what requests made since.
        gc.collect()
        gc.freeze()
        log.info("%d objects of the start frozen out of the garbage collector's scans", gc.get_freeze_count())
        if settings.index_preload:
            try:
                preloading = await anyio.to_thread.run_sync(ctx.indexes.preload)
            except Exception as exc:  # noqa: BLE001 - the server starts without: indexes build on first use
                log.warning("the maps' localization indexes are built at first use: listing the maps failed: %s",
                            exc)  # fmt: skip
            else:
                if preloading:
                    log.info("building the localization indexes of %d maps in the background", len(preloading))
        if ctx.jobs is not None:
            ctx.jobs.start()
        pruner = None
        if settings.feed_retention_days is not None:
            from .retention import FeedPruner

            pruner = FeedPruner(store, settings.feed_retention_days, settings.feed_prune_interval_s)
            pruner.start()
        try:
            yield
        finally:
            if pruner is not None:
                pruner.stop()
            if ctx.jobs is not None:
                ctx.jobs.stop()
            ctx.indexes.close()

    app = FastAPI(
        title="lanemap",
        version="0.1.0",
        description=API_DESCRIPTION,
        lifespan=lifespan,
        openapi_tags=[
            {"name": "Capabilities", "description": "Landing page and conformance (OGC API Common)"},
            {"name": "Maps", "description": "Maps as OGC API Features collections"},
            {"name": "Features", "description": "Markings: read (Part 1) and edit (Part 4)"},
            {"name": "Changesets", "description": "Atomic multi-feature edits, history, revert"},
            {"name": "Imagery", "description": "Imagery upload and basemap tiles"},
            {"name": "Jobs", "description": "Map builds (OGC API Processes job status)"},
            {"name": "Localization", "description": "Vehicle pose from observed markings"},
            {"name": "Health", "description": "Database reachable, schema revision, version"},
        ],
    )
    app.state.ctx = ctx
    problems.install(app)
    from .openapi import document_problems

    document_problems(app)

    from . import metrics
    from .routers import changes, changesets, collections, evaluate, health, imagery, jobs, landing, localize

    for module in (landing, collections, changes, changesets, imagery, jobs, localize, evaluate, health, metrics):
        app.include_router(module.router)

    if EDITOR_DIR.is_dir():
        app.mount("/editor", StaticFiles(directory=EDITOR_DIR, html=True), name="editor")

    # Outermost first: CORS must also answer for requests the body guard refuses.
    app.add_middleware(BodyGuard, max_bytes=settings.max_body_bytes, stream_paths=STREAM_PATHS)
    # Outside the body guard (its refusals count), inside HEAD-as-GET (whose copy
    # of the request is the one the router labels with its route).
    app.add_middleware(metrics.RequestMetrics)
    app.add_middleware(HeadAsGet)
    origins = settings.cors_origin_list()
    if origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"],
            allow_headers=["Authorization", "Content-Type", "If-Match", "If-None-Match", "X-Request-ID"],
            expose_headers=["ETag", "Location", "Link", "X-Request-ID", "X-Map-Revision"],
        )
    # Outermost: every answer carries its ID, a CORS preflight's and a refused body's too.
    app.add_middleware(RequestId)
    return app


def app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory service.app:app_from_env`` (used with several workers)."""
    return create_app()

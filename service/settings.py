"""Settings of the HTTP service, read from ``LANEMAP_*`` environment variables.

The database URL and the data folder are the store's
(:class:`mapbuilder.settings.Settings`); this module holds what only the web
service needs: API tokens, CORS and request limits.
"""

from __future__ import annotations

import logging
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from mapbuilder.settings import Settings as StoreSettings

log = logging.getLogger(__name__)

#: Name of the file in the data folder that keeps the generated write token.
TOKEN_FILE = "api-token"
#: prometheus_client's variable for its multiprocess mode: the folder in which
#: every server process counts its metrics (``service.metrics``).
PROMETHEUS_MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
#: How far a map speaks for the ground (``mapbuilder.store.MAP_COVERAGES``): the server's
#: setting and the API's member.
MapCoverage = Literal["hull", "markings", "imagery"]


class IndexDirSettings(BaseSettings):
    """Where built localization indexes are kept (:mod:`service.index_files`): the server's and
    ``lanemap localize``'s, which reads only these.

    Attributes
    ----------
    index_dir : str
        ``LANEMAP_INDEX_DIR``: where built localization indexes of large maps
        are kept for the next process that needs them (``lanemap localize``,
        a server worker that starts; :mod:`service.index_files`). Empty:
        ``<data_dir>/indexes``; ``off``: none are kept.
    index_dir_from : int
        ``LANEMAP_INDEX_DIR_FROM``: the fewest markings of an index that is
        kept (a smaller map's builds in milliseconds).
    index_dir_max_mb : int
        ``LANEMAP_INDEX_DIR_MAX_MB``: beyond this, the least recently used
        kept indexes are deleted (an index of 1,000,000 markings takes about
        110 MB).
    """

    model_config = SettingsConfigDict(env_prefix="LANEMAP_", extra="ignore")

    index_dir: str = ""
    index_dir_from: int = Field(10_000, ge=1)
    index_dir_max_mb: int = Field(2048, ge=1)

    def index_directory(self, data_dir: Path) -> Path | None:
        """Where built indexes are kept (``index_dir``); None: nowhere."""
        value = self.index_dir.strip()
        if value.lower() == "off":
            return None
        return Path(value) if value else Path(data_dir) / "indexes"


class ServiceSettings(IndexDirSettings):
    """Service options.

    Attributes
    ----------
    api_tokens : str
        ``LANEMAP_API_TOKENS``: comma-separated bearer tokens that may write.
        An entry ``name=token`` records ``name`` as the author of edits made
        with that token. Empty: ``serve`` generates one token at first start and
        keeps it in ``<data_dir>/api-token``.
    read_tokens : str
        ``LANEMAP_READ_TOKENS``: comma-separated bearer tokens that may only
        read (``name=token`` entries too): for vehicles and tools that
        localize and fetch maps, on a server whose reads need a token. A
        write with one answers 403. A token may not be in both lists.
    read_token_required : bool
        ``LANEMAP_READ_TOKEN_REQUIRED=1``: reads need a token too (a read
        token or a write token).
    cors_origins : str
        ``LANEMAP_CORS_ORIGINS``: comma-separated origins allowed to call the
        API from a browser (``*`` for any).
    max_body_bytes : int
        Largest JSON request body, bytes.
    max_upload_bytes : int
        Largest imagery upload, bytes.
    max_import_bytes : int
        Largest GeoJSON body of an import (``POST /collections/{id}/import``),
        bytes. It is read a feature at a time and written in one transaction; at
        its peak an import holds its body as text and about 470 bytes per marking
        (a body of 256 MB, 1,000,000 markings, raised a server's memory by 737 MB).
    items_default_limit, items_max_limit : int
        Page sizes of ``/collections/{mapId}/items``.
    max_observations : int
        Most observations one localization request (or one frame of a drive)
        may carry.
    max_drive_observations : int
        Most observations one drive request may carry over all its frames: a
        frame costs up to about 0.2 s of CPU where nothing matches, so this
        bounds what one request can take of a worker's localization thread.
    localize_max_pending : int
        Localizations one server process takes on at once, running or waiting
        for a thread; beyond that it answers 503 with ``Retry-After`` at once
        instead of queueing (a vehicle is better served by a quick refusal
        than by a pose seconds old). At about 20 ms per localization, 8 pending
        mean up to about 160 ms of waiting per process. 0: no limit.
    build_workers : int
        Build jobs that run at the same time (each in its own process); imports sent with
        ``Prefer: respond-async`` run one at a time beside them.
    dask_scheduler : str
        ``LANEMAP_DASK_SCHEDULER``: address of a Dask distributed scheduler
        (``tcp://host:8786``). Set: build jobs run their tiles on that cluster
        (its workers must read the imagery at the same paths as the server).
        Empty: in local worker processes.
    dask_timeout_s : float
        How long a build tries to reach the scheduler, seconds.
    health_timeout_s : float
        How long ``/health`` waits for the database, seconds.
    feed_retention_days : float or None
        ``LANEMAP_FEED_RETENTION_DAYS``: the server forgets deletions older
        than this from every map's change feed (:mod:`service.retention`); a
        copy older than that reads its map whole. Unset: deletions are kept
        until ``lanemap maps prune-feed``.
    feed_prune_interval_s : float
        How often the server prunes the feeds when a retention is set, seconds.
    map_coverage : {"hull", "markings", "imagery"}
        ``LANEMAP_MAP_COVERAGE``: how far a map that does not say (its
        ``coverage``) speaks for the ground, for the localizer's check at a
        map's edge (:func:`localizer.index.map_extent`): ``hull``, the convex
        hull of its markings (maps of an area surveyed whole), or ``markings``,
        the ground between them (maps of routes or of separate parts of a
        city, whose streets go on unmapped inside that hull), or ``imagery``,
        the ground its builds imaged and the ground between its markings
        beyond it (maps built from imagery).
    index_background_from : int
        ``LANEMAP_INDEX_BACKGROUND_FROM``: a map of at least this many
        markings goes on answering localizations from its previous index while
        the index of its newest revision is built (the answer's
        ``X-Map-Revision`` names the one used); a smaller map's requests wait
        for the build, milliseconds. 0: every map.
    index_process_from : int
        ``LANEMAP_INDEX_PROCESS_FROM``: the index of a map of at least this
        many markings is built in a child process and handed over through its
        kept file (``LANEMAP_INDEX_DIR``; in the server's own process where
        that is ``off``), so that the build neither holds the server's
        localizations (up to 0.8 s at a time for 1,000,000 markings) nor
        grows its memory.
    index_preload : bool
        ``LANEMAP_INDEX_PRELOAD``: at start, build the localization index of
        every map with markings in the background, so that no map's first
        vehicle waits for it (seconds for a city's map). Off: each map's index
        is built at its first localization.
    log_format : {"text", "json"}
        ``LANEMAP_LOG_FORMAT``: the server's log as uvicorn's text lines, or
        as one JSON object per line for a log collector (:mod:`service.logs`).
    """

    model_config = SettingsConfigDict(env_prefix="LANEMAP_", extra="ignore")

    api_tokens: str = ""
    read_tokens: str = ""
    read_token_required: bool = False
    cors_origins: str = ""
    max_body_bytes: int = Field(16 * 1024 * 1024, ge=1)
    max_upload_bytes: int = Field(2 * 1024 * 1024 * 1024, ge=1)
    max_import_bytes: int = Field(256 * 1024 * 1024, ge=1)
    items_default_limit: int = Field(100, ge=1)
    items_max_limit: int = Field(10_000, ge=1)
    max_observations: int = Field(500, ge=1)
    max_drive_observations: int = Field(5_000, ge=1)
    localize_max_pending: int = Field(8, ge=0)
    build_workers: int = Field(1, ge=1)
    dask_scheduler: str = ""
    dask_timeout_s: float = Field(20.0, gt=0, allow_inf_nan=False)
    health_timeout_s: float = Field(2.0, gt=0, allow_inf_nan=False)
    feed_retention_days: float | None = Field(None, gt=0, allow_inf_nan=False)
    feed_prune_interval_s: float = Field(3600.0, gt=0, allow_inf_nan=False)
    index_background_from: int = Field(10_000, ge=0)
    index_preload: bool = True
    index_process_from: int = Field(200_000, ge=1)
    log_format: Literal["text", "json"] = "text"
    map_coverage: MapCoverage = "hull"

    @field_validator("feed_retention_days", mode="before")
    @classmethod
    def _empty_is_unset(cls, value):
        # Compose passes an unset variable on as an empty one.
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("read_tokens")
    @classmethod
    def _read_tokens_do_not_write(cls, value: str, info: ValidationInfo) -> str:
        writes = {t.secret for t in parse_tokens(info.data.get("api_tokens", ""))}
        if any(t.secret in writes for t in parse_tokens(value)):
            raise ValueError("a token is in LANEMAP_API_TOKENS too: a read token must differ from every write token")
        return value

    def cors_origin_list(self) -> list[str]:
        return [o.strip() for o in self.cors_origins.split(",") if o.strip()]


@dataclass(frozen=True)
class Token:
    """A bearer token the server takes: its secret, the name edits are recorded under,
    and whether it may write (``LANEMAP_API_TOKENS``) or only read (``LANEMAP_READ_TOKENS``)."""

    secret: str
    who: str
    write: bool = True


def parse_tokens(text: str, write: bool = True) -> list[Token]:
    """Parse ``LANEMAP_API_TOKENS`` or ``LANEMAP_READ_TOKENS`` (``token`` or ``name=token``
    entries, comma-separated); ``write`` says which."""
    out = []
    for entry in text.split(","):
        entry = entry.strip()
        if not entry:
            continue
        name, sep, secret = entry.partition("=")
        if sep and name.strip() and secret.strip():
            out.append(Token(secret.strip(), name.strip(), write))
        else:
            out.append(Token(entry, "api" if write else "reader", write))
    return out


def token_path(data_dir: Path) -> Path:
    return Path(data_dir) / TOKEN_FILE


def read_token_file(data_dir: Path) -> str | None:
    path = token_path(data_dir)
    try:
        text = path.read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        return None
    return text or None


def ensure_token_file(data_dir: Path) -> tuple[str, bool]:
    """Return the stored write token, generating it (file mode 0600) if there is none.

    Returns
    -------
    token : str
    created : bool
        True when the token was generated by this call.
    """
    existing = read_token_file(data_dir)
    if existing:
        return existing, False
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    path = token_path(data_dir)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(token + "\n")
    os.chmod(path, 0o600)
    log.info("generated a write token in %s", path)
    return token, True


def resolve_tokens(settings: ServiceSettings, data_dir: Path) -> list[Token]:
    """The tokens the server takes: those that may write (``LANEMAP_API_TOKENS``, else the
    stored one, if any), then those that may only read (``LANEMAP_READ_TOKENS``)."""
    tokens = parse_tokens(settings.api_tokens)
    if not tokens:
        stored = read_token_file(data_dir)
        tokens = [Token(stored, "api")] if stored else []
    return tokens + parse_tokens(settings.read_tokens, write=False)


def store_settings() -> StoreSettings:
    return StoreSettings()

"""Settings shared by every part, read from ``LANEMAP_*`` environment variables."""

from __future__ import annotations

from pathlib import Path

from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Store and file locations.

    Attributes
    ----------
    database_url : str or None
        ``LANEMAP_DATABASE_URL``: an SQLAlchemy URL. ``sqlite:///path.sqlite`` or
        ``postgresql://user@host/db``. Unset: an SQLite file in ``data_dir``.
    data_dir : Path
        ``LANEMAP_DATA_DIR``: where the default database, uploaded imagery and
        job files live. Default ``./lanemap-data``.
    """

    model_config = SettingsConfigDict(env_prefix="LANEMAP_", extra="ignore")

    database_url: str | None = None
    data_dir: Path = Path("lanemap-data")

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'lanemap.sqlite').resolve()}"

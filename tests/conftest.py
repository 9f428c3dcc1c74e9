"""Shared fixtures: real databases and the shared third-party data.

``db_url`` runs a test against a fresh SQLite file and a fresh database on a
real PostgreSQL server. The server is the one at ``LANEMAP_TEST_POSTGRES_URL``
(default ``postgresql://postgres:postgres@127.0.0.1:5432/postgres``), which
``scripts/test.sh`` installs and starts; if it cannot be reached the tests fail.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
KARLSRUHE_OSM = SHARED_DATA / "karlsruhe-lanelet2" / "mapping_example.osm"
USGS_DIR = SHARED_DATA / "usgs-hro-colorado"

POSTGRES_ADMIN_URL = os.environ.get(
    "LANEMAP_TEST_POSTGRES_URL", "postgresql://postgres:postgres@127.0.0.1:5432/postgres"
)


def _psycopg_url(url: str) -> str:
    return url.replace("postgresql://", "postgresql+psycopg://", 1)


@pytest.fixture(scope="session")
def postgres_admin():
    """An engine on the PostgreSQL server's admin database (autocommit)."""
    engine = create_engine(_psycopg_url(POSTGRES_ADMIN_URL), isolation_level="AUTOCOMMIT")
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # noqa: BLE001 - turn any connection failure into a clear failure
        pytest.fail(
            f"PostgreSQL is not reachable at {POSTGRES_ADMIN_URL} ({exc.__class__.__name__}); "
            "run the tests with scripts/test.sh, which installs and starts it",
            pytrace=False,
        )
    yield engine
    engine.dispose()


@pytest.fixture
def postgres_url(postgres_admin):
    """URL of a fresh, empty PostgreSQL database, dropped after the test."""
    name = f"lanemap_test_{uuid.uuid4().hex[:12]}"
    with postgres_admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    base = POSTGRES_ADMIN_URL.rsplit("/", 1)[0]
    yield f"{base}/{name}"
    with postgres_admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))


@pytest.fixture
def sqlite_url(tmp_path):
    return f"sqlite:///{tmp_path / 'lanemap.sqlite'}"


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    """A fresh database of each kind: the same test runs on SQLite and PostgreSQL."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'lanemap.sqlite'}"
    return request.getfixturevalue("postgres_url")


@pytest.fixture
def store(db_url):
    from mapbuilder.store import Store

    s = Store(db_url)
    yield s
    s.close()


@pytest.fixture(scope="session")
def karlsruhe_markings():
    """Markings laid out from the real Karlsruhe Lanelet2 map (EPSG:25832)."""
    from mapbuilder.lanelet2 import layout_markings, read_lanelet2

    return layout_markings(read_lanelet2(KARLSRUHE_OSM, crs="EPSG:25832"))

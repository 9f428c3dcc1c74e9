"""``lanemap db``: the database schema."""

from __future__ import annotations

import typer

from mapbuilder import migrate
from mapbuilder.store import Store


def register(app: typer.Typer) -> None:
    db = typer.Typer(help="Database schema (Alembic migrations).", no_args_is_help=True)

    @db.command("upgrade")
    def upgrade(revision: str = typer.Argument("head", help="Target revision.")) -> None:
        """Apply schema migrations up to REVISION (default: the newest)."""
        store = Store(upgrade=False)
        before, after = store.upgrade(revision)
        typer.echo(f"schema {before or '(empty)'} -> {after}")

    @db.command("current")
    def current() -> None:
        """Print the database's schema revision and the one this lanemap needs."""
        store = Store(upgrade=False)
        typer.echo(f"database: {store.schema_revision() or '(empty)'}  required: {migrate.head_revision()}")

    app.add_typer(db, name="db")

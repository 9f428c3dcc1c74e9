"""``lanemap db``: the database schema."""

from __future__ import annotations

import typer

from mapbuilder import migrate
from mapbuilder.store import Store

from ..cli_io import PROGRESS_OPTION, progress_bar


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

    @db.command("copy")
    def copy(
        target: str = typer.Argument(..., metavar="TARGET_URL",
                                     help="An empty database: postgresql://user:password@host/db or sqlite:///file"),
        source: str = typer.Option(None, "--from", metavar="SOURCE_URL",
                                   help="The database to copy; default LANEMAP_DATABASE_URL (or the SQLite file "
                                        "in LANEMAP_DATA_DIR)"),
        progress: bool | None = PROGRESS_OPTION,
    ) -> None:
        """Copy every map, marking, edit, changeset and job into an empty database, ids kept.

        From SQLite to PostgreSQL as a deployment grows, or to an SQLite file as a backup
        that is one consistent snapshot. A copy that fails leaves the target empty.
        Imagery files stay where they are.
        """
        from pathlib import Path

        from sqlalchemy.engine import make_url

        from mapbuilder.dbcopy import copy_database
        from mapbuilder.settings import Settings

        url = make_url(source or Settings().resolved_database_url())
        if url.get_backend_name() == "sqlite" and not Path(url.database or "").is_file():
            raise ValueError(f"no database at {url.database}: nothing to copy")
        src = Store(url.render_as_string(hide_password=False), upgrade=False)
        src.check_schema()
        dst = Store(target)
        with progress_bar(progress, None, "row", "copy") as bar:
            def moved(table: str, done: int, total: int) -> None:
                if done == 0:
                    bar.reset(total=total)
                    bar.set_description(f"copy {table}")
                bar.update(done - bar.n)

            report = copy_database(src, dst, progress=moved)
        counts = ", ".join(f"{report.rows[t]:,} {t}" for t in ("maps", "markings", "changesets", "edits", "jobs"))
        typer.echo(f"copied {counts} to {dst.display_url} in {report.seconds:.1f} s")

    app.add_typer(db, name="db")

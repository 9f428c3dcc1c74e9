"""The ``lanemap`` command.

Feature commands live in :mod:`service.commands`, one module each with a
``register(app)`` function. Any error derived from ``ValueError`` or ``OSError``
that escapes a command is reported as one line on stderr with exit code 1; a
traceback is shown only with ``LANEMAP_DEBUG=1``.
"""

from __future__ import annotations

import importlib
import logging
import os
import pkgutil
import sys

import typer

from . import commands

app = typer.Typer(
    name="lanemap",
    help="Lane-marking maps from aerial imagery, and vehicle localization against them.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


def _register_all() -> None:
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)


_register_all()


def main() -> None:
    """Entry point of the ``lanemap`` console script."""
    try:
        app()
    except (ValueError, OSError) as exc:
        if os.environ.get("LANEMAP_DEBUG"):
            raise
        typer.echo(f"error: {exc or exc.__class__.__name__}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()

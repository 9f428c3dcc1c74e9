"""The ``lanemap`` command.

Feature commands live in :mod:`service.commands`, one module each with a
``register(app)`` function; :data:`COMMAND_MODULES` says which module holds
which command, so that a command line imports only its own. Any error
derived from ``ValueError`` or ``OSError`` that escapes a command is reported
as one line on stderr with exit code 1 (a settings error names its
``LANEMAP_`` variable); a traceback is shown only with ``LANEMAP_DEBUG=1``.
"""

from __future__ import annotations

import importlib
import logging
import os
import pkgutil
import sys
from collections.abc import Iterable

import typer

from . import commands

#: The module of :mod:`service.commands` that registers each top-level command.
#: ``main`` imports only the one a command line names: the localizer, for one,
#: takes half a second to import that ``lanemap maps list`` need not wait for.
COMMAND_MODULES = {
    "build": "build",
    "db": "db",
    "evaluate": "evaluate",
    "export": "exchange",
    "from-lanelet2": "exchange",
    "import": "exchange",
    "localize": "localize",
    "maps": "maps",
    "review": "review",
    "serve": "serve",
    "synth": "synth",
    "train": "train",
}


def _print_version(value: bool) -> None:
    if value:
        from . import package_version

        typer.echo(f"lanemap {package_version()}")
        raise typer.Exit()


def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the installed version and exit."),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


def make_app(modules: Iterable[str] | None = None) -> typer.Typer:
    """The ``lanemap`` app with the commands of ``modules`` (names in
    :mod:`service.commands`; every command module when None)."""
    cli = typer.Typer(
        name="lanemap",
        help="Lane-marking maps from aerial imagery, and vehicle localization against them.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    cli.callback()(_root)
    if modules is None:
        modules = [info.name for info in pkgutil.iter_modules(commands.__path__)]
    for name in sorted(modules):
        register = getattr(importlib.import_module(f"{commands.__name__}.{name}"), "register", None)
        if register is not None:
            register(cli)
    return cli


def _named_module(args: list[str]) -> str | None:
    """The command module of the command ``args`` names, if it is one of ours."""
    first = next((a for a in args if not a.startswith("-")), None)
    return COMMAND_MODULES.get(first) if first is not None else None


def __getattr__(name: str):
    # ``service.cli.app``: every command, built on first use (tests and embedding code).
    if name == "app":
        globals()["app"] = built = make_app()
        return built
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:
    """Entry point of the ``lanemap`` console script."""
    module = _named_module(sys.argv[1:])
    if module is None and "--version" in sys.argv[1:]:
        modules: list[str] | None = []  # the version needs no command
    else:
        modules = None if module is None else [module]
    try:
        rc = make_app(modules)(prog_name="lanemap", standalone_mode=False)
    except typer.TyperException as exc:  # what Click calls a ClickException: a usage error, mostly
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group named alone shows its help
            exc.show()
            sys.exit(exc.exit_code)
        # A usage error is one line too: what is wrong, and where the command's help is.
        ctx = getattr(exc, "ctx", None)
        where = f"; see '{ctx.command_path} --help'" if ctx is not None else ""
        typer.echo(f"error: {exc.format_message().rstrip('.')}{where}", err=True)
        sys.exit(exc.exit_code)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(1)
    except (ValueError, OSError) as exc:
        if os.environ.get("LANEMAP_DEBUG"):
            raise
        from pydantic import ValidationError

        from .cli_errors import validation_error_line

        message = validation_error_line(exc) if isinstance(exc, ValidationError) else exc
        typer.echo(f"error: {message or exc.__class__.__name__}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        rc = 130
    if rc == 130:  # Ctrl+C: Typer answers it with exit code 130, silently
        typer.echo("interrupted", err=True)
    sys.exit(rc if isinstance(rc, int) else 0)


if __name__ == "__main__":
    main()

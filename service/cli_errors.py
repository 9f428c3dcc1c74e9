"""How the CLI reports a failure: one line on stderr, a non-zero exit code."""

from __future__ import annotations

from typing import TYPE_CHECKING, NoReturn

import typer

if TYPE_CHECKING:
    from pydantic import ValidationError


def fail(message: str, code: int = 1) -> NoReturn:
    """Print ``error: <message>`` to stderr and exit with ``code``."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _short(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def validation_error_line(exc: ValidationError) -> str:
    """One line for a pydantic validation error; a settings model's fields are named as the
    environment variables they are read from (``LANEMAP_MAX_OBSERVATIONS``)."""
    from pydantic_settings import BaseSettings

    from mapbuilder.settings import Settings

    from .settings import ServiceSettings

    prefixes = {
        cls.__name__: cls.model_config.get("env_prefix", "")
        for cls in (Settings, ServiceSettings)
        if issubclass(cls, BaseSettings)
    }
    prefix = prefixes.get(exc.title)
    parts = []
    for err in exc.errors():
        loc = err.get("loc") or ()
        if prefix is not None and loc:
            where = f"{prefix}{str(loc[0]).upper()}"
        else:
            where = ".".join(map(str, loc)) or exc.title
        if where.endswith("_TOKENS"):
            parts.append(f"{where}: {err['msg']}")  # the value is a secret
        else:
            parts.append(f"{where}: {err['msg']} (got {_short(err.get('input'))})")
    return "; ".join(parts)

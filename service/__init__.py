"""The lanemap service: the HTTP API and the ``lanemap`` command."""

from importlib import metadata


def package_version() -> str:
    """The installed ``lanemap`` distribution's version (``0+unknown`` when not installed)."""
    try:
        return metadata.version("lanemap")
    except metadata.PackageNotFoundError:
        return "0+unknown"

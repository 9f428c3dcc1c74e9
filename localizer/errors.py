"""Exceptions raised by the localizer."""

from __future__ import annotations


class LocalizationInputError(ValueError):
    """An input to the localizer is malformed (the message names the field and problem)."""

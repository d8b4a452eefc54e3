"""Errors that the CLI turns into a one-paragraph message instead of a traceback."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input: the message names the file or option and the fix."""


class MissingInputError(FileNotFoundError):
    """A required file or folder is absent: the message names it and the fix."""

"""Errors that the CLI turns into a one-paragraph message instead of a traceback."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input: the message names the file or option and the fix."""


class MissingInputError(FileNotFoundError):
    """A required file or folder is absent: the message names it and the fix."""


class UselessOutputError(InputError):
    """A stage found mid-run that its output would be useless (e.g. a segmenter
    that finds nothing): the chain deletes that key's partial artifact, so the
    rerun after the fix starts clean. The message names the likely causes."""


class UnknownImageError(InputError, KeyError):
    """An image name the scene or field does not have (e.g. `--image`)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""

"""Errors the command line reports as one line (exit code 2) instead of a traceback.

They live here, not in ``deform.cli``: ``python -m deform.cli`` runs that module as ``__main__``,
so a class defined there would be a different class from the one other modules import.
"""


class UsageError(ValueError):
    """Arguments or inputs that cannot be used; the message names the file or option."""


class CheckpointError(ValueError):
    """A model file that is missing, not a DEFORM checkpoint, or one of another model; the message
    names the file."""

"""Exceptions that mean "the user asked for something that cannot be done".

The CLI prints these as one clear line and exits with status 2 instead of a traceback.
Everything else is a bug and keeps its traceback.
"""


class LcrlError(Exception):
    """Base class for user-facing errors (bad input, missing files, bad configuration)."""

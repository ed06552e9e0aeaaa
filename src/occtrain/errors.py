"""User-facing errors: one line that names the file or key and what to do."""

from __future__ import annotations


class OcctrainError(Exception):
    """An error caused by the user's input (a file, a key, an argument).

    The CLI prints ``error: <message>`` on one line and exits non-zero, with no
    traceback. The message must name the offending file or key and say what to do.
    """


class DataError(OcctrainError):
    """A dataset, shard or prediction file is missing, corrupt or malformed."""


class ConfigError(OcctrainError):
    """A config file or command-line override is invalid."""

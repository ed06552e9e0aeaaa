"""User-facing errors: one line that names the file or key and what to do."""

from __future__ import annotations

import difflib


class OcctrainError(Exception):
    """An error caused by the user's input (a file, a key, an argument).

    The CLI prints ``error: <message>`` on one line and exits non-zero, with no
    traceback. The message must name the offending file or key and say what to do.
    """


class DataError(OcctrainError):
    """A dataset, shard or prediction file is missing, corrupt or malformed."""


class ConfigError(OcctrainError):
    """A config file or command-line override is invalid."""


def cause_line(err: BaseException) -> str:
    """``Type: first line`` of what went wrong behind ``err``.

    A wrapper whose first line only introduces its cause (huggingface_hub's
    ``StrictDataclassClassValidationError``: "Class validation error for validator
    'validate_architecture':", the ValueError that says why on later lines and in
    ``__cause__``) is followed to that cause: the line a person needs is the reason, not
    the validator's name.
    """
    line = _first_line(err)
    while line.endswith(":") and err.__cause__ is not None:
        err = err.__cause__
        line = _first_line(err)
    return f"{type(err).__name__}: {line}" if line else type(err).__name__


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else ""


def did_you_mean(key: str, valid: list[str]) -> str:
    """The end of an error about an unknown ``key``: the closest valid one, or all of them."""
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(sorted(valid))}"

"""Check a JSON value against a declared Python type; each mismatch is a message naming its key path.

Understood: ``Any``, ``bool``, ``int`` (not bool), ``float`` (int or float; not bool, NaN or
infinity), ``str``, ``None``, ``list[X]``, ``dict[str, X]``, ``Union``/``Optional``,
``Literal``, TypedDict classes (``__required_keys__``; ``NotRequired``/``total=False``
keys may be absent; unknown extra keys are allowed) and ``Annotated[X, Len(n)]`` for a
list of exactly ``n`` items.

    >>> problems({"a": [1, "2"]}, dict[str, list[int]], "")
    ['a[1] is the string "2", expected an integer']
"""

from __future__ import annotations

import json
import math
import types
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import (
    Annotated,
    Any,
    Literal,
    NotRequired,
    Protocol,
    Required,
    Union,
    get_args,
    get_origin,
    get_type_hints,
    is_typeddict,
)


@dataclass(frozen=True)
class Len:
    """``Annotated[list[X], Len(n)]``: the list holds exactly ``n`` items."""

    n: int


class _Enough(Exception):
    """Raised inside the walk once ``limit`` problems are found."""


def problems(value: Any, tp: Any, where: str = "", limit: int | None = None) -> list[str]:
    """Every way ``value`` differs from ``tp`` (at most ``limit``), each as ``<key path> is ..., expected ...``.

    ``where`` is the key path of ``value`` itself ("" for a file's top level).
    """
    found: list[str] = []
    try:
        _walk(value, tp, where, found, limit)
    except _Enough:
        pass
    return found


def first_problem(value: Any, tp: Any, where: str = "") -> str | None:
    """The first mismatch of ``value`` against ``tp``, or None when it conforms."""
    found = problems(value, tp, where, limit=1)
    return found[0] if found else None


def key_path(where: str, key: str | int) -> str:
    """``where.key`` for an object key, ``where[i]`` for a list index."""
    if isinstance(key, int):
        return f"{where}[{key}]"
    return f"{where}.{key}" if where else key


# ----------------------------------------------------------------------------- the walk
# Two passes: a predicate compiled once per type says whether a value conforms (fast, no
# key paths; a real annotations.json holds millions of numbers), and only a subtree that
# does not is walked again to word its problems.


def _is_number(v: Any) -> bool:
    # bool is an int subclass; a JSON true is never a number here.
    return type(v) is int or (type(v) is float and math.isfinite(v))


def _len_of(meta: tuple) -> int | None:
    return next((m.n for m in meta if isinstance(m, Len)), None)


@cache
def _ok(tp: Any) -> Callable[[Any], bool]:
    """A predicate: does a value conform to ``tp``?"""
    origin, args = get_origin(tp), get_args(tp)
    if tp is Any:
        return lambda v: True
    if origin in (Required, NotRequired):
        return _ok(args[0])
    if origin is Annotated:
        inner, n = _ok(args[0]), _len_of(args[1:])
        return inner if n is None else (lambda v: isinstance(v, list) and len(v) == n and inner(v))
    if tp is None or tp is type(None):
        return lambda v: v is None
    if tp is float:
        return _is_number
    if tp in (int, str, bool):
        return lambda v: type(v) is tp
    if origin is Literal:
        # (type, value) pairs: JSON true must not pass for 1, nor 1.0 for 1
        allowed = frozenset((type(a), a) for a in args)
        return lambda v: isinstance(v, (str, int)) and (type(v), v) in allowed
    if origin in (Union, types.UnionType):
        members = [_ok(a) for a in args]
        return lambda v: any(m(v) for m in members)
    if origin is list:
        item = _ok(args[0])
        return lambda v: isinstance(v, list) and all(map(item, v))
    if origin is dict:
        item = _ok(args[1])
        return lambda v: isinstance(v, dict) and all(map(item, v.values()))
    if is_typeddict(tp):
        fields, required = _fields(tp)
        checks = [(k, _ok(h)) for k, h in fields.items()]

        def conforms(v: Any) -> bool:
            return isinstance(v, dict) and required.issubset(v) and all(k not in v or ok(v[k]) for k, ok in checks)

        return conforms
    raise TypeError(f"validate: unsupported type {tp!r}")  # a schema bug, not a user error


class _TypedDictClass(Protocol):
    """What a TypedDict class has that ``type`` does not declare."""

    __required_keys__: frozenset[str]


@cache
def _fields(tp: _TypedDictClass) -> tuple[dict[str, Any], frozenset[str]]:
    """A TypedDict's field types and required keys."""
    hints = get_type_hints(tp, include_extras=True)
    # Under `from __future__ import annotations`, Python 3.11 files NotRequired[...] fields
    # in __required_keys__ (it cannot see through the string), so the qualifiers decide.
    required = {
        k
        for k, h in hints.items()
        if get_origin(h) is Required or (get_origin(h) is not NotRequired and k in tp.__required_keys__)
    }
    return hints, frozenset(required)


def _add(found: list[str], limit: int | None, message: str) -> None:
    found.append(message)
    if limit is not None and len(found) >= limit:
        raise _Enough


def _walk(value: Any, tp: Any, where: str, found: list[str], limit: int | None) -> None:
    """Word the problems of ``value`` against ``tp`` (nothing when it conforms)."""
    if _ok(tp)(value):
        return
    origin, args = get_origin(tp), get_args(tp)
    if origin in (Required, NotRequired):
        return _walk(value, args[0], where, found, limit)
    here = where or "the top level"
    if origin is Annotated:
        n = _len_of(args[1:])
        if n is not None and isinstance(value, list) and len(value) != n:
            return _add(found, limit, f"{here} holds {_items(len(value))}, expected {expected(tp)}")
        if get_origin(args[0]) is list and not isinstance(value, list):
            return _add(found, limit, f"{here} is {describe(value)}, expected {expected(tp)}")  # with its length
        return _walk(value, args[0], where, found, limit)
    if origin in (Union, types.UnionType):
        others = [a for a in args if a is not type(None)]
        if len(others) == 1 and value is not None:  # Optional[X]: X's own words name the deeper key
            return _walk(value, others[0], where, found, limit)
    elif origin is list and isinstance(value, list):
        for i, v in enumerate(value):
            _walk(v, args[0], key_path(where, i), found, limit)
        return
    elif origin is dict and isinstance(value, dict):
        for k, v in value.items():
            _walk(v, args[1], key_path(where, k), found, limit)
        return
    elif is_typeddict(tp) and isinstance(value, dict):
        fields, required = _fields(tp)
        for key, field in fields.items():
            if key in value:
                _walk(value[key], field, key_path(where, key), found, limit)
            elif key in required:
                _add(found, limit, f"{key_path(where, key)} is missing, expected {expected(field)}")
        return
    _add(found, limit, f"{here} is {describe(value)}, expected {expected(tp)}")


# ----------------------------------------------------------------------------- words


def describe(value: Any) -> str:
    """What a JSON value is, in words: ``a string``, ``NaN``, ``a list of 2 items``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"the integer {value}"
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return f"the number {value:g}"
    if isinstance(value, str):
        shown = value if len(value) <= 24 else value[:21] + "..."
        return f"the string {json.dumps(shown)}"
    if isinstance(value, list):
        return f"a list of {_items(len(value))}"
    if isinstance(value, dict):
        return "an object"
    return f"a {type(value).__name__}"


def _items(n: int) -> str:
    return "1 item" if n == 1 else f"{n} items"


def expected(tp: Any, plural: bool = False) -> str:
    """The words for a declared type: ``a list of 3 numbers``, ``one of "a", "b"``."""
    origin, args = get_origin(tp), get_args(tp)

    def noun(one: str, many: str, article: str = "a") -> str:
        return many if plural else f"{article} {one}"

    if origin in (Required, NotRequired):
        return expected(args[0], plural)
    if origin is Annotated:
        n, inner = _len_of(args[1:]), args[0]
        if n is not None and get_origin(inner) is list:
            return noun(
                f"list of {n} {expected(get_args(inner)[0], True)}",
                f"lists of {n} {expected(get_args(inner)[0], True)}",
            )
        return expected(inner, plural)
    if tp is Any:
        return noun("value", "values")
    if tp is None or tp is type(None):
        return "null" if not plural else "nulls"
    if tp is float:
        return noun("number", "numbers")
    if tp is int:
        return noun("integer", "integers", "an")
    if tp is str:
        return noun("string", "strings")
    if tp is bool:
        return "true or false"
    if origin is Literal:
        return ("one of " if len(args) > 1 else "") + ", ".join(json.dumps(a) for a in args)
    if origin in (Union, types.UnionType):
        return " or ".join(expected(a, plural) for a in args)
    if origin is list:
        return noun(f"list of {expected(args[0], True)}", f"lists of {expected(args[0], True)}")
    if origin is dict or is_typeddict(tp):
        return noun("object", "objects", "an")
    return repr(tp)


__all__ = ["Len", "describe", "expected", "first_problem", "key_path", "problems"]

"""A configuration reference read off the dataclass schemas themselves: every key with its
type, default and the ``#:`` comment written above it (or the comment beside it), so the
documented keys are the validated ones and cannot drift from them.

The documentation site builds its configuration page from :func:`reference_rows`
(``docs/hooks.py``); nothing here knows which schemas exist, only how to read one.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import re
import tokenize
import types
import typing
from dataclasses import dataclass
from functools import cache

from omegaconf import MISSING

from occtrain.config.loading import section_type


@dataclass(frozen=True)
class KeyDoc:
    """One key of a schema, as a reader of a recipe meets it."""

    path: str
    type: str
    default: str
    doc: str


#: Comments for tools, not readers: a linter's or type checker's or formatter's.
_PRAGMA = re.compile(r"#\s*(noqa|type:|fmt:|pragma)")


@cache
def field_comments(cls: type) -> dict[str, str]:
    """Field name -> its comment in ``cls``'s source: the ``#:`` lines right above it, else
    a ``#`` comment on the same line. Empty for a class without source (``make_dataclass``)."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    comments: dict[str, str] = {}
    pending: list[str] = []
    field_line = re.compile(r"\s+([A-Za-z_]\w*)\s*:")
    lines = source.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        text = tok.string
        row = lines[tok.start[0] - 1]
        if text.startswith("#:") and not row[: tok.start[1]].strip():
            pending.append(text[2:].strip())
            following = lines[tok.start[0]] if tok.start[0] < len(lines) else ""
            match = field_line.match(following)
            if match and not following.strip().startswith("#"):
                comments[match.group(1)] = " ".join(pending)
            if not following.strip().startswith("#:"):
                pending = []
        elif (match := field_line.match(row)) and row[: tok.start[1]].strip() and not _PRAGMA.match(text):
            comments.setdefault(match.group(1), text.lstrip("#").strip())
    return comments


def _comments(schema: type) -> dict[str, str]:
    """Comments of ``schema``'s fields, a subclass's over its bases'."""
    merged: dict[str, str] = {}
    for base in reversed(schema.__mro__):
        if dataclasses.is_dataclass(base):
            merged.update(field_comments(base))
    return merged


def type_name(hint: object) -> str:
    """A type as a recipe's author reads it: ``int``, ``list[str]``, ``float | null``."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # Optional[X] and X | None
        names = [type_name(a) for a in args if a is not type(None)]
        return " | ".join(names) + (" | null" if type(None) in args else "")
    if origin is not None:
        return f"{getattr(origin, '__name__', str(origin))}[{', '.join(type_name(a) for a in args)}]"
    if hint is typing.Any:
        return "any"
    if dataclasses.is_dataclass(hint):
        return "section"
    return getattr(hint, "__name__", str(hint).replace("typing.", ""))


def _default(f: dataclasses.Field) -> object:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return MISSING


def _shown(value: object) -> str:
    if value is MISSING or value == MISSING:
        return "required"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def reference_rows(schema: type, prefix: str = "") -> list[KeyDoc]:
    """Every key of ``schema``, nested sections expanded (a list of sections as ``key[]``)."""
    hints = typing.get_type_hints(schema)
    docs = _comments(schema)
    rows: list[KeyDoc] = []
    for f in dataclasses.fields(schema):
        hint = hints.get(f.name, f.type)
        path = f"{prefix}{f.name}"
        inner = section_type(hint)
        doc = docs.get(f.name, "")
        if inner is not None:
            many = typing.get_origin(hint) is list
            section = "list of sections" if many else "section" if dataclasses.is_dataclass(hint) else "section | null"
            rows.append(
                KeyDoc(path, section, "", doc or (inspect.getdoc(inner) or "").split("\n\n")[0].replace("\n", " "))
            )
            rows.extend(reference_rows(inner, f"{path}[]." if many else f"{path}."))
            continue
        rows.append(KeyDoc(path, type_name(hint), _shown(_default(f)), doc))
    return rows


def markdown_table(rows: list[KeyDoc]) -> str:
    """``rows`` as a Markdown table (pipes in a cell escaped)."""

    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    lines = ["| key | type | default | what it sets |", "|---|---|---|---|"]
    lines += [
        f"| `{r.path}` | {cell(r.type)} | {cell(f'`{r.default}`' if r.default else '')} | {cell(r.doc)} |" for r in rows
    ]
    return "\n".join(lines) + "\n"

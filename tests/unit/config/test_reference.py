"""The configuration reference is read off the schemas: types, defaults and the comments
written beside the fields, for every registered stage kind, family and tokenizer."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from omegaconf import MISSING

from occtrain.cli import main
from occtrain.config.reference import KeyDoc, markdown_table, reference_rows
from occtrain.core import registry
from occtrain.stages import kind_names


@dataclass
class _Inner:
    """A nested section."""

    #: How many.
    count: int = 3


@dataclass
class _Schema:
    name: str = MISSING
    #: The rate,
    #: over two lines.
    rate: float = 0.5
    mode: str = "a"  # a | b
    tags: list[str] = field(default_factory=lambda: ["x"])
    limit: int | None = None
    inner: _Inner = field(default_factory=_Inner)
    items: list[_Inner] = field(default_factory=list)
    flag: bool = False


def test_rows_read_types_defaults_and_comments():
    assert reference_rows(_Schema, "model.") == [
        KeyDoc("model.name", "str", "required", ""),
        KeyDoc("model.rate", "float", "0.5", "The rate, over two lines."),
        KeyDoc("model.mode", "str", '"a"', "a | b"),
        KeyDoc("model.tags", "list[str]", "['x']", ""),
        KeyDoc("model.limit", "int | null", "null", ""),
        KeyDoc("model.inner", "section", "", "A nested section."),
        KeyDoc("model.inner.count", "int", "3", "How many."),
        KeyDoc("model.items", "list of sections", "", "A nested section."),
        KeyDoc("model.items[].count", "int", "3", "How many."),
        KeyDoc("model.flag", "bool", "false", ""),
    ]


@dataclass
class _Unions:
    # Both spellings of an optional section, as schemas may write either.
    old: Optional[_Inner] = None  # noqa: UP045
    new: _Inner | None = None


def test_both_spellings_of_an_optional_section_expand():
    assert reference_rows(_Unions) == [
        KeyDoc("old", "section | null", "", "A nested section."),
        KeyDoc("old.count", "int", "3", "How many."),
        KeyDoc("new", "section | null", "", "A nested section."),
        KeyDoc("new.count", "int", "3", "How many."),
    ]


def test_the_table_escapes_pipes():
    table = markdown_table([KeyDoc("mode", "str", '"a"', "a | b")])
    assert table.splitlines()[-1] == '| `mode` | str | `"a"` | a \\| b |'


def test_the_command_prints_every_kind_family_and_tokenizer(capsys):
    assert main(["config", "reference"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("# Configuration reference")
    for kind in kind_names():
        assert f"## `model:` of the `{kind}` kind" in text
    for family in registry.world_families():
        assert f"## Family `{family}`" in text and f"`model.family: {family}`" in text
    for arch in registry.tokenizer_archs():
        assert f"## Tokenizer `{arch}`" in text
    assert "| `trainer.max_steps` | int | `100` |" in text

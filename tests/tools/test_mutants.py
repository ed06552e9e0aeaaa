"""tools/mutants.py stays runnable: every mutant's change applies to the current code, once,
and names tests that exist (running the mutants is the tool's job: it takes half an hour)."""

from __future__ import annotations

import ast

import pytest

from conftest import REPO, load_tool

mutants = load_tool("mutants")


@pytest.mark.parametrize("mutant", mutants.MUTANTS, ids=[m.name for m in mutants.MUTANTS])
def test_each_mutant_applies_once_and_names_real_tests(mutant):
    assert (REPO / mutant.file).read_text().count(mutant.old) == 1
    assert mutant.old != mutant.new and mutant.tests
    for node in mutant.tests:
        path, _, name = node.partition("::")
        name = name.split("[")[0]
        tree = ast.parse((REPO / path).read_text())
        assert name in {f.name for f in tree.body if isinstance(f, ast.FunctionDef)}, node


def test_mutant_names_are_unique():
    names = [m.name for m in mutants.MUTANTS]
    assert len(set(names)) == len(names)

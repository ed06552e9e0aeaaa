"""Every shipped recipe loads and validates: kinds, handoffs and each stage's model config."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import REPO
from occtrain.runner import load_recipe

RECIPES = sorted((REPO / "stages").rglob("*.yaml"))


def test_there_are_recipes():
    assert {p.name for p in RECIPES} >= {"quickstart.yaml", "occllama.yaml", "tokenizer.yaml", "occllama_multitask.yaml"}


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: str(p.relative_to(REPO)))
def test_recipe_validates(path: Path):
    recipe, planned = load_recipe(path)
    assert planned and all(p.config_hash for p in planned)
    names = [p.spec.name for p in planned]
    for p in planned:  # every handoff points at an earlier stage
        assert all(names.index(dep) < names.index(p.spec.name) for dep in p.spec.consumes)

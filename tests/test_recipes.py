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


def test_readme_lists_every_recipe():
    readme = (REPO / "README.md").read_text()
    unlisted = []
    for path in RECIPES:
        rel = str(path.relative_to(REPO))
        # A family's ablations may be listed by their pattern (stages/ablations/occllm_*.yaml).
        pattern = f"{rel.rsplit('_', 1)[0]}_*.yaml" if path.parent.name == "ablations" else rel
        if rel not in readme and pattern not in readme:
            unlisted.append(rel)
    assert not unlisted, f"README does not name: {unlisted}"

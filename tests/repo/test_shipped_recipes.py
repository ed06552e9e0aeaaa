"""Every shipped recipe loads and validates: kinds, handoffs and each stage's model config."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import REPO
from occtrain.errors import ConfigError
from occtrain.run.planning import load_recipe

RECIPES = sorted((REPO / "recipes").rglob("*.yaml"))


def test_there_are_recipes():
    assert {p.name for p in RECIPES} >= {
        "quickstart.yaml",
        "occllama.yaml",
        "tokenizer.yaml",
        "occllama_multitask.yaml",
    }


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: str(p.relative_to(REPO)))
def test_recipe_validates(path: Path):
    recipe, planned = load_recipe(path)
    assert planned and all(p.config_hash for p in planned)
    names = [p.spec.name for p in planned]
    for p in planned:  # every handoff points at an earlier stage
        assert all(names.index(dep) < names.index(p.spec.name) for dep in p.spec.consumes)


def test_the_docs_list_every_recipe():
    docs = "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))])
    unlisted = []
    for path in RECIPES:
        rel = str(path.relative_to(REPO))
        # A family's ablations may be listed by their pattern (recipes/ablations/occllm_*.yaml).
        pattern = f"{rel.rsplit('_', 1)[0]}_*.yaml" if path.parent.name == "ablations" else rel
        if rel not in docs and pattern not in docs:
            unlisted.append(rel)
    assert not unlisted, f"neither README nor docs/ name: {unlisted}"


def test_the_shipped_gpu_trainer_config_validates_with_every_device():
    # configs/trainer/gpu.yaml asks for every GPU (devices: -1, Lightning's convention); the
    # range check must take it, and still refuse 0 devices in one line.
    _, planned = load_recipe(REPO / "recipes/quickstart.yaml", [f"trainer={REPO / 'configs/trainer/gpu.yaml'}"])
    assert {(p.trainer.accelerator, p.trainer.devices, p.trainer.precision) for p in planned} == {
        ("gpu", -1, "bf16-mixed")
    }
    with pytest.raises(ConfigError, match=r"trainer.devices is 0 in .*: it must be at least 1, or -1 for every device"):
        load_recipe(REPO / "recipes/quickstart.yaml", ["trainer.devices=0"])

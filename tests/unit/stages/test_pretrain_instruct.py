"""The world-model stages' settings, refused before anything runs."""

from __future__ import annotations

import pytest

from conftest import REPO
from occtrain.errors import ConfigError
from occtrain.run.planning import load_recipe


def test_packing_is_planned_for_a_family_whose_sequences_can_share_a_row():
    _, planned = load_recipe(REPO / "recipes/quickstart.yaml", ["stages.pretrain.model.pack_sequences=true"])
    assert next(p for p in planned if p.spec.name == "pretrain").model_cfg.pack_sequences


def test_packing_a_family_with_per_sequence_targets_is_refused_in_one_line():
    with pytest.raises(ConfigError) as err:
        load_recipe(REPO / "recipes/occvla.yaml", ["stages.stage2.model.pack_sequences=true"])
    assert str(err.value) == (
        "stages.stage2.model.pack_sequences: the occvla world model's sequences carry per-sequence targets and "
        "cannot share a row; set it to false"
    )
    with pytest.raises(ConfigError, match=r"pack_length: -4 is negative"):
        load_recipe(REPO / "recipes/quickstart.yaml", ["stages.instruct.model.pack_length=-4"])

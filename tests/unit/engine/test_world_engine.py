"""The world-model engine serves a family's inputs by name without knowing any: an
encoded one from the cache ``prepare_inputs`` fills (and ``add_samples`` grows), another
from the dataset."""

from __future__ import annotations

import pytest
import torch

from occtrain.config.llm import LLMConfig
from occtrain.data.layout import DatasetIndex
from occtrain.engine import new_world_model

TINY_LLM = LLMConfig(hidden_size=16, num_layers=1, num_heads=2, intermediate_size=32, text_vocab_size=300)


@pytest.fixture
def engine(synth_dataset):
    from plugins.tiny_family import ColumnTasks

    return new_world_model({}, TINY_LLM, ColumnTasks(weights={"qa": 1.0}), synth_dataset, family="tiny_columns")


def test_an_encoded_input_is_read_from_its_cache(engine, synth_dataset, tmp_path):
    index = DatasetIndex.open(synth_dataset)
    (scene, token), *_ = index.samples()
    with pytest.raises(RuntimeError, match="prepare_inputs"):
        engine.read("visible_columns", token)
    engine.prepare_inputs(synth_dataset, tmp_path)
    assert (tmp_path / "visible_columns.safetensors").is_file()
    row = engine.read("visible_columns", token)
    mask = torch.from_numpy(index.labels(scene, token)["mask_camera"]).float()
    assert row.shape == (100,) and torch.isclose(row.mean(), mask.mean(), atol=1e-6)


def test_an_unregistered_input_is_named(engine):
    with pytest.raises(KeyError, match="registers no input 'voxels'"):
        engine.read("voxels", "any")


def test_add_samples_encodes_frames_met_one_at_a_time(engine, synth_dataset):
    index = DatasetIndex.open(synth_dataset)
    samples = list(index.samples())[:2]
    engine.add_samples(index, samples)
    assert set(engine.input_caches["visible_columns"]) == {t for _, t in samples}

"""Exports load strictly or refuse in one line: a handoff whose weights and config disagree in
any tensor, missing, unexpected or reshaped, is refused naming the tensor (never loaded with
a layer at its random init), for the LLM directory, the LoRA and bottleneck adapters, the
vision tower, the scene tokenizer and occtrain's own weights. Nothing is changed on disk.

Each case copies a tiny valid export, breaks one thing, and loads it as a later stage would.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
import torch
from safetensors.torch import load_file, save_file

from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.core.registry import build_tokenizer, load_tokenizer, save_tokenizer
from occtrain.engine import export_engine, load_world_model, new_world_model
from occtrain.errors import OcctrainError
from occtrain.families.occllama import TaskConfig
from occtrain.models.adapters import AdapterConfig, add_adapters
from occtrain.models.llm import apply_lora
from occtrain.models.vision import DenseHead, MultiViewEncoder, VisionConfig, export_vision, load_vision_encoder
from test_bad_inputs import snapshot

TINY_TOKENIZER = {"num_codes": 16, "code_dim": 8, "class_embed_dim": 4, "base_channels": 4, "channel_mult": [1, 1, 1, 1],
                  "strides": [2, 2, 5], "num_res_blocks": 1, "z_channels": 8, "latent_attention": False}
TINY_LLM = LLMConfig(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, text_vocab_size=300)


@pytest.fixture(scope="module")
def exports(tmp_path_factory, synth_dataset) -> Path:
    """Four valid exports: a scene tokenizer, a world model with a LoRA adapter, one with
    bottleneck adapters, and a vision stage's."""
    root = tmp_path_factory.mktemp("exports")
    torch.manual_seed(0)
    tokenizer = save_tokenizer(build_tokenizer("occworld_vqvae", TINY_TOKENIZER), "occworld_vqvae", TINY_TOKENIZER, root / "tokenizer")
    lora = new_world_model({"tokenizer": tokenizer}, TINY_LLM, TaskConfig(context_frames=1), synth_dataset, family="occllama")
    lora.world.llm = apply_lora(lora.world.llm, LoRAConfig(r=2, alpha=4, dropout=0.0))
    export_engine(lora, root / "lora", stage="instruct")
    bottleneck = new_world_model({"tokenizer": tokenizer}, TINY_LLM, TaskConfig(context_frames=1), synth_dataset, family="occllama")
    add_adapters(bottleneck.world.llm, AdapterConfig(reduction_factor=4))
    export_engine(bottleneck, root / "bottleneck", stage="pretrain")
    encoder = MultiViewEncoder(VisionConfig(hidden_size=32, num_layers=1))
    export_vision(root / "vision", encoder, DenseHead(encoder.hidden_size, encoder.patch_size))
    return root


def edit_json(rel: str, change: Callable[[dict], None]) -> Callable[[Path], None]:
    def setup(root: Path) -> None:
        data = json.loads((root / rel).read_text())
        change(data)
        (root / rel).write_text(json.dumps(data))

    return setup


def edit_tensors(rel: str, change: Callable[[dict], None]) -> Callable[[Path], None]:
    def setup(root: Path) -> None:
        state = load_file(str(root / rel))
        change(state)
        save_file(state, str(root / rel))

    return setup


def drop_first(prefix: str = "") -> Callable[[dict], None]:
    return lambda state: state.pop(sorted(k for k in state if k.startswith(prefix))[0])


def truncate(rel: str, keep: int) -> Callable[[Path], None]:
    return lambda root: (root / rel).write_bytes((root / rel).read_bytes()[:keep])


def add_layer(data: dict) -> None:
    data["num_hidden_layers"] += 1


def widen_codes(data: dict) -> None:
    data["config"]["code_dim"] = 16


@dataclass(frozen=True)
class Case:
    id: str
    export: str  # which fixture export the case breaks
    setup: Callable[[Path], None]
    #: What the one line says besides the file (which it always names): ``{export}`` is the copy.
    says: str


def load(export: Path) -> object:
    if export.name == "vision":
        return load_vision_encoder(export)
    if export.name == "tokenizer":
        return load_tokenizer(export)
    return load_world_model(export)


CASES = [
    # ---------------------------------------------------------------- the LLM's Hugging Face directory
    Case("llm-config-one-more-layer", "lora", edit_json("llm/config.json", add_layer), "missing tensor 'model.layers.2."),
    Case("llm-weights-truncated", "lora", truncate("llm/model.safetensors", 200), "cannot load the model in {export}/llm"),
    Case("llm-weights-not-safetensors", "lora", lambda root: (root / "llm/model.safetensors").write_bytes(b"PK\x03\x04 a zip"),
         "cannot load the model in {export}/llm"),
    Case("llm-weights-missing-tensor", "lora", edit_tensors("llm/model.safetensors", drop_first("model.layers.1.mlp")),
         "missing tensor 'model.layers.1.mlp"),
    # ---------------------------------------------------------------- the export's own config and weights
    Case("config-without-tasks", "lora", edit_json("config.json", lambda c: c.pop("tasks")), "{export}/config.json: no 'tasks' entry"),
    Case("config-without-vocab", "lora", edit_json("config.json", lambda c: c.pop("vocab")), "{export}/config.json: no 'vocab' entry"),
    Case("config-tasks-unknown-key", "lora", edit_json("config.json", lambda c: c["tasks"].update(speed=1)),
         "{export}/config.json: its 'tasks' do not fit the 'occllama' family"),
    Case("own-weights-missing-tensor", "lora", edit_tensors("model.safetensors", drop_first("occ_proj")), "missing tensor 'occ_proj"),
    Case("own-weights-unexpected-tensor", "lora", edit_tensors("model.safetensors", lambda s: s.update(extra=torch.zeros(2))),
         "unexpected tensor 'extra'"),
    Case("own-weights-reshaped", "lora", edit_tensors("model.safetensors", lambda s: s.update({"occ_proj.1.weight": torch.zeros(3, 3)})),
         "tensor 'occ_proj.1.weight' has shape (3, 3) in the weights"),
    # ---------------------------------------------------------------- adapters
    Case("lora-missing-tensor", "lora", edit_tensors("llm/adapter/adapter_model.safetensors", drop_first()), "{export}/llm/adapter: adapter weights do not match the model (missing tensor"),
    Case("lora-unexpected-tensor", "lora", edit_tensors("llm/adapter/adapter_model.safetensors", lambda s: s.update({"base_model.extra.lora_A.weight": torch.zeros(2, 2)})),
         "unexpected tensor 'base_model.extra.lora_A.weight'"),
    Case("lora-weights-truncated", "lora", truncate("llm/adapter/adapter_model.safetensors", 100), "{export}/llm/adapter: cannot load the LoRA adapter"),
    Case("bottleneck-missing-tensor", "bottleneck", edit_tensors("llm/bottleneck_adapter/adapter.safetensors", drop_first()),
         "{export}/llm/bottleneck_adapter: adapter weights do not match the model (missing tensor"),
    Case("bottleneck-reshaped", "bottleneck", edit_json("llm/bottleneck_adapter/adapter_config.json", lambda c: c.update(reduction_factor=2)),
         "has shape"),
    Case("bottleneck-truncated", "bottleneck", truncate("llm/bottleneck_adapter/adapter.safetensors", 50), "unreadable bottleneck adapter"),
    # ---------------------------------------------------------------- the scene tokenizer, alone and inside a world model
    Case("tokenizer-code-dim-changed", "tokenizer", edit_json("config.json", widen_codes), "has shape"),
    Case("tokenizer-missing-tensor", "tokenizer", edit_tensors("model.safetensors", drop_first()), "missing tensor"),
    Case("world-scene-tokenizer-code-dim-changed", "lora", edit_json("scene_tokenizer/config.json", widen_codes), "{export}/scene_tokenizer: tensor"),
    # ---------------------------------------------------------------- the vision stage's tower and its own weights
    Case("vision-tower-one-more-layer", "vision", edit_json("vision/config.json", add_layer), "missing tensor 'encoder.layers.1."),
    Case("vision-tower-unexpected-tensor", "vision", edit_tensors("vision/model.safetensors", lambda s: s.update(extra=torch.zeros(2))),
         "unexpected tensor 'extra'"),
    Case("vision-own-weights-missing-tensor", "vision", edit_tensors("model.safetensors", drop_first("encoder.")), "missing tensor"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_broken_export_is_refused_in_one_line_and_changes_nothing(case: Case, exports: Path, tmp_path: Path) -> None:
    export = tmp_path / case.export
    shutil.copytree(exports / case.export, export)
    case.setup(export)
    before = snapshot(tmp_path)
    with pytest.raises(OcctrainError) as err:
        load(export)
    message = str(err.value)
    assert "\n" not in message and str(export) in message, message
    assert case.says.format(export=export) in message, message
    assert snapshot(tmp_path) == before


def test_every_valid_export_loads(exports: Path) -> None:
    for name in ("tokenizer", "lora", "bottleneck", "vision"):
        assert load(exports / name) is not None

"""Exports load strictly or refuse in one line: a handoff whose weights and config disagree in
any tensor, missing, unexpected or reshaped, is refused naming the tensor (never loaded with
a layer at its random init), for the LLM directory, the LoRA and bottleneck adapters, the
vision tower, the scene tokenizer and occtrain's own weights. Nothing is changed on disk.

Each case copies a tiny valid export, breaks one thing, and loads it as a later stage would.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

import occtrain
from builders import snapshot
from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.core.tokenizer_exports import build_tokenizer, load_tokenizer, save_tokenizer
from occtrain.engine import export_engine, load_world_model, new_world_model
from occtrain.errors import OcctrainError
from occtrain.families.occllama import TaskConfig
from occtrain.formats.exports import write_export
from occtrain.formats.io import WriteError
from occtrain.models.adapters import AdapterConfig, add_adapters
from occtrain.models.camera_encoder import DenseHead, MultiViewEncoder, VisionConfig, export_vision, load_vision_encoder
from occtrain.models.llm import apply_lora

TINY_TOKENIZER = {
    "num_codes": 16,
    "code_dim": 8,
    "class_embed_dim": 4,
    "base_channels": 4,
    "channel_mult": [1, 1, 1, 1],
    "strides": [2, 2, 5],
    "num_res_blocks": 1,
    "z_channels": 8,
    "latent_attention": False,
}
TINY_LLM = LLMConfig(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, text_vocab_size=300)


@pytest.fixture(scope="module")
def exports(tmp_path_factory, synth_dataset) -> Path:
    """Four valid exports: a scene tokenizer, a world model with a LoRA adapter, one with
    bottleneck adapters, and a vision stage's."""
    root = tmp_path_factory.mktemp("exports")
    torch.manual_seed(0)
    tokenizer = save_tokenizer(
        build_tokenizer("occworld_vqvae", TINY_TOKENIZER), "occworld_vqvae", TINY_TOKENIZER, root / "tokenizer"
    )
    lora = new_world_model(
        {"tokenizer": tokenizer}, TINY_LLM, TaskConfig(context_frames=1), synth_dataset, family="occllama"
    )
    lora.world.llm = apply_lora(lora.world.llm, LoRAConfig(r=2, alpha=4, dropout=0.0))
    export_engine(lora, root / "lora", stage="instruct")
    bottleneck = new_world_model(
        {"tokenizer": tokenizer}, TINY_LLM, TaskConfig(context_frames=1), synth_dataset, family="occllama"
    )
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
    Case(
        "llm-config-one-more-layer", "lora", edit_json("llm/config.json", add_layer), "missing tensor 'model.layers.2."
    ),
    Case(
        "llm-weights-truncated", "lora", truncate("llm/model.safetensors", 200), "cannot load the model in {export}/llm"
    ),
    Case(
        "llm-weights-not-safetensors",
        "lora",
        lambda root: (root / "llm/model.safetensors").write_bytes(b"PK\x03\x04 a zip"),
        "cannot load the model in {export}/llm",
    ),
    Case(
        "llm-weights-missing-tensor",
        "lora",
        edit_tensors("llm/model.safetensors", drop_first("model.layers.1.mlp")),
        "missing tensor 'model.layers.1.mlp",
    ),
    # ---------------------------------------------------------------- the export's own config and weights
    Case(
        "config-without-tasks",
        "lora",
        edit_json("config.json", lambda c: c.pop("tasks")),
        "{export}/config.json: no 'tasks' entry",
    ),
    Case(
        "config-without-vocab",
        "lora",
        edit_json("config.json", lambda c: c.pop("vocab")),
        "{export}/config.json: no 'vocab' entry",
    ),
    Case(
        "config-tasks-unknown-key",
        "lora",
        edit_json("config.json", lambda c: c["tasks"].update(speed=1)),
        "{export}/config.json: its 'tasks' do not fit the 'occllama' family",
    ),
    Case(
        "config-unknown-key",
        "lora",
        edit_json("config.json", lambda c: c.update(familly="occllm")),
        "{export}/config.json: unknown key 'familly' (rename or remove it); did you mean 'family'?",
    ),
    Case(
        "own-weights-missing-tensor",
        "lora",
        edit_tensors("model.safetensors", drop_first("occ_proj")),
        "missing tensor 'occ_proj",
    ),
    Case(
        "own-weights-unexpected-tensor",
        "lora",
        edit_tensors("model.safetensors", lambda s: s.update(extra=torch.zeros(2))),
        "unexpected tensor 'extra'",
    ),
    Case(
        "own-weights-reshaped",
        "lora",
        edit_tensors("model.safetensors", lambda s: s.update({"occ_proj.1.weight": torch.zeros(3, 3)})),
        "tensor 'occ_proj.1.weight' has shape (3, 3) in the weights",
    ),
    # ---------------------------------------------------------------- adapters
    Case(
        "lora-missing-tensor",
        "lora",
        edit_tensors("llm/adapter/adapter_model.safetensors", drop_first()),
        "{export}/llm/adapter: adapter weights do not match the model (missing tensor",
    ),
    Case(
        "lora-unexpected-tensor",
        "lora",
        edit_tensors(
            "llm/adapter/adapter_model.safetensors",
            lambda s: s.update({"base_model.extra.lora_A.weight": torch.zeros(2, 2)}),
        ),
        "unexpected tensor 'base_model.extra.lora_A.weight'",
    ),
    Case(
        "lora-weights-truncated",
        "lora",
        truncate("llm/adapter/adapter_model.safetensors", 100),
        "{export}/llm/adapter: cannot load the LoRA adapter",
    ),
    Case(
        "bottleneck-missing-tensor",
        "bottleneck",
        edit_tensors("llm/bottleneck_adapter/adapter.safetensors", drop_first()),
        "{export}/llm/bottleneck_adapter: adapter weights do not match the model (missing tensor",
    ),
    Case(
        "bottleneck-reshaped",
        "bottleneck",
        edit_json("llm/bottleneck_adapter/adapter_config.json", lambda c: c.update(reduction_factor=2)),
        "has shape",
    ),
    Case(
        "bottleneck-truncated",
        "bottleneck",
        truncate("llm/bottleneck_adapter/adapter.safetensors", 50),
        "unreadable bottleneck adapter",
    ),
    # -------------------------------------------------- the scene tokenizer, alone and inside a world model
    Case("tokenizer-code-dim-changed", "tokenizer", edit_json("config.json", widen_codes), "has shape"),
    Case("tokenizer-missing-tensor", "tokenizer", edit_tensors("model.safetensors", drop_first()), "missing tensor"),
    Case(
        "tokenizer-config-unknown-key",
        "tokenizer",
        edit_json("config.json", lambda c: c.update(num_code=8)),
        "{export}/config.json: unknown key 'num_code' (rename or remove it); did you mean 'num_codes'?",
    ),
    Case(
        "world-scene-tokenizer-code-dim-changed",
        "lora",
        edit_json("scene_tokenizer/config.json", widen_codes),
        "{export}/scene_tokenizer: tensor",
    ),
    Case(
        "world-scene-tokenizer-unknown-key",
        "lora",
        edit_json("scene_tokenizer/config.json", lambda c: c.update(zzz=1)),
        "{export}/scene_tokenizer/config.json: unknown key 'zzz' (rename or remove it); valid keys: arch, "
        "codebook_sizes",
    ),
    # ---------------------------------------------------------------- the vision stage's tower and its own weights
    Case(
        "vision-tower-one-more-layer",
        "vision",
        edit_json("vision/config.json", add_layer),
        "missing tensor 'encoder.layers.1.",
    ),
    Case(
        "vision-tower-unexpected-tensor",
        "vision",
        edit_tensors("vision/model.safetensors", lambda s: s.update(extra=torch.zeros(2))),
        "unexpected tensor 'extra'",
    ),
    Case(
        "vision-own-weights-missing-tensor",
        "vision",
        edit_tensors("model.safetensors", drop_first("encoder.")),
        "missing tensor",
    ),
    Case(
        "vision-config-unknown-key",
        "vision",
        edit_json("config.json", lambda c: c.update(image_means=[0.5])),
        "{export}/config.json: unknown key 'image_means' (rename or remove it); did you mean 'image_mean'?",
    ),
    # -------------------------------------------------- unknown keys inside a section, not only at the top
    Case(
        "tokenizer-section-unknown-key",
        "tokenizer",
        edit_json("config.json", lambda c: c["config"].update(num_code=8)),
        "{export}/config.json: unknown key 'config.num_code' (rename or remove it); did you mean 'num_codes'?",
    ),
    Case(
        "world-family-section-unknown-key",
        "lora",
        edit_json("config.json", lambda c: c["world"][c["family"]].update(zzz=1)),
        "{export}/config.json: unknown key 'world.occllama.zzz' (rename or remove it)",
    ),
    Case(
        "vision-section-unknown-key",
        "vision",
        edit_json("config.json", lambda c: c["vision"].update(patchsize=8)),
        "{export}/config.json: unknown key 'vision.patchsize' (rename or remove it)",
    ),
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


def test_a_writer_whose_key_the_readers_do_not_know_fails_before_writing(tmp_path: Path) -> None:
    with pytest.raises(
        ValueError, match="export config key 'new_setting' is missing from occtrain.formats.exports.EXPORT_KEYS"
    ):
        write_export(tmp_path / "export", {"w": torch.zeros(1)}, {"stage_kind": "tokenizer", "new_setting": 1})
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- a full disk while exporting


def fail_at(where: str, code: int) -> Callable[[pytest.MonkeyPatch], None]:
    """Make one step of writing an export fail as the machine would, with ``code``'s errno."""

    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    real_rename = Path.rename

    def rename(
        self, target
    ):  # the new export (.export.<random>) moving into place, once the old one is aside (.export.old)
        return fail() if self.name.startswith(".export.") and self.name != ".export.old" else real_rename(self, target)

    def patch(monkeypatch: pytest.MonkeyPatch) -> None:
        if where == "swap":
            monkeypatch.setattr(Path, "rename", rename)
        else:
            monkeypatch.setattr(where, fail)

    return patch


@pytest.mark.parametrize(
    "where, code, says",
    [
        (
            "occtrain.formats.exports.os.fsync",
            errno.ENOSPC,
            "the disk is full; free space and rerun (a run resumes where it stopped)",
        ),
        ("occtrain.formats.exports.shutil.copy2", errno.EDQUOT, "the disk quota is exhausted"),
        ("occtrain.formats.exports.tempfile.mkdtemp", errno.EROFS, "the file system is read-only"),
        ("swap", errno.EACCES, "permission denied"),
    ],
    ids=["weights-fsync-disk-full", "extra-copy-quota", "read-only", "swap-denied"],
)
def test_an_export_that_cannot_be_written_is_one_line_and_keeps_the_old_one(
    tmp_path: Path, monkeypatch, where, code, says
) -> None:
    export, extra = tmp_path / "stage" / "export", tmp_path / "extra"
    (extra / "sub").mkdir(parents=True)
    (extra / "sub" / "f.json").write_text("{}")
    write_export(export, {"w": torch.zeros(2)}, {"k": 1}, {"llm": extra})
    before = snapshot(tmp_path)
    fail_at(where, code)(monkeypatch)
    with pytest.raises(WriteError) as err:
        write_export(export, {"w": torch.ones(3)}, {"k": 2}, {"llm": extra})
    assert str(err.value).startswith(f"cannot write {export}: {says}") and "\n" not in str(err.value), err.value
    assert snapshot(tmp_path) == before  # the old export whole, no temp directory left


def _write_vision(export: Path) -> None:
    encoder = load_vision_encoder(export)
    export_vision(export, encoder, DenseHead(encoder.hidden_size, encoder.patch_size))


@pytest.mark.parametrize(
    "kind, write, where",
    [
        # The vision stage's export, its Hugging Face tower copied in.
        ("vision", _write_vision, "occtrain.formats.exports.os.fsync"),
        # A world model stages its LLM directory beside the export: a full disk there names the
        # export (not a SafetensorError from a system temp directory).
        (
            "lora",
            lambda export: export_engine(load_world_model(export), export, stage="instruct"),
            "occtrain.engine.export._save_hf_llm",
        ),
    ],
    ids=["vision", "world-model-llm-staging"],
)
def test_a_full_disk_surfaces_through_a_real_writer(
    exports: Path, tmp_path: Path, monkeypatch, kind, write, where
) -> None:
    """A real stage's writer on a full disk: the same one line, the export it replaces kept."""
    export = tmp_path / kind
    shutil.copytree(exports / kind, export)
    before = snapshot(tmp_path)
    fail_at(where, errno.ENOSPC)(monkeypatch)
    with pytest.raises(WriteError, match=f"^cannot write {export}: the disk is full"):
        write(export)
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- occtrain.load given another directory


@pytest.fixture
def run_dir(exports: Path, tmp_path: Path) -> Path:
    """A run: a tokenizer stage done, a pretrain stage cut off before its export, and an
    instruct stage done (the LoRA world model its export)."""
    run = tmp_path / "run"
    stages = {"tokenizer": "done", "pretrain": "interrupted", "instruct": "done"}
    (run / "pretrain" / "logs").mkdir(parents=True)
    shutil.copytree(exports / "tokenizer", run / "tokenizer" / "export")
    shutil.copytree(exports / "lora", run / "instruct" / "export")
    (run / "manifest.json").write_text(
        json.dumps({"name": "r", "stages": {n: {"kind": n, "status": s} for n, s in stages.items()}})
    )
    return run


def test_load_given_a_stage_directory_loads_its_export(run_dir: Path) -> None:
    model = occtrain.load(run_dir / "instruct")
    assert model.family == "occllama" and model.operations


@pytest.mark.parametrize(
    "given, says",
    [
        (
            "pretrain",
            "{run}/pretrain is a stage directory without an export; its stage is not done — run it, or pass "
            "{run}/pretrain/export",
        ),
        (
            ".",
            "{run} is a run directory, not an export; its stages are tokenizer (done), pretrain (interrupted), "
            "instruct (done); "
            "pass a world-model stage's export (e.g. {run}/instruct/export)",
        ),
    ],
    ids=["stage-without-export", "run-directory"],
)
def test_load_given_a_directory_without_a_world_model_says_what_to_pass(run_dir: Path, given: str, says: str) -> None:
    before = snapshot(run_dir)
    with pytest.raises(OcctrainError) as err:
        occtrain.load(run_dir / given if given != "." else run_dir)
    assert str(err.value) == says.format(run=run_dir)
    assert snapshot(run_dir) == before

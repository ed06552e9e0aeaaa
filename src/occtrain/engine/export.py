"""World-model exports: a standard Hugging Face LLM directory beside occtrain's own parts.

::

    export/
      config.json          occtrain's: stage kind, family, joint vocabulary, world-model
                           settings, the task/prompt config and generation length it trained with
      model.safetensors    occtrain's own weights, not the LLM's (OccLLaMA: the occupancy
                           projection; Occ-LLM: patch embedding, patch head, pre-fusion)
      llm/                 a Hugging Face directory: config.json (model_type), model.safetensors
                           under HF names, generation_config.json, the tokenizer with the
                           joint-vocabulary tokens
      llm/adapter/         the peft adapter, when the stage trained one and did not merge it
      llm/bottleneck_adapter/  bottleneck adapters (OccVLA): adapter.safetensors + adapter_config.json
      scene_tokenizer/     the tokenizer stage's export, copied
      vision_encoder/      the vision stage's export, copied (a world model that reads cameras)

``AutoModelForCausalLM.from_pretrained("export/llm")`` then
``PeftModel.from_pretrained(model, "export/llm/adapter")`` gives occtrain's logits on text
and action tokens. OccLLaMA's occupancy tokens enter occtrain's model through a projection
of the scene codebook; their embedding rows in ``llm/`` hold that projection (unless the LLM
ties its embeddings to its head), so plain transformers reads them too where attention is
causal. Occ-LLM's patch tokens carry their cells beside the ids, which only occtrain reads.
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from safetensors.torch import save

from occtrain.config import to_container
from occtrain.config.llm import MAX_NEW_TEXT_TOKENS, LLMConfig
from occtrain.core.lm_world_model import WorldInputs
from occtrain.core.registry import get_world
from occtrain.core.scene_encoders import SCENE_ENCODER_DIR
from occtrain.core.shared_tasks import TaskConfig, corpus_texts
from occtrain.core.vocab import JointVocab
from occtrain.data.layout import DatasetIndex
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.formats.exports import check_section, load_state_strict, read_export, require_config, write_export
from occtrain.formats.io import write_error
from occtrain.models.adapters import has_adapters, load_adapters, save_adapters, without_adapters
from occtrain.models.camera_encoder import load_vision_encoder
from occtrain.models.llm import build_llm, load_lora_strict, load_pretrained_strict, load_text_tokenizer
from occtrain.models.text_tokenizer import train_text_tokenizer

LLM_DIR = "llm"
ADAPTER_DIR = "adapter"
VISION_DIR = "vision_encoder"
BOTTLENECK_DIR = "bottleneck_adapter"
WORLD_MODEL = "world_model"


def world_inputs(family: str, exports: dict[str, Path], world_cfg: Any, where: str) -> WorldInputs:
    """What a fresh world model of ``family`` is built over, from the consumed exports by
    stage kind: its scene encoder and, for a model that reads the cameras, the vision encoder."""
    world = get_world(family, f"{where}.family")
    scene = world.scene_encoder(exports, world_cfg) if world.scene_encoder is not None else None
    vision = None
    if world.reads_cameras:
        if "vision" not in exports:
            raise ConfigError(
                f"{where}: the '{family}' world model reads the cameras; add a vision stage to the stage's consumes"
            )
        vision = load_vision_encoder(exports["vision"])
    return WorldInputs(scene, vision)


def new_world_model(
    exports: dict[str, Path],
    llm_cfg: LLMConfig,
    tasks: TaskConfig,
    data_root: str | Path,
    max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS,
    family: str = "",
    world_cfg: Any = None,
    where: str = "model",
) -> WorldModelEngine:
    """A freshly initialised world model of ``family`` (what pretraining starts from), over
    the consumed exports (by stage kind: the tokenizer's, the vision stage's) and with its
    world settings ``world_cfg`` (checked against them; errors name ``<where>.<family>.<key>``).

    The text tokenizer is the LLM's own when ``llm_cfg.path`` is set, else a BPE trained on
    the dataset's text; training is deterministic, so every DDP rank and a resumed run build
    the same one. The LLM is initialised under the current torch seed.
    """
    world = get_world(family, f"{where}.family")
    if world_cfg is None and world.world_config is not None:
        world_cfg = world.world_config()
    inputs = world_inputs(family, exports, world_cfg, where)
    if world_cfg is not None:
        world_cfg.validate(f"{where}.{family}", inputs)
    if llm_cfg.path:
        text_tok = load_text_tokenizer(llm_cfg.path)
    else:
        text_tok = train_text_tokenizer(
            corpus_texts(DatasetIndex.open(data_root), world.prompt_words), llm_cfg.text_vocab_size
        )
    vocab = JointVocab(text_tok, llm_cfg=llm_cfg, **world.model.vocab_layout(inputs, world_cfg))
    llm = build_llm(llm_cfg, len(vocab))
    model = world.model.create(llm, vocab, inputs, llm_cfg.scene_prediction, world_cfg)
    return WorldModelEngine(inputs.scene, model, text_tok, tasks, max_new_text_tokens, family, inputs.vision)


def export_engine(engine: WorldModelEngine, path: Path, stage: str, merge: bool = False) -> Path:
    """Write a world-model export (see the module docstring). With a LoRA adapter,
    ``llm/`` holds the base weights and ``llm/adapter/`` the adapter; ``merge`` folds the
    adapter into ``llm/`` instead. The engine itself is left as it was."""
    path = Path(path)
    try:
        # Staged beside the export (the same disk it is moved to), so a full disk or a
        # read-only place is reported for the export, in one line, before it is swapped in.
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.llm.") as tmp:
            return _stage_and_write(engine, path, stage, merge, Path(tmp))
    except OSError as err:
        raise write_error(path, err) from None


def _stage_and_write(engine: WorldModelEngine, path: Path, stage: str, merge: bool, tmp: Path) -> Path:
    """:func:`export_engine` with its LLM directory staged in ``tmp``."""
    from peft import PeftModel

    world = engine.world
    llm = world.llm
    llm_dir = tmp / LLM_DIR
    if isinstance(llm, PeftModel) and merge:
        base = copy.deepcopy(llm).merge_and_unload()
        state = base.state_dict()
    elif isinstance(llm, PeftModel):
        base = llm.get_base_model()
        state = _base_names(llm.state_dict())
        # The base embedding table is in llm/ already; the adapter keeps its own LoRA weights only.
        llm.save_pretrained(str(llm_dir / ADAPTER_DIR), save_embedding_layers=False)
    else:
        base = llm
        state = base.state_dict()
    if has_adapters(base):
        # The Hugging Face directory holds the LM's own weights; the adapters sit beside them.
        state = without_adapters(state)
        save_adapters(base, llm_dir / BOTTLENECK_DIR)
    _save_hf_llm(llm_dir, base, state, world, engine)
    own = {k: v for k, v in world.state_dict().items() if not k.startswith("llm.")}
    config = {
        "stage_kind": WORLD_MODEL,
        "stage": stage,
        "family": engine.family,
        "vocab": engine.vocab.to_json(),
        "world": world.export_config(),
        "tasks": to_container(OmegaConf.structured(engine.tasks)),
        "max_new_text_tokens": engine.max_new_text_tokens,
    }
    extra = {LLM_DIR: llm_dir}
    if engine.scene_encoder is not None and engine.encoder.export_dir is not None:
        extra[SCENE_ENCODER_DIR] = Path(engine.encoder.export_dir)
    if engine.vision is not None:
        if engine.vision.export_dir is None:
            raise ValueError("a world model's camera encoder comes from a vision export, which it copies")
        extra[VISION_DIR] = Path(engine.vision.export_dir)
    return write_export(path, own, config, extra)


def _save_hf_llm(
    llm_dir: Path, base: Any, state: dict[str, torch.Tensor], world: Any, engine: WorldModelEngine
) -> None:
    """A plain Hugging Face directory: config, weights (safetensors, HF names), generation
    config and tokenizer."""
    from transformers import GenerationConfig

    llm_dir.mkdir(parents=True, exist_ok=True)
    # Copies: the occupancy rows are written below, and tied tensors must not share storage.
    state = {k: v.detach().cpu().clone().contiguous() for k, v in state.items()}
    embed_key = next((k for k in state if k.endswith("embed_tokens.weight")), None)
    rows = world.scene_token_rows()
    if embed_key is not None and rows is not None and not base.config.get_text_config().tie_word_embeddings:
        with torch.no_grad():
            lo, hi = engine.vocab.occ_range
            state[embed_key][lo:hi] = rows.to(state[embed_key].dtype).cpu()
    # Serialised here and written by Python: safetensors' save_file reports a full disk as a
    # SafetensorError that has lost the errno.
    (llm_dir / "model.safetensors").write_bytes(save(state, metadata={"format": "pt"}))
    base.config.save_pretrained(str(llm_dir))
    vocab = engine.vocab
    GenerationConfig(
        bos_token_id=vocab.bos_id,
        eos_token_id=vocab.eos_id,
        pad_token_id=vocab.pad_id,
        max_new_tokens=engine.max_new_text_tokens,
        do_sample=False,
    ).save_pretrained(str(llm_dir))
    engine.text_tokenizer.save_pretrained(str(llm_dir))


def _base_names(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """peft's wrapped names (``base_model.model.``, ``.base_layer.``) back to the plain model's;
    LoRA weights dropped."""
    out = {}
    for name, value in state.items():
        if ".lora_" in name:
            continue
        out[name.replace("base_model.model.", "", 1).replace(".base_layer.", ".")] = value
    return out


def load_world_model(export_dir: Path) -> WorldModelEngine:
    """Rebuild the engine from a world-model export: the LLM from its Hugging Face directory
    (and adapter), occtrain's parts, the frozen encoders, the text tokenizer and the saved
    task settings; the family's registration says how."""
    from transformers import AutoModelForCausalLM

    export_dir = Path(export_dir)
    state, config = read_export(export_dir)
    if config.get("stage_kind") != WORLD_MODEL:
        raise ConfigError(f"{export_dir}: not a world-model export (stage kind '{config.get('stage_kind')}')")
    require_config(config, ("family", "vocab", "world", "tasks"), export_dir)
    family = config.get("family", "")
    world = get_world(family, f"{export_dir / 'config.json'}: family")
    llm_dir = export_dir / LLM_DIR
    scene = world.load_scene_encoder(export_dir, config) if world.load_scene_encoder is not None else None
    text_tok = load_text_tokenizer(llm_dir)
    vocab = JointVocab.from_json(config["vocab"], text_tok)
    world_cfg = config["world"]
    if world.world_config is not None and family in world_cfg:  # the family's own settings
        check_section(world.world_config, world_cfg[family], f"world.{family}", export_dir)
    llm = load_pretrained_strict(
        AutoModelForCausalLM,
        llm_dir,
        f"{export_dir}",
        "re-run the stage that wrote it",
        attn_implementation=world_cfg["attn_implementation"],
        dtype=torch.float32,
    )
    if (llm_dir / BOTTLENECK_DIR).is_dir():
        load_adapters(llm, llm_dir / BOTTLENECK_DIR)
    vision = load_vision_encoder(export_dir / VISION_DIR) if (export_dir / VISION_DIR).is_dir() else None
    model = world.model.from_export(world_cfg, llm, vocab, WorldInputs(scene, vision))
    load_state_strict(model, state, ignore=("llm.",), source=str(export_dir))
    if (llm_dir / ADAPTER_DIR).is_dir():
        model.llm = load_lora_strict(model.llm, llm_dir / ADAPTER_DIR)
    try:
        tasks = world.task_config(**config["tasks"])  # as saved: a merge onto the defaults would add task weights
    except TypeError as err:
        raise ConfigError(
            f"{export_dir / 'config.json'}: its 'tasks' do not fit the '{family}' family ({err}); re-run the stage "
            "that wrote it"
        ) from None
    return WorldModelEngine(
        scene, model, text_tok, tasks, config.get("max_new_text_tokens", MAX_NEW_TEXT_TOKENS), family, vision
    )

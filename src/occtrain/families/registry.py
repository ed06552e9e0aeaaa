"""The registry of paper families and of the scene-tokenizer architectures they bring.

A family registers one :class:`FamilySpec`: its scene tokenizers, its world-model class,
its tasks and the export format of its world model. Stages and the engine look things up
here by name (``model.arch: occllama_tokenizer``, an export's ``"family"``), so adding a
tokenizer architecture is its file plus one entry in its family's registration.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from omegaconf import DictConfig, OmegaConf

from occtrain.errors import ConfigError
from occtrain.exports import read_export, write_export
from occtrain.models import count_parameters

#: The families that ship with occtrain, imported on first look-up.
BUILTIN_FAMILIES = ("occtrain.families.occworld", "occtrain.families.occllama", "occtrain.families.occllm", "occtrain.families.occvla")


@dataclass(frozen=True)
class TokenizerArch:
    """A scene-tokenizer architecture: ``model.arch`` name, config dataclass, model class."""

    name: str
    config: type
    model: type


@dataclass(frozen=True)
class FamilySpec:
    """What one paper family contributes to the shared stage kinds."""

    name: str
    #: The paper, as README's table names it.
    paper: str
    tokenizers: tuple[TokenizerArch, ...] = ()
    #: The world model class (``from_export`` / ``export_config``), if the family has one.
    world_model: type | None = None
    #: Task name -> builder ``(clip, task_config, rng) -> parts | None``.
    tasks: Mapping[str, Callable[..., Any]] = field(default_factory=dict)
    #: Tasks whose evaluation asks every item of a clip: name -> ``(clip, task_config) -> [parts]``.
    every_item: Mapping[str, Callable[..., Any]] = field(default_factory=dict)
    #: The dataclass of the task/prompt settings its world-model exports carry.
    task_config: type | None = None
    #: The dataclass of its world model's own settings (``model.<family>`` of a world-model stage).
    world_config: type | None = None
    #: Stage kind ("pretrain", "instruct") -> the task weights a stage that names none trains.
    default_tasks: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    #: Fixed words of its prompts, added to the text a world model's BPE tokenizer trains on.
    prompt_words: tuple[str, ...] = ()
    #: Its world model reads the cameras through a vision stage's encoder (pretraining consumes one).
    reads_cameras: bool = False


_FAMILIES: dict[str, FamilySpec] = {}
_TOKENIZERS: dict[str, tuple[TokenizerArch, str]] = {}
_loaded = False


def register_family(spec: FamilySpec) -> FamilySpec:
    """Add a family (a plugin may register its own); tokenizer names must be unique."""
    for arch in spec.tokenizers:
        owner = _TOKENIZERS.get(arch.name)
        if owner is not None and owner[1] != spec.name:
            raise ConfigError(f"tokenizer arch '{arch.name}' of family '{spec.name}' is already registered by '{owner[1]}'")
        _TOKENIZERS[arch.name] = (arch, spec.name)
    _FAMILIES[spec.name] = spec
    return spec


def _load_builtin() -> None:
    global _loaded
    if not _loaded:
        _loaded = True
        for module in BUILTIN_FAMILIES:
            importlib.import_module(module)


def families() -> dict[str, FamilySpec]:
    """Every registered family by name, the built-in ones first."""
    _load_builtin()
    return dict(_FAMILIES)


def get_family(name: str) -> FamilySpec:
    _load_builtin()
    if name not in _FAMILIES:
        raise ConfigError(f"unknown model family '{name}'; families are {', '.join(_FAMILIES)}")
    return _FAMILIES[name]


def tokenizer_archs() -> dict[str, TokenizerArch]:
    """Every registered scene-tokenizer architecture by ``model.arch`` name."""
    _load_builtin()
    return {name: arch for name, (arch, _) in _TOKENIZERS.items()}


def tokenizer_family(arch: str) -> str:
    _load_builtin()
    return _TOKENIZERS[arch][1]


def _arch(name: str) -> TokenizerArch:
    archs = tokenizer_archs()
    if name not in archs:
        raise ConfigError(f"model.arch: '{name}' is not a tokenizer; use one of {', '.join(archs)}")
    return archs[name]


def tokenizer_config(arch: str, cfg: Any, where: str | None = None) -> Any:
    """``cfg`` (a dataclass, a DictConfig or a mapping) as ``arch``'s validated config dataclass."""
    schema = _arch(arch).config
    if not isinstance(cfg, schema):
        node = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
        cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), node))
    cfg.validate(where or f"model.{arch}")
    return cfg


def build_tokenizer(arch: str, cfg: Any) -> Any:
    """Build tokenizer ``arch`` from its config: a dataclass, a DictConfig or a plain mapping."""
    return _arch(arch).model(tokenizer_config(arch, cfg))


def save_tokenizer(model: Any, arch: str, cfg: dict, export_dir: Path) -> Path:
    """Write a tokenizer export: weights, ``arch`` and its config, and the codebook layout
    (size, latent grid) that a world model's joint vocabulary is laid out from."""
    config = {
        "stage_kind": "tokenizer",
        "arch": arch,
        "config": cfg,
        "num_codes": int(model.num_codes),
        "codebook_sizes": model.codebook_sizes,
        "latent_hw": list(model.latent_hw),
        "params": count_parameters(model),
        "label_convention": "occ3d",
    }
    return write_export(export_dir, model.state_dict(), config)


def load_tokenizer(export_dir: Path) -> Any:
    """Rebuild a scene tokenizer from a tokenizer stage's export (frozen, eval mode)."""
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "tokenizer":
        raise ConfigError(f"{export_dir}: not a tokenizer export (stage kind '{config.get('stage_kind')}'); consume the tokenizer stage")
    model = build_tokenizer(config["arch"], config["config"])
    model.load_state_dict(state)
    model.export_dir = Path(export_dir)  # a world-model export copies it from here
    model.arch = config["arch"]
    return model.eval().requires_grad_(False)

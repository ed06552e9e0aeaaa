"""Stage kinds: each a LightningModule plus how to build, feed and export it.

A kind registers a :class:`StageKind`; the runner looks kinds up by name. Kinds whose
module is not implemented yet are reported as such when a recipe names them.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import lightning as L

from occtrain.config.recipe import StageSpec
from occtrain.config.schema import DataConfig, TrainerConfig


@dataclass
class StageContext:
    """Everything a stage kind needs to build its module."""

    spec: StageSpec
    model_cfg: Any  # the kind's validated model config (an omegaconf structured object)
    data: DataConfig
    trainer: TrainerConfig
    stage_dir: Path
    #: Export directories of the consumed stages, by stage name.
    inputs: dict[str, Path]


@dataclass(frozen=True)
class StageKind:
    name: str
    model_schema: type
    data_kind: str  # "frames" or "clips"
    #: Builds the stage's LightningModule. The module may define ``entries``: per split
    #: ("train", "val"), the shard entries it reads (None: all), so that e.g. a stage that
    #: trains on annotations alone never decodes occupancy.
    build: Callable[[StageContext], L.LightningModule]
    #: Validation metric that picks ``best.ckpt``, and whether higher is better.
    monitor: str | None = None
    mode: str = "max"


_KINDS: dict[str, StageKind] = {}


def register(kind: StageKind) -> StageKind:
    _KINDS[kind.name] = kind
    return kind


#: Built-in kinds and the module that registers each. Imported on first use, so a recipe
#: of tokenizer stages never pays for importing transformers.
BUILTIN_KINDS = {
    "tokenizer": "occtrain.stages.tokenizer",
    "pretrain": "occtrain.stages.world_model",
    "instruct": "occtrain.stages.world_model",
    "planner": "occtrain.stages.planner",
    "distill": "occtrain.stages.distill",
}


def get_kind(name: str) -> StageKind | None:
    """The registered kind, importing a built-in kind's module on first use."""
    if name not in _KINDS and name in BUILTIN_KINDS:
        importlib.import_module(BUILTIN_KINDS[name])
    return _KINDS.get(name)


def kind_names() -> list[str]:
    return sorted(set(_KINDS) | set(BUILTIN_KINDS))

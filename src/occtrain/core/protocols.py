"""The seams between the family-neutral engine and a family: declared once, checked when
a family registers (``core.registry.register_family``).

Subject to change while the families that use them settle; docs/adding-a-family.md
shows them in use.

- :class:`SceneEncoder`: occupancy -> what a world model's scene parts hold, and back:
  discrete codes (a VQ tokenizer's) or continuous tokens with their 3D positions.
- :class:`Scorer`: grades one task's generated answers with the papers' metrics and adds
  its baselines; :class:`EvalHook`: family-level scoring that belongs to no task (OccVLA's
  occupancy queries).
- :class:`WorldEngine`: what family code and the shared operations and scorers may ask of
  the world-model engine (``engine.WorldModelEngine``), which sits above them;
  :func:`family_world` and :func:`family_tasks` read its world model and task settings as
  the family's own classes.
- :class:`SceneMover`: a scene moved by the ego and re-encoded (what the moved query
  blocks hold); the engine makes it.
- :class:`PromptInputs`: what a sequence builder reads besides a prompt's parts (the
  per-sample inputs its family registered, served by the engine), so a family's own part
  kinds can be laid out.
- :class:`Planner`: what the ``planner`` stage trains (OccVLA's MLP head on the meta
  action, a diffusion planner, ...), Lightning-free; it answers :class:`Plans`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, TypeVar, runtime_checkable

import numpy as np
import torch
from omegaconf import DictConfig
from torch import nn

from occtrain.config.groups import DataConfig
from occtrain.config.recipe import StageSpec
from occtrain.core.ego_steps import EgoStep

if TYPE_CHECKING:  # types only: these modules import this one's neighbours
    from torchmetrics import Metric

    from occtrain.core.decoding import Answer
    from occtrain.core.lm_world_model import LMWorldModel
    from occtrain.core.scorers import Item, Priors
    from occtrain.core.sequence import TokenSequence
    from occtrain.core.shared_tasks import TaskConfig, TaskSpec
    from occtrain.core.vocab import JointVocab
    from occtrain.data.clips import Clip, Part
    from occtrain.data.layout import DatasetIndex

World = TypeVar("World", bound="LMWorldModel")
Tasks = TypeVar("Tasks", bound="TaskConfig")


class WorldEngine(Protocol):
    """A family's world model as the engine runs it: the model, its vocabulary and task
    settings, the cached encodings of the dataset it was prepared on, and the rollout of a
    task's prompts. Families and ``core`` receive the engine typed as this; the engine
    (a layer above them) implements it."""

    @property
    def family(self) -> str: ...

    @property
    def world(self) -> LMWorldModel: ...

    @property
    def vision(self) -> torch.nn.Module | None: ...

    def operation(self, name: str) -> Callable[..., object] | None: ...

    def to(self, device: torch.device) -> torch.nn.Module: ...

    @property
    def vocab(self) -> JointVocab: ...

    @property
    def tasks(self) -> TaskConfig: ...

    @property
    def task_specs(self) -> Mapping[str, TaskSpec]: ...

    @property
    def max_new_text_tokens(self) -> int: ...

    @property
    def scene_cache(self) -> Mapping[str, torch.Tensor] | None: ...

    @property
    def data_index(self) -> DatasetIndex | None: ...

    def needs_semantics(self) -> bool: ...

    def scenes(self, batch: dict, needed: list[set[int]]) -> dict[tuple[int, int], torch.Tensor]: ...

    def decode_scenes(self, scenes: torch.Tensor) -> torch.Tensor: ...

    def encodes_labels(self) -> bool: ...

    def encode_scenes(self, semantics: torch.Tensor) -> torch.Tensor: ...

    def encode_parts(self, parts: list[Part], scenes: dict[int, torch.Tensor]) -> TokenSequence: ...

    def prompt_and_plan(
        self, parts: list[Part], scenes: dict[int, torch.Tensor]
    ) -> tuple[TokenSequence, list[Answer]]: ...

    def task_items(self, task: str, clip: Clip, seed: int = 0, every: bool = False) -> list[list[Part]]: ...

    def rollouts(
        self,
        task: str,
        clips: list[Clip],
        batch: dict,
        seed: int = 0,
        batched: bool = True,
        every: bool = False,
        select: Callable[[Clip, list[Part]], bool] | None = None,
    ) -> Iterator[tuple[int, list[Part], list[Part], dict[int, torch.Tensor]]]: ...


def family_world(engine: WorldEngine, cls: type[World]) -> World:
    """The engine's world model as its family's class ``cls``. A family's operations,
    scorers and hooks are only given an engine of their own family (looked up by it), whose
    world model that family's ``WorldSpec.model`` made."""
    world = engine.world
    if not isinstance(world, cls):
        raise TypeError(f"the '{engine.family}' engine's world model is a {type(world).__name__}, not a {cls.__name__}")
    return world


def family_tasks(engine: WorldEngine, cls: type[Tasks]) -> Tasks:
    """The engine's task settings as its family's class ``cls`` (its ``WorldSpec.task_config``),
    for the same reason as :func:`family_world`."""
    tasks = engine.tasks
    if not isinstance(tasks, cls):
        raise TypeError(
            f"the '{engine.family}' engine's task settings are a {type(tasks).__name__}, not a {cls.__name__}"
        )
    return tasks


class SceneMover(Protocol):
    """A scene as the ego would see it after a move, with everything else standing still,
    through the frozen scene encoder (its labels shifted and encoded again): the code ids
    (S,) of a scene in the codes layout -> those of it moved by ``step``; ``codes``: the
    same on its raw codes (flat, codebook-major), what the patches layout tracks."""

    def __call__(self, code_ids: torch.Tensor, step: EgoStep) -> torch.Tensor: ...

    def codes(self, codes: torch.Tensor, step: EgoStep) -> torch.Tensor: ...

    def labels(self, codes: torch.Tensor, step: EgoStep | None) -> torch.Tensor | None:
        """The label volume of the dataset frame whose raw codes these are, moved by
        ``step`` (None: as it is); None when they are no dataset frame's (a generated scene)."""
        ...


class PromptInputs(Protocol):
    """What a sequence builder's ``lay`` reads for the parts that hold no values of their
    own: the input ``name`` of sample ``token``, one its family registered
    (``core.sample_inputs.SampleInput`` in ``WorldSpec.sample_inputs``)."""

    def read(self, name: str, token: str) -> torch.Tensor: ...


@runtime_checkable
class SceneEncoder(Protocol):
    """Frozen scene encoder of a world model.

    ``encode`` maps label volumes Long[B, X, Y, Z] to one row per sample: with
    ``discrete``, Long[B, L] codes; otherwise Float[B, N, 3 + D], N tokens of which the
    first three channels are the token's position (metres, ego frame) and the rest its
    features. An encoder that reads the cameras instead (SparseOccVLA's) also has
    ``encode_samples(index, samples) -> rows`` for ``(scene, token)`` samples of a
    ``DatasetIndex``; the engine then always encodes through it, once per dataset.
    ``decode`` maps rows back to label volumes Long[N, X, Y, Z] (how forecasts are
    scored). ``export_dir`` is the directory a world-model export copies (None: nothing
    to copy, the encoder is rebuilt from the world model's settings).
    """

    discrete: bool
    export_dir: Path | None

    def encode(self, semantics: torch.Tensor) -> torch.Tensor: ...

    def decode(self, scenes: torch.Tensor) -> torch.Tensor: ...


@runtime_checkable
class CameraSceneEncoder(SceneEncoder, Protocol):
    """A scene encoder that reads the cameras (SparseOccVLA's): rows for ``(scene, token)``
    samples of a ``DatasetIndex``, encoded once per dataset."""

    def encode_samples(self, index: DatasetIndex, samples: list[tuple[str, str]]) -> torch.Tensor: ...


class ScoringContext(Protocol):
    """What a scorer or an eval hook reads and writes of the evaluator running it
    (``engine.evaluator.Evaluator``): the metrics by name, the baselines' priors, the
    dataset, caches made once a run, and what it keeps for the dashboard and the
    predictions file."""

    #: Every metric its scorers and hooks declared, by name (``metric`` gives one typed).
    metrics: torch.nn.ModuleDict
    priors: Priors
    #: The dataset the clips come from (None before a run).
    index: DatasetIndex | None
    #: Whether every prediction is kept, by kind, in ``predictions``.
    record: bool
    predictions: dict[str, dict]

    @property
    def device(self) -> torch.device: ...

    def metric(self, name: str) -> Metric: ...

    def once(self, key: Hashable) -> bool: ...

    def reconstructed(self, token: str, make: Callable[[], torch.Tensor]) -> torch.Tensor: ...

    def keep_text(self, task: str, prompt: str, prediction: str, reference: str) -> None: ...

    def keep_scene(self, kind: str, caption: str, panels: list[tuple]) -> None: ...

    def keep_forecast_picture(self, token: str, pred: np.ndarray, target: np.ndarray, n: int) -> None: ...

    def keep_plan_picture(self, name: str, anchor: dict, plan: np.ndarray, truth: np.ndarray) -> None: ...


@runtime_checkable
class Scorer(Protocol):
    """Grades one task's generated answers. ``metrics``: name -> a factory of the
    torchmetrics Metric it updates (an evaluator makes each name once, so scorers share a
    baseline by naming it alike); ``needs_semantics``: it reads the clip's label volumes.
    ``score(evaluator, item)`` updates metrics through ``evaluator.metrics[name]``;
    ``summary(prefix)`` adds derived numbers; ``reset()`` clears its own state."""

    metrics: dict[str, Callable[[], Metric]]
    needs_semantics: bool

    def score(self, evaluator: ScoringContext, item: Item) -> None: ...

    def summary(self, prefix: str) -> dict[str, float]: ...

    def reset(self) -> None: ...


#: Which clips an ``EvalHook`` scores: the first evaluated task's, or every frame with a
#: whole 3 s future (a forecast head's).
TASK_CLIPS, FUTURE_CLIPS = "task", "future"


@runtime_checkable
class EvalHook(Protocol):
    """Family-level scoring after the tasks' (e.g. an occupancy query branch), on the
    clips its ``clips`` names (``TASK_CLIPS`` or ``FUTURE_CLIPS``). ``applies(engine)``:
    whether it runs at all."""

    metrics: dict[str, Callable[[], Metric]]
    clips: str

    def applies(self, engine: WorldEngine) -> bool: ...

    def run(self, evaluator: ScoringContext, engine: WorldEngine, clips: list[Clip]) -> None: ...


@dataclass(frozen=True)
class Plans:
    """A planner's answer for a batch of clips: the waypoints it drives, and which of them
    are not its own (it had nothing to plan from, e.g. no meta action came out of the chain
    of thought, and drives on at constant velocity): closed loop counts those apart."""

    #: (B, 6, 2) metres in each anchor's ego frame, FRAME_DT apart.
    xy: np.ndarray
    #: (B,) bool: the row is the constant-velocity fallback.
    fell_back: np.ndarray

    @classmethod
    def own(cls, xy: np.ndarray) -> Plans:
        """Waypoints that are all the planner's own."""
        xy = np.asarray(xy, dtype=np.float64)
        return cls(xy, np.zeros(len(xy), dtype=bool))


@dataclass
class PlannerSettings:
    """Base of a family planner's settings (``WorldSpec.planner_config``, flat in a planner
    stage's ``model:``): what the planner stage asks of them, with defaults."""

    def validate(self, where: str) -> None:
        """Refuse settings that cannot work, in one line naming ``where``."""

    def needs_teacher(self) -> bool:
        """Whether the planner reads the consumed stage's world model (loaded, frozen)."""
        return True


class PlannerContext(Protocol):
    """What a family's planner is built from in a ``planner`` stage (``stages.StageContext``
    is one): the stage's name, its planner settings (``model:``, the family's
    ``WorldSpec.planner_config`` joined to the stage's), the run's dataset and the stage's
    own cache folder."""

    @property
    def spec(self) -> StageSpec: ...
    @property
    def model_cfg(self) -> DictConfig: ...
    @property
    def data(self) -> DataConfig: ...
    @property
    def cache_dir(self) -> Path: ...


class Planner(nn.Module, ABC):
    """What a ``planner`` stage trains, given the stage's settings and, when it reads one,
    the frozen world model of the consumed stage (``teacher``): a torch module, so the
    stage's optimizer, checkpoints and devices treat it as any other. ``monitor``: the
    validation metric that picks its best checkpoint (lower is better)."""

    monitor: str

    @abstractmethod
    def closed_loop_refusal(self) -> str | None:
        """Why its plans cannot drive closed loop (e.g. they read a logged input the
        closed loop does not have), or None."""

    @abstractmethod
    def sidecar_tasks(self) -> list[str]:
        """The frame-sidecar annotations it reads (the stage refuses a dataset without them)."""

    def prepare_training(self, device: torch.device) -> None:
        """Work done once before the first step (e.g. the world model's outputs for the
        training clips); nothing by default."""

    @abstractmethod
    def training_loss(self, clips: list[Clip]) -> torch.Tensor: ...

    @abstractmethod
    def validate(self, clips: list[Clip], batch_idx: int, generate_batches: int = -1) -> None:
        """Score a validation batch (``generate_batches``: how many batches may generate
        text, -1 every one)."""

    @abstractmethod
    def waypoints(self, clips: list[Clip]) -> Plans:
        """The stage's plan for each clip (``Plans.xy``: (B, 6, 2) metres in each anchor's
        ego frame): what it is scored on and what closed-loop driving follows, with the rows
        it had no plan of its own for."""

    @abstractmethod
    def compute(self, prefix: str) -> dict[str, float]:
        """The validation metrics gathered since the last call, keys under ``prefix``."""

    def save_cache(self) -> None:
        """Keep what it computed once (the world model's outputs) for the next attempt; nothing by default."""

    @abstractmethod
    def summary(self) -> tuple[str, dict[str, float]]:
        """The finished stage's one-line summary and metrics to add (its size, ...)."""

    @abstractmethod
    def export(self, path: Path) -> Path:
        """Write the trained planner (weights and config) into ``path``."""

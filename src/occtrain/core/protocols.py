"""The seams between the family-neutral engine and a family: declared once, checked when
a family registers (``core.registry.register_family``).

Subject to change while the families that use them settle; docs/adding-a-family.md
shows them in use.

- :class:`SceneEncoder`: occupancy -> what a world model's scene parts hold, and back:
  discrete codes (a VQ tokenizer's) or continuous tokens with their 3D positions.
- :class:`Scorer`: grades one task's generated answers with the papers' metrics and adds
  its baselines; :class:`EvalHook`: family-level scoring that belongs to no task (OccVLA's
  occupancy queries).
- :class:`PromptInputs`: what a sequence builder reads besides a prompt's parts (the
  engine's encodings of a dataset's frames), so a family's own part kinds can be laid out.
- :class:`Planner`: what the ``planner`` stage trains (OccVLA's MLP head on the meta
  action, a diffusion planner, ...), Lightning-free.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import torch


class PromptInputs(Protocol):
    """What a sequence builder's ``lay`` reads for the parts that hold no values of their
    own, by sample token: the world-model engine's cached image tokens Float[T, D] of a
    frame's cameras and its voxel labels Long[X, Y, Z]."""

    def image_tokens(self, token: str) -> torch.Tensor: ...

    def voxels(self, token: str) -> torch.Tensor: ...


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
class Scorer(Protocol):
    """Grades one task's generated answers. ``metrics``: name -> a factory of the
    torchmetrics Metric it updates (an evaluator makes each name once, so scorers share a
    baseline by naming it alike); ``needs_semantics``: it reads the clip's label volumes.
    ``score(evaluator, item)`` updates metrics through ``evaluator.metrics[name]``;
    ``summary(prefix)`` adds derived numbers; ``reset()`` clears its own state."""

    metrics: dict[str, Callable[[], Any]]
    needs_semantics: bool

    def score(self, evaluator: Any, item: Any) -> None: ...

    def summary(self, prefix: str) -> dict[str, float]: ...

    def reset(self) -> None: ...


@runtime_checkable
class EvalHook(Protocol):
    """Family-level scoring after the tasks' (e.g. an occupancy query branch), on the
    clips of the first evaluated task, or with a class attribute ``clips = "future"`` on
    every frame with a whole 3 s future (a forecast head's). ``applies(engine)``: whether
    it runs at all."""

    metrics: dict[str, Callable[[], Any]]

    def applies(self, engine: Any) -> bool: ...

    def run(self, evaluator: Any, engine: Any, clips: list) -> None: ...


@runtime_checkable
class Planner(Protocol):
    """What a ``planner`` stage trains, given the stage's settings and, when it reads one,
    the frozen world model of the consumed stage (``teacher``). A ``torch.nn.Module``."""

    def training_loss(self, clips: list) -> torch.Tensor | None: ...

    def validate(self, clips: list, batch_idx: int) -> None: ...

    def compute(self, prefix: str) -> dict[str, float]: ...

    def export(self, path: Path) -> Path: ...

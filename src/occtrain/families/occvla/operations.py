"""What OccVLA's model offers beyond its tasks' scoring: the reference and generated meta
actions and the visual summary its planning head reads, and the Python API's operations."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from occtrain.core import shared_operations
from occtrain.core.builder import collate
from occtrain.core.protocols import WorldEngine, family_tasks
from occtrain.data.clips import Clip, text_of
from occtrain.data.schema import MetaAction
from occtrain.families.occvla.config import TaskConfig
from occtrain.families.occvla.parts import Images
from occtrain.families.occvla.tasks import read_meta_action


def reference_meta_action(engine: WorldEngine, clip: Clip) -> MetaAction | None:
    """The clip's meta action labelled from the poses with the task settings' rules (the
    answer its ``meta_action`` task trains on); None where the clip is too short for it."""
    items = engine.task_items("meta_action", clip)
    return read_meta_action(text_of(items[0][-1]), clip, family_tasks(engine, TaskConfig)) if items else None


def generated_meta_actions(engine: WorldEngine, clips: list[Clip]) -> list[tuple[MetaAction | None, None] | None]:
    """Per clip, the meta action parsed from the generated chain of thought (None when it
    cannot be parsed; OccVLA generates no trajectory); None where the task does not apply."""
    out: list[tuple[MetaAction | None, None] | None] = [None] * len(clips)
    tasks = family_tasks(engine, TaskConfig)
    for b, _, generated, _ in engine.rollouts("meta_action", clips, {"ann": [c.ann for c in clips]}):
        out[b] = (read_meta_action(text_of(generated[0]), clips[b], tasks), None)
    return out


def meta_action(engine: WorldEngine, clip: Clip) -> MetaAction | None:
    """The meta action the generated chain of thought ends with, None if unparsed."""
    return read_meta_action(shared_operations.chain_of_thought(engine, clip)[0], clip, family_tasks(engine, TaskConfig))


@torch.no_grad()
def visual_summary(engine: WorldEngine, clips: list[Clip]) -> torch.Tensor:
    """(B, hidden): the world model's last-layer outputs at each anchor's image tokens,
    averaged (what the planning head reads of the scene)."""
    seqs = [engine.encode_parts([Images(c.anchor["token"])], {}) for c in clips]
    batch = collate(seqs, engine.vocab.pad_id)
    batch = {k: v.to(engine.world.device) if torch.is_tensor(v) else v for k, v in batch.items()}
    hidden = engine.world(batch, output_hidden_states=True).hidden.float()
    images = engine.vocab.is_image(batch["input_ids"]).float()[..., None]
    return (hidden * images).sum(1) / images.sum(1).clamp(min=1)


OPERATIONS: dict[str, Callable[..., Any]] = {
    "answer": shared_operations.answer,
    "chain_of_thought": shared_operations.chain_of_thought,
    "meta_action": meta_action,
    "reference_meta_action": reference_meta_action,
    "generated_meta_actions": generated_meta_actions,
    "visual_summary": visual_summary,
}

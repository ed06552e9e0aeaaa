"""What OccVLA's model offers beyond its tasks' scoring: the reference and generated meta
actions and the visual summary its planning head reads, and the Python API's operations."""

from __future__ import annotations

from typing import Any

import torch

from occtrain.core import shared_operations
from occtrain.core.builder import collate
from occtrain.data.clips import Clip
from occtrain.families.occvla.parts import Images
from occtrain.families.occvla.tasks import read_meta_action


def reference_meta_action(engine: Any, clip: Clip) -> dict | None:
    """The clip's meta action labelled from the poses with the task settings' rules (the
    answer its ``meta_action`` task trains on); None where the clip is too short for it."""
    items = engine.task_items("meta_action", clip)
    return read_meta_action(items[0][-1].text, clip, engine.tasks) if items else None


def generated_meta_actions(engine: Any, clips: list[Clip]) -> list[tuple[dict | None, None] | None]:
    """Per clip, the meta action parsed from the generated chain of thought (None when it
    cannot be parsed; OccVLA generates no trajectory); None where the task does not apply."""
    out: list = [None] * len(clips)
    for b, _, generated, _ in engine.rollouts("meta_action", clips, {"ann": [c.ann for c in clips]}):
        out[b] = (read_meta_action(generated[0].text, clips[b], engine.tasks), None)
    return out


def meta_action(engine: Any, clip: Clip) -> dict | None:
    """The meta action the generated chain of thought ends with, None if unparsed."""
    return read_meta_action(shared_operations.chain_of_thought(engine, clip)[0], clip, engine.tasks)


@torch.no_grad()
def visual_summary(engine: Any, clips: list[Clip]) -> torch.Tensor:
    """(B, hidden): the world model's last-layer outputs at each anchor's image tokens,
    averaged (what the planning head reads of the scene)."""
    seqs = [engine.encode_parts([Images(c.anchor["token"])], {}) for c in clips]
    batch = collate(seqs, engine.vocab.pad_id)
    batch = {k: v.to(engine.world.device) if torch.is_tensor(v) else v for k, v in batch.items()}
    hidden = engine.world(batch, output_hidden_states=True).hidden.float()
    images = engine.vocab.is_image(batch["input_ids"]).float()[..., None]
    return (hidden * images).sum(1) / images.sum(1).clamp(min=1)


OPERATIONS = {
    "answer": shared_operations.answer,
    "chain_of_thought": shared_operations.chain_of_thought,
    "meta_action": meta_action,
    "reference_meta_action": reference_meta_action,
    "generated_meta_actions": generated_meta_actions,
    "visual_summary": visual_summary,
}

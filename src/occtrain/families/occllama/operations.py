"""What OccLLaMA's world model offers beyond its tasks' scoring: the meta action its chain
of thought reasons to (what a planner stage reads) and the Python API's operations."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from occtrain.core import shared_operations
from occtrain.core.protocols import WorldEngine
from occtrain.core.scorers import said_meta_action
from occtrain.data.clips import Actions, Clip, Text
from occtrain.data.schema import MetaAction


def reference_meta_action(engine: WorldEngine, clip: Clip) -> MetaAction | None:
    """The clip's meta action: the frame sidecar's (the chain of thought ends with it)."""
    return clip.anchor.get("meta_action")


#: Per clip: the parsed meta action and the trajectory generated after it, or None.
GeneratedMeta = tuple[MetaAction | None, np.ndarray | None] | None


def generated_meta_actions(engine: WorldEngine, clips: list[Clip]) -> list[GeneratedMeta]:
    """Per clip, the meta action parsed from the generated chain of thought (None when it
    cannot be parsed) and the trajectory generated after it; None for a clip the chain of
    thought does not apply to (no known future or no narration)."""
    out: list[GeneratedMeta] = [None] * len(clips)
    for b, _, (text, traj), _ in engine.rollouts("cot_planning", clips, {"ann": [c.ann for c in clips]}):
        assert isinstance(text, Text) and isinstance(traj, Actions)  # cot_planning's answer: narration, then plan
        out[b] = (said_meta_action(text.text, clips[b]), np.asarray(traj.xy))
    return out


OPERATIONS: dict[str, Callable[..., Any]] = {
    "answer": shared_operations.answer,
    "plan": shared_operations.plan,
    "forecast": shared_operations.forecast,
    "chain_of_thought": shared_operations.chain_of_thought,
    "meta_action": shared_operations.meta_action,
    "reference_meta_action": reference_meta_action,
    "generated_meta_actions": generated_meta_actions,
    "scene_summary": shared_operations.scene_summary,
}

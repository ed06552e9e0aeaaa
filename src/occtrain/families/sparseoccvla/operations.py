"""What a trained SparseOccVLA model offers through the Python API (``occtrain.load``):
answer a question, describe the scene, state its decision, forecast the occupancy."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from occtrain.core import shared_operations
from occtrain.core.protocols import WorldEngine, family_world
from occtrain.data.clips import Clip, Text, text_of
from occtrain.families.sparseoccvla.tasks import FORECAST_PROMPT, context
from occtrain.families.sparseoccvla.world_model import SparseOccVLAWorldModel


def caption(engine: WorldEngine, clip: Clip) -> str:
    """The model's description of the anchor frame's scene."""
    generated, _ = shared_operations.generate_one(engine, "caption", clip)
    return text_of(generated[0]).strip()


def decision(engine: WorldEngine, clip: Clip) -> str:
    """The model's decision with its reasoning (what its planner reads)."""
    generated, _ = shared_operations.generate_one(engine, "planning", clip)
    return text_of(generated[0]).strip()


@torch.no_grad()
def forecast(engine: WorldEngine, clip: Clip) -> np.ndarray:
    """The forecast occupancy of the next frames (T, 200, 200, 16) uint8, from the forecaster's points."""
    a = clip.anchor_index
    rows = engine.scenes({"ann": [clip.ann]}, [{a}])[(0, a)]
    world = family_world(engine, SparseOccVLAWorldModel)
    steps = world.forecast(engine.encode_parts([*context(clip, engine.tasks), Text(FORECAST_PROMPT)], {a: rows}))
    return np.stack([world.voxelize(p, c).cpu().numpy().astype(np.uint8) for p, c in steps])


OPERATIONS: dict[str, Callable[..., Any]] = {
    "answer": shared_operations.answer,
    "caption": caption,
    "decision": decision,
    "forecast": forecast,
}

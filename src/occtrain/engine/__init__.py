"""The Lightning-free world-model engine: input encoding with its caches, sequence
building, rollout, evaluation, and export/load. Stages, ``occtrain eval``, the Python API
and the benchmarks use it; it never imports Lightning, a stage or a family."""

from __future__ import annotations

from occtrain.engine.evaluator import Evaluator, Priors, evaluation_clips, scorable
from occtrain.engine.export import export_engine, load_world_model, new_world_model
from occtrain.engine.speed import compare_generation_speed, speed_prompt
from occtrain.engine.world_engine import SCENE_CACHE, TEXT_ENTRIES, WorldModelEngine, move_batch

__all__ = [
    "SCENE_CACHE",
    "TEXT_ENTRIES",
    "Evaluator",
    "WorldModelEngine",
    "export_engine",
    "load_world_model",
    "Priors",
    "compare_generation_speed",
    "evaluation_clips",
    "move_batch",
    "new_world_model",
    "scorable",
    "speed_prompt",
]

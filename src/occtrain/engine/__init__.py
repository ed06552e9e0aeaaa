"""The Lightning-free world-model engine: scene encoding with the code cache, sequence
building, rollout and chain of thought, evaluation, and export/load. Stages, ``occtrain
eval`` and the benchmarks use it; it never imports Lightning or a stage."""

from __future__ import annotations

from occtrain.engine.evaluator import Evaluator, Priors, evaluation_clips
from occtrain.engine.export import export_engine, load_world_model, new_world_model
from occtrain.engine.speed import compare_generation_speed, speed_prompt
from occtrain.engine.world_model import CODE_CACHE, IMAGE_CACHE, TEXT_ENTRIES, CotOutput, WorldModelEngine, move_batch

__all__ = [
    "CODE_CACHE", "IMAGE_CACHE", "TEXT_ENTRIES", "CotOutput", "Evaluator", "WorldModelEngine", "export_engine", "load_world_model",
    "Priors", "compare_generation_speed", "evaluation_clips", "move_batch", "new_world_model", "speed_prompt",
]

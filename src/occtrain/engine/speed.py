"""Generation speed of world models compared side by side, one protocol for every caller.

Distillation's in-training validation and ``occtrain eval`` of a distilled stage both call
:func:`compare_generation_speed` with the same prompt (the first question of the split's
first frame, with its full scene context) and the same length, so their speedups measure
one thing. The engines are timed in turn, best of several rounds, because a shared
machine's noise only ever slows a round down.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from occtrain.core.sequence import TokenSequence
from occtrain.data.layout import DatasetIndex
from occtrain.engine.world_engine import WorldModelEngine

#: New tokens generated per timed round (end-of-text ignored, so every round is this long).
SPEED_TOKENS = 32
ROUNDS = 3


def speed_prompt(engine: WorldModelEngine, data_root: str | Path, split: str = "val") -> TokenSequence:
    """The timing prompt: the first question of the first frame of ``split`` that has one."""
    from occtrain.engine.evaluator import evaluation_clips

    index = DatasetIndex.open(data_root)
    clip = evaluation_clips(index, split, "qa", engine.tasks.context_frames)[0]
    parts = engine.task_items("qa", clip, every=True)[0]
    scenes = engine.scenes({"ann": [clip.ann]}, [set(range(len(clip.ann["tokens"])))]) if engine.reads_scenes() else {}
    prompt, _ = engine.prompt_and_plan(parts, {f: c for (_, f), c in scenes.items()})
    return prompt


@torch.no_grad()
def compare_generation_speed(
    engines: dict[str, WorldModelEngine], prompt: TokenSequence, new_tokens: int = SPEED_TOKENS
) -> dict[str, float]:
    """Greedy tokens per second of each engine on ``prompt``, ``new_tokens`` long."""
    best = {name: float("inf") for name in engines}
    for engine in engines.values():
        engine.world.generate_text(prompt, 2)  # warm-up: allocator, kernels
    for _ in range(ROUNDS):
        for name, engine in engines.items():
            start = time.perf_counter()
            engine.world.generate_text(prompt, new_tokens, stop_at_eos=False)
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: new_tokens / t for name, t in best.items()}

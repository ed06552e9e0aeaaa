"""Operations a trained world model offers through the Python API (``occtrain.load``) and
the planner stage, built on a family's tasks: answer a question about a scene, plan,
forecast, reason to a meta action. A family lists the ones its tasks support in
``WorldSpec.operations`` (and may add its own); each takes the engine first.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from occtrain.core.builder import collate
from occtrain.core.protocols import WorldEngine
from occtrain.core.scorers import said_meta_action
from occtrain.data.clips import Actions, Clip, PromptPart, Scene, Text
from occtrain.data.schema import MetaAction
from occtrain.errors import ConfigError


def generate_one(engine: WorldEngine, task: str, clip: Clip) -> tuple[list, dict]:
    """The generated parts (and scenes) of ``task``'s one prompt on ``clip``: what a family's
    own operation (``WorldSpec.operations``) builds its result from."""
    if task not in engine.task_specs:
        raise ConfigError(f"the '{engine.family}' world model has no task '{task}'")
    out = list(engine.rollouts(task, [clip], _batch(engine, clip), batched=False))
    if not out:
        raise ConfigError(
            f"task '{task}' does not apply to sample {clip.anchor['token']} (its future or its text is not known)"
        )
    _, _, generated, scenes = out[0]
    return generated, scenes


def answer(engine: WorldEngine, clip: Clip, question: str) -> str:
    """The model's answer to ``question`` about ``clip``'s anchor frame."""
    asked = replace(
        clip,
        qa=[
            {
                "question": question,
                "answer": "",
                "sample_token": clip.anchor["token"],
                "template_type": "exist",
                "num_hop": 0,
            }
        ],
    )
    spec = engine.task_specs.get("qa")
    if spec is None or spec.every_item is None:
        raise ConfigError(f"the '{engine.family}' world model answers no questions")
    parts = spec.every_item(asked, engine.tasks)[0]
    prefix, plan = engine.prompt_and_plan(parts, _context_scenes(engine, clip, parts))
    return engine.vocab.decode_text(engine.world.generate(prefix, plan)[0]).strip()


def _context_scenes(engine: WorldEngine, clip: Clip, parts: list) -> dict[int, torch.Tensor]:
    frames = {p.frame for p in parts if isinstance(p, Scene) and not p.supervise}
    rows = engine.scenes(_batch(engine, clip), [frames])
    return {f: rows[(0, f)] for f in frames}


def _batch(engine: WorldEngine, clip: Clip) -> dict:
    batch: dict = {"ann": [clip.ann]}
    if engine.needs_semantics():
        index = engine.data_index
        if index is None:
            raise ValueError("the engine reads label volumes: prepare it on a dataset first (prepare_inputs)")
        batch["semantics"] = [
            torch.from_numpy(np.stack([index.labels(index.scene_of(t), t)["semantics"] for t in clip.ann["tokens"]]))
        ]
    return batch


def plan(engine: WorldEngine, clip: Clip) -> np.ndarray:
    """The ego's plan (steps, 2) in the anchor's ego frame: the planning task's, or the
    waypoints a forecast alternates with its scenes (a family without a planning task)."""
    if "planning" in engine.task_specs:
        generated, _ = generate_one(engine, "planning", clip)
        return np.asarray([p for p in generated if isinstance(p, Actions)][-1].xy)
    generated, _ = generate_one(engine, "forecasting", clip)
    return np.asarray([pt for p in generated if isinstance(p, Actions) for pt in p.xy])


def forecast(engine: WorldEngine, clip: Clip) -> np.ndarray:
    """The forecast scenes (T, 200, 200, 16) uint8, decoded by the scene encoder."""
    generated, scenes = generate_one(engine, "forecasting", clip)
    rows = torch.stack([scenes[p.frame] for p in generated if isinstance(p, Scene)])
    return engine.decode_scenes(rows).cpu().numpy().astype(np.uint8)


def chain_of_thought(engine: WorldEngine, clip: Clip) -> tuple[str, np.ndarray | None]:
    """The chain of thought's text and, when the task plans after it, its trajectory (6, 2)."""
    task = "cot_planning" if "cot_planning" in engine.task_specs else "meta_action"
    generated, _ = generate_one(engine, task, clip)
    text = next(p.text for p in generated if isinstance(p, Text))
    actions = [p for p in generated if isinstance(p, Actions)]
    return text, (np.asarray(actions[-1].xy) if actions else None)


def meta_action(engine: WorldEngine, clip: Clip) -> MetaAction | None:
    """The meta action the chain of thought ends with ({"speed", "direction"}), None if unparsed."""
    return said_meta_action(chain_of_thought(engine, clip)[0], clip)


def scene_summary(engine: WorldEngine, clips: list[Clip]) -> torch.Tensor:
    """(B, hidden): the world model's last-layer outputs at each anchor's scene tokens,
    averaged: what a planning head reads of the occupancy the world model sees (as OccVLA's
    reads its image tokens, ``visual_summary``)."""
    seqs = []
    for clip in clips:
        parts: list[PromptPart] = [Scene(clip.anchor_index)]
        seqs.append(engine.encode_parts(parts, _context_scenes(engine, clip, parts)))
    batch = collate(seqs, engine.vocab.pad_id)
    batch = {k: v.to(engine.world.device) if torch.is_tensor(v) else v for k, v in batch.items()}
    hidden = engine.world(batch, output_hidden_states=True).hidden.float()
    scene = engine.vocab.is_occ(batch["input_ids"]).float()[..., None]
    return (hidden * scene).sum(1) / scene.sum(1).clamp(min=1)

"""Occ-LLM's tasks (Sec. III-C), switched by the paper's prompts.

``forecasting``: "<4-D occupancy forecasting and self-ego planning>" asks for the future
frames with the ego's waypoints alternating with them (waypoint k then frame k); the
evaluator scores the scenes as the forecast and the waypoints as the plan. ``qa``:
"<question-answering>" asks NuScenes-QA questions. Both start from the same context: each
history frame and the anchor frame, each right after the ego's position at that frame (in
the anchor's ego axes), so pre-fusion gates every scene with the action that reached it
and a forecast frame with the waypoint generated for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.core import scorers
from occtrain.core.shared_tasks import (
    ForecastTaskConfig,
    TaskSpec,
    as_xy,
    each_question,
    forecast_after,
    questions_after,
)
from occtrain.data.clips import Actions, Clip, Part, Scene, Text

FORECAST_PROMPT = "<4-D occupancy forecasting and self-ego planning>"
QA_PROMPT = "<question-answering>"
#: Fixed words of the prompts, for the world model's text tokenizer.
PROMPT_WORDS = (FORECAST_PROMPT, QA_PROMPT)


@dataclass
class TaskConfig(ForecastTaskConfig):
    """Occ-LLM's task settings: history frames, forecast length, questions per sequence."""


def _context(clip: Clip, cfg: TaskConfig) -> list[Part]:
    """Each history frame and the anchor frame, after the ego's position at it."""
    a = clip.anchor_index
    positions = clip.ego_positions()
    parts: list[Part] = []
    for f in range(max(0, a - cfg.context_frames), a + 1):
        parts += [Actions(as_xy(positions[f])), Scene(f)]
    return parts


def forecasting(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """4-D occupancy forecasting and self-ego planning: waypoint k, then frame k, ``forecast_frames`` times."""
    return forecast_after([*_context(clip, cfg), Text(FORECAST_PROMPT)], clip, cfg.forecast_frames, cfg.plan_prior)


def qa(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Occupancy-based question answering on the anchor frame."""
    return questions_after([*_context(clip, cfg), Text(QA_PROMPT)], clip, cfg, rng)


def every_question(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    """One prompt per question of the anchor frame (evaluation asks them all)."""
    return each_question([*_context(clip, cfg), Text(QA_PROMPT)], clip)


#: The forecast is scored as a forecast and its waypoints as a plan (the paper's two results).
TASKS = {
    "forecasting": TaskSpec(
        forecasting, scorer=(scorers.ForecastScorer, scorers.plan_scorer("plan_alternate", alternate=True))
    ),
    "qa": TaskSpec(qa, every_question, scorers.QAScorer),
}

"""SparseOccVLA's tasks (Sec. 3.2-3.3, 4.1): every prompt starts with the anchor frame's
occupancy tokens, the global tokens and the ego-state token, then:

``caption``: the scene description (OmniDrive-nuScenes' ``desc`` where an OmniDrive root
is given and holds the frame, else the frame's own caption). ``conversation``: OmniDrive's
conversation and VQA pairs (with an OmniDrive root). ``qa``: NuScenes-QA. ``planning``: the
decision with its reasoning (the narration's plan and meta-action lines), whose tokens the
anchor-diffusion planner reads. ``forecast``: no text answer; the forecaster's points for
the next 3 s against each frame's ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.core import scorers
from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig
from occtrain.core.shared_tasks import TaskSpec, each_question, questions_after
from occtrain.data.clips import Clip, Part, Scene, Text
from occtrain.families.sparseoccvla.omnidrive import omnidrive
from occtrain.families.sparseoccvla.scoring import CaptionScorer, ConversationScorer, DecisionScorer
from occtrain.families.sparseoccvla.world_model import Ego, Forecast, ego_state

CAPTION_PROMPT = "Describe the current driving scene."
PLANNING_PROMPT = "What should the ego car do next, and why?"
FORECAST_PROMPT = "Forecast the next 3 seconds."
PROMPT_WORDS = (CAPTION_PROMPT, PLANNING_PROMPT, FORECAST_PROMPT, "Plan:", "Meta action:")
#: The lines of a synthetic narration that state the decision (its reasoning and meta action).
DECISION_LINES = ("Plan:", "Meta action:")


@dataclass
class TaskConfig(BaseTaskConfig):
    """SparseOccVLA's task settings. Its prompts hold the anchor frame's scene alone (the
    encoder reads the earlier frames' images itself)."""

    context_frames: int = 0
    #: An OmniDrive-nuScenes root (``desc/``, ``conv/``, ``vqa/``, ``keywords/``) whose text
    #: the caption and conversation tasks read; empty: the dataset's own captions only.
    omnidrive: str = ""
    #: Future frames the forecast task supervises (at 0.5 s; 6 = 3 s).
    forecast_frames: int = 6


def context(clip: Clip, cfg: BaseTaskConfig) -> list[Part]:
    """The anchor's occupancy tokens (with the global tokens) and the ego-state token
    (whatever the task settings: none of them changes the context)."""
    return [Scene(clip.anchor_index), Ego(ego_state(clip.anchor))]


def description(clip: Clip, cfg: TaskConfig) -> str:
    token = clip.anchor["token"]
    text = omnidrive(cfg.omnidrive).description(token) if cfg.omnidrive else None
    return text if text is not None else clip.anchor.get("caption", "")


def caption(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    text = description(clip, cfg)
    return [*context(clip, cfg), Text(CAPTION_PROMPT), Text(text, True)] if text else None


def _pair(clip: Clip, cfg: TaskConfig, q: dict) -> list[Part]:
    return [*context(clip, cfg), Text(f"Question: {q['question']} Answer:"), Text(q["answer"], True)]


def conversation(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    pairs = omnidrive(cfg.omnidrive).pairs(clip.anchor["token"]) if cfg.omnidrive else []
    return _pair(clip, cfg, pairs[int(rng.integers(len(pairs)))]) if pairs else None


def every_pair(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    pairs = omnidrive(cfg.omnidrive).pairs(clip.anchor["token"]) if cfg.omnidrive else []
    return [_pair(clip, cfg, q) for q in pairs]


def decision(clip: Clip) -> str | None:
    """The narration's decision lines (its plan and meta action), or None without them."""
    lines = [line for line in clip.anchor.get("narration", "").splitlines() if line.startswith(DECISION_LINES)]
    return " ".join(lines) if lines else None


def planning(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    text = decision(clip)
    return [*context(clip, cfg), Text(PLANNING_PROMPT), Text(text, True)] if text else None


def forecast(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """The next ``forecast_frames`` frames' occupancy; None unless the clip holds them."""
    a, tokens = clip.anchor_index, clip.ann["tokens"]
    future = tokens[a + 1 : a + 1 + cfg.forecast_frames]
    if len(future) < cfg.forecast_frames:
        return None
    return [*context(clip, cfg), Text(FORECAST_PROMPT), Forecast(tuple(future))]


def qa(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    return questions_after(context(clip, cfg), clip, cfg, rng)


def every_question(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    return each_question(context(clip, cfg), clip)


TASKS = {
    "caption": TaskSpec(caption, scorer=CaptionScorer),
    "conversation": TaskSpec(conversation, every_pair, scorer=ConversationScorer),
    "qa": TaskSpec(qa, every_question, scorers.QAScorer),
    "planning": TaskSpec(planning, scorer=DecisionScorer),
    "forecast": TaskSpec(forecast),
}

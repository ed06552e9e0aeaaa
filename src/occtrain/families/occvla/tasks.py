"""OccVLA's tasks (Sec. 3.3, App. D): each prompt starts with the six current camera views
as image tokens and, when the occupancy weight is above 0, the occupancy query block that
is trained on the anchor's voxels (nothing after it sees it).

``meta_action``: the past meta actions (t-5 .. t-1) in, the chain of thought out: the
scene description, the history analysis from the past meta actions, then the future meta
action in ``text_formats``' fixed sentence (``chain_of_thought: false``: the sentence
alone, Table 7's "without CoT"). ``qa``: NuScenes-QA. ``caption``: the scene description
alone (stage 1's driving-scene pretraining). Meta actions are labelled from the clip's ego
poses by ``data.meta_actions`` with the task settings' rules.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from occtrain.core import scorers
from occtrain.core.scorers import last_past_meta_action
from occtrain.core.shared_tasks import TaskSpec, each_question, questions_after
from occtrain.data.clips import Clip, Part, Text
from occtrain.data.meta_actions import label, past_labels
from occtrain.data.schema import MetaAction
from occtrain.data.text_formats import caption_surroundings, format_meta_action, meta_action_words, parse_meta_action
from occtrain.families.occvla.config import TaskConfig
from occtrain.families.occvla.parts import Images, Occupancy
from occtrain.families.occvla.scoring import MetaActionScorer
from occtrain.formats.occ3d import FRAME_DT

META_PROMPT = "Past meta actions:"
META_QUESTION = "What is the next meta action?"
CAPTION_PROMPT = "Describe the driving scene."
PROMPT_WORDS = (META_PROMPT, META_QUESTION, CAPTION_PROMPT, "Scene:", "History:", "none known")

#: Past-tense words of the history analysis.
_SPEED_PAST = {"accelerate": "sped up", "decelerate": "slowed down", "maintain": "kept its speed"}
_DIRECTION_PAST = {
    "straight": "went straight",
    "left": "turned left",
    "right": "turned right",
    "bear left": "bore left",
    "bear right": "bore right",
    "stop": "stood still",
}


def context(clip: Clip, cfg: TaskConfig) -> list[Part]:
    """The anchor's camera views, then its occupancy queries (when weighted)."""
    token = clip.anchor["token"]
    parts: list[Part] = [Images(token)]
    if cfg.occupancy_weight > 0:
        parts.append(Occupancy(token, cfg.occupancy_weight))
    return parts


def _poses(clip: Clip) -> np.ndarray:
    return np.asarray(clip.ann["ego_poses"], dtype=np.float64).reshape(-1, 3)


def future_meta_action(clip: Clip, cfg: TaskConfig) -> MetaAction | None:
    """The anchor's meta action, when the clip holds the whole direction window after it."""
    a, poses = clip.anchor_index, _poses(clip)
    if a + cfg.meta_actions.steps(cfg.meta_actions.direction_window_s) >= len(poses):
        return None
    return label(poses, a, cfg.meta_actions)


def past_meta_actions(clip: Clip, cfg: TaskConfig) -> list[MetaAction]:
    return past_labels(_poses(clip), clip.anchor_index, cfg.past_meta_actions, cfg.meta_actions)


def read_meta_action(text: str, clip: Clip, cfg: TaskConfig) -> MetaAction | None:
    """The meta action an answer ends with, "as before" read as the last past one."""
    return parse_meta_action(text, last_past_meta_action(clip, cfg.meta_actions))


def describe_past(past: list[MetaAction]) -> str:
    """The prompt's list of past meta actions, oldest first."""
    if not past:
        return f"{META_PROMPT} none known."
    return f"{META_PROMPT} " + "; ".join(meta_action_words(m) for m in past) + "."


def history_analysis(past: list[MetaAction]) -> str:
    """The chain of thought's second step: what the past meta actions show."""
    if not past:
        return "History: no earlier motion is known."
    speed = Counter(m["speed"] for m in past).most_common(1)[0][0]
    direction = Counter(m["direction"] for m in past).most_common(1)[0][0]
    last = past[-1]
    return (
        f"History: over the last {len(past) * FRAME_DT:g} s the ego mostly {_SPEED_PAST[speed]} and "
        f"{_DIRECTION_PAST[direction]}; lately it {_SPEED_PAST[last['speed']]} and "
        f"{_DIRECTION_PAST[last['direction']]}."
    )


def chain_of_thought(clip: Clip, cfg: TaskConfig, past: list[MetaAction], meta: MetaAction) -> str:
    """Scene description -> history analysis -> meta action (or the meta action alone)."""
    previous = past[-1] if past and cfg.meta_action_prior == "repeat_last" else None
    answer = format_meta_action(meta, previous)
    if not cfg.chain_of_thought:
        return answer
    caption = clip.anchor.get("caption", "")
    if cfg.cot_scene == "surroundings":
        caption = caption_surroundings(caption)
    scene = f"Scene: {caption} " if caption else ""
    return f"{scene}{history_analysis(past)} {answer}"


def meta_action(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Past meta actions in; chain of thought and the future meta action out."""
    meta = future_meta_action(clip, cfg)
    if meta is None:
        return None
    past = past_meta_actions(clip, cfg)
    return [
        *context(clip, cfg),
        Text(f"{describe_past(past)} {META_QUESTION}"),
        Text(chain_of_thought(clip, cfg, past, meta), True),
    ]


def caption(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """The scene description alone (from the frame's caption)."""
    text = clip.anchor.get("caption", "")
    if not text:
        return None
    return [*context(clip, cfg), Text(CAPTION_PROMPT), Text(text, True)]


def qa(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """NuScenes-QA questions about the anchor frame, from its camera views."""
    return questions_after(context(clip, cfg), clip, cfg, rng)


def every_question(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    return each_question(context(clip, cfg), clip)


TASKS = {
    "meta_action": TaskSpec(meta_action, scorer=MetaActionScorer),
    "qa": TaskSpec(qa, every_question, scorers.QAScorer),
    "caption": TaskSpec(caption),
}

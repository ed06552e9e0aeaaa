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
from dataclasses import dataclass, field

import numpy as np

from occtrain.core import scorers
from occtrain.core.scorers import last_past_meta_action
from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig
from occtrain.core.shared_tasks import TaskSpec, each_question, questions_after
from occtrain.data.clips import Clip, Part, Text
from occtrain.data.meta_actions import MetaActionConfig, label, past_labels
from occtrain.data.schema import MetaAction
from occtrain.data.text_formats import caption_surroundings, format_meta_action, meta_action_words, parse_meta_action
from occtrain.errors import ConfigError
from occtrain.families.occvla.parts import Images, Occupancy
from occtrain.families.occvla.scoring import MetaActionScorer
from occtrain.formats.occ3d import FRAME_DT

META_PROMPT = "Past meta actions:"
META_QUESTION = "What is the next meta action?"
CAPTION_PROMPT = "Describe the driving scene."
COT_SCENES = ("surroundings", "caption")
#: ``meta_action_prior`` values, the paper's first.
META_ACTION_PRIORS = ("none", "repeat_last")
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


@dataclass
class TaskConfig(BaseTaskConfig):
    """OccVLA's task settings: its prompts, the chain of thought and the occupancy loss."""

    #: History frames of a clip (the past meta actions t-5 .. t-1 read the poses back to t-6).
    context_frames: int = 6
    #: lambda_occ (Eq. 3): the weight of the occupancy-query loss beside the text loss in
    #: every sequence; 0 leaves the queries out.
    occupancy_weight: float = 1.0
    #: The answer reasons (scene, history) before the meta action (Table 7).
    chain_of_thought: bool = True
    #: The chain's scene step: "surroundings", the caption without its opening clause on the
    #: ego's own motion, or "caption", the whole caption. That clause states the frame's
    #: meta action, so under teacher forcing the model learns to copy it into the answer,
    #: and at inference it guesses the clause from the cameras and copies the guess over the
    #: prompt's history (docs/families/occllama.md, "Switches beyond the papers").
    cot_scene: str = "surroundings"
    #: How the answer writes its meta action. "none" (the paper): always as speed and
    #: direction. "repeat_last": "as before" when it equals the last past one, which the
    #: prompt lists, so keeping it is one phrase and the model learns when it changes
    #: (docs/families/occllama.md, "Switches beyond the papers").
    meta_action_prior: str = "none"
    #: Past meta actions in the prompt (t-5 .. t-1; fewer where the clip's history is shorter).
    past_meta_actions: int = 5
    #: How meta actions are labelled from the ego poses.
    meta_actions: MetaActionConfig = field(default_factory=MetaActionConfig)

    def __post_init__(self) -> None:
        if isinstance(self.meta_actions, dict):  # as an export's config.json holds it
            self.meta_actions = MetaActionConfig(**self.meta_actions)

    def validate(self, key: str) -> None:
        super().validate(key)
        if self.occupancy_weight < 0:
            raise ConfigError(
                f"{key}.occupancy_weight: {self.occupancy_weight} is negative (paper: 1; 0 turns the occupancy queries "
                "off)"
            )
        if self.past_meta_actions < 0:
            raise ConfigError(f"{key}.past_meta_actions: {self.past_meta_actions} is negative (paper: 5)")
        self.meta_actions.validate(f"{key}.meta_actions")
        if self.meta_action_prior not in META_ACTION_PRIORS:
            raise ConfigError(
                f"{key}.meta_action_prior: {self.meta_action_prior!r} is not one of {', '.join(META_ACTION_PRIORS)} "
                "(paper: none)"
            )
        if self.cot_scene not in COT_SCENES:
            raise ConfigError(f"{key}.cot_scene: {self.cot_scene!r} is not one of {', '.join(COT_SCENES)}")


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

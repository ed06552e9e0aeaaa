"""OccLLaMA's tasks and prompt formats: prompt-answer parts built from one clip.

A task turns a clip (``occtrain.data.clips``) into a list of parts: text, an occupancy
scene (by its frame index in the clip) or action waypoints, each marked as supervised (the
answer) or not (the prompt). ``occllama.world_model`` lays them out in the joint
vocabulary. Pretraining tasks follow OccLLaMA Sec. III-C (detection, counting,
prediction, planning, forecasting); instruction tasks are NuScenes-QA and
chain-of-thought planning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.core import scorers
from occtrain.core.scorers import last_past_meta_action
from occtrain.core.shared_tasks import (
    ForecastTaskConfig,
    TaskSpec,
    as_xy,
    each_question,
    ego_plan,
    forecast_after,
    known_future,
    questions_after,
)
from occtrain.data.clips import Actions, Clip, Part, Scene, Text
from occtrain.data.text_formats import format_meta_action, meta_action_words, parse_meta_action
from occtrain.errors import ConfigError

#: ``meta_action_prior`` values, the paper's first.
META_ACTION_PRIORS = ("none", "repeat_last")
PRETRAIN_TASKS = ("detection", "counting", "prediction", "planning", "forecasting")
INSTRUCT_TASKS = ("qa", "cot_planning")
#: Box categories the detection and counting tasks talk about (movable objects).
OBJECT_CLASSES = (
    "car",
    "truck",
    "bus",
    "trailer",
    "construction_vehicle",
    "pedestrian",
    "motorcycle",
    "bicycle",
    "barrier",
    "traffic_cone",
)


@dataclass
class TaskConfig(ForecastTaskConfig):
    """Which tasks an OccLLaMA world-model stage trains on, and how their prompts look
    (paper: 4 history scenes, a forecast of 6 = 3 s)."""

    #: At most this many objects in a detection answer (nearest first).
    max_objects: int = 6
    #: How the chain of thought ends. "none" (the paper's form): the narration's meta
    #: action. "repeat_last": the prompt states the last past meta action and the chain
    #: of thought says "as before" when it is unchanged (occtrain's; the narration alone
    #: leaves the model to guess the future motion and copy its guess).
    meta_action_prior: str = "none"

    def validate(self, key: str) -> None:
        super().validate(key)
        if self.meta_action_prior not in META_ACTION_PRIORS:
            raise ConfigError(
                f"{key}.meta_action_prior: {self.meta_action_prior!r} is not one of {', '.join(META_ACTION_PRIORS)} "
                "(paper: none)"
            )


def _context(clip: Clip, cfg: TaskConfig) -> list[Part]:
    """History scenes with the ego's moves between them, the anchor scene, command and ego past."""
    a = clip.anchor_index
    first = max(0, a - cfg.context_frames)
    steps = clip.ego_steps()
    parts: list[Part] = []
    for f in range(first, a):
        parts += [Scene(f), Actions(as_xy(steps[f]))]
    parts.append(Scene(a))
    anchor = clip.anchor
    past = np.asarray(anchor.get("ego_past", []), dtype=np.float64).reshape(-1, 2)
    past_mask = np.asarray(anchor.get("ego_past_mask", []), dtype=bool)
    # Real data without occtrain's sidecar has no command or speed: say nothing rather
    # than a made-up "go straight" at 0 m/s.
    state = []
    if "command" in anchor:
        state.append(f"Command: {anchor['command']}.")
    if "ego_speed" in anchor:
        state.append(f"Ego speed {anchor['ego_speed']:.1f} m/s.")
    if "ego_accel" in anchor:  # from the past only (``kinematics.past_acceleration``)
        state.append(f"Ego acceleration {anchor['ego_accel']:.1f} m/s2.")
    if state:
        parts.append(Text(" ".join(state)))
    if past_mask.any():
        parts += [Text("Ego past:"), Actions(as_xy(past[past_mask]))]
    return parts


def _objects(anchor: dict) -> list[dict]:
    boxes = [b for b in anchor.get("boxes", []) if b["category"] in OBJECT_CLASSES]
    return sorted(boxes, key=lambda b: float(np.hypot(*b["center"][:2])))


def detection(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Categories in language, positions as action bins, nearest objects first."""
    boxes = _objects(clip.anchor)[: cfg.max_objects]
    answer: list[Part] = []
    for b in boxes:
        answer += [Text(b["category"].replace("_", " "), True), Actions(as_xy(b["center"][:2]), True)]
    if not answer:
        answer = [Text("no objects", True)]
    return [*_context(clip, cfg), Text("Task: detect the nearest objects.")] + answer


def counting(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """How many objects of one category (present or not) are in the scene."""
    category = OBJECT_CLASSES[int(rng.integers(len(OBJECT_CLASSES)))]
    n = sum(b["category"] == category for b in clip.anchor.get("boxes", []))
    noun = category.replace("_", " ")
    return [*_context(clip, cfg), Text(f"Task: count the {noun} objects."), Text(str(n), True)]


def prediction(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """The 3 s future of one moving object whose whole future is known."""
    anchor = clip.anchor
    masks = anchor.get("agent_future_mask", [])
    candidates = [
        i
        for i, b in enumerate(anchor.get("boxes", []))
        if b.get("attribute") == "moving" and i < len(masks) and all(masks[i])
    ]
    if not candidates:
        return None
    i = candidates[int(rng.integers(len(candidates)))]
    box = anchor["boxes"][i]
    return [
        *_context(clip, cfg),
        Text(f"Task: predict the future of the {box['category'].replace('_', ' ')} at"),
        Actions(as_xy(box["center"][:2])),
        Actions(as_xy(anchor["agent_futures"][i]), True),
    ]


def planning(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """The ego's 3 s trajectory (6 waypoints, anchor ego frame) as action tokens."""
    future = known_future(clip)
    if future is None:
        return None
    return [*_context(clip, cfg), Text("Task: plan the ego trajectory."), ego_plan(future, clip, cfg.plan_prior)]


def forecasting(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Alternate the next waypoint and the next scene, ``forecast_frames`` times."""
    return forecast_after(
        [*_context(clip, cfg), Text("Task: forecast the scene.")], clip, cfg.forecast_frames, cfg.plan_prior
    )


def qa(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """NuScenes-QA questions about the anchor frame: one, or ``questions_per_sample`` packed."""
    return questions_after(_context(clip, cfg), clip, cfg, rng)


def every_question(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    """One prompt per NuScenes-QA question of the anchor frame (evaluation asks them all)."""
    return each_question(_context(clip, cfg), clip)


def cot_planning(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Chain of thought: narration, then the meta action, then the trajectory."""
    future = known_future(clip)
    if future is None or not clip.narration:
        return None
    # The narration ends with the meta action (older sidecars may lack it): written again
    # here, "as before" under the repeat-last prior.
    lines = clip.narration.rstrip().split("\n")
    if parse_meta_action(lines[-1]) is not None:
        lines = lines[:-1]
    prompt = [*_context(clip, cfg)]
    previous = None
    if cfg.meta_action_prior == "repeat_last":
        previous = last_past_meta_action(clip)
        prompt.append(Text(f"Last meta action: {meta_action_words(previous) + '.' if previous else 'none known.'}"))
    text = "\n".join([*lines, format_meta_action(clip.anchor["meta_action"], previous)])
    return [
        *prompt,
        Text("Task: describe the scene, then plan."),
        Text(text, True),
        ego_plan(future, clip, cfg.plan_prior),
    ]


#: The tasks, with what evaluation asks of each and how it is scored (M0-M3: planning
#: directly, alternating with forecast scenes, after the chain of thought).
TASKS = {
    "detection": TaskSpec(detection),
    "counting": TaskSpec(counting),
    "prediction": TaskSpec(prediction),
    "planning": TaskSpec(planning, scorer=scorers.plan_scorer("plan_direct", record=True)),
    "forecasting": TaskSpec(
        forecasting, scorer=(scorers.ForecastScorer, scorers.plan_scorer("plan_alternate", alternate=True))
    ),
    "qa": TaskSpec(qa, every_question, scorers.QAScorer),
    "cot_planning": TaskSpec(cot_planning, scorer=(scorers.ChainOfThoughtScorer, scorers.plan_scorer("plan_cot"))),
}

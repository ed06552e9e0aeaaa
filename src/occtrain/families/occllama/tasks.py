"""OccLLaMA's tasks and prompt formats: prompt-answer parts built from one clip.

A task turns a clip (``occtrain.data.clips``) into a list of parts: text, an occupancy
scene (by its frame index in the clip) or action waypoints, each marked as supervised (the
answer) or not (the prompt). ``occllama.world_model`` lays them out in the joint
vocabulary. Pretraining tasks follow OccLLaMA Sec. III-C (detection, counting,
prediction, planning, forecasting); instruction tasks are NuScenes-QA and
chain-of-thought planning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from occtrain.data.meta_actions import MetaActionConfig
from occtrain.data.clips import Actions, Branch, Clip, Part, Scene, Text, clip_rng, ego_future
from occtrain.data.text_formats import format_meta_action, parse_meta_action
from occtrain.errors import ConfigError

PRETRAIN_TASKS = ("detection", "counting", "prediction", "planning", "forecasting")
INSTRUCT_TASKS = ("qa", "cot_planning")
#: Box categories the detection and counting tasks talk about (movable objects).
OBJECT_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle", "bicycle", "barrier", "traffic_cone")


@dataclass
class TaskConfig:
    """Which tasks a world-model stage trains on, and how their prompts look."""

    #: Task name -> sampling weight; a task missing here is not used. Empty: the family's
    #: default tasks for the stage kind (``FamilySpec.default_tasks``). A recipe's mapping
    #: is the whole set: merged onto a non-empty default it could only add tasks.
    weights: dict[str, float] = field(default_factory=dict)
    #: History scenes in the prompt (paper: 4), besides the anchor scene.
    context_frames: int = 4
    #: Future scenes the forecasting task alternates with waypoints (paper: 6 = 3 s).
    forecast_frames: int = 6
    #: At most this many objects in a detection answer (nearest first).
    max_objects: int = 6
    #: NuScenes-QA questions about one frame per training sequence (paper: 1). Above 1 they
    #: are packed as branches that share the frame's context and do not see each other, so
    #: each is learned exactly as alone, for a fraction of the compute.
    questions_per_sample: int = 1
    #: OccVLA's lambda_occ (Eq. 3): the weight of the occupancy-query loss beside the text
    #: loss in every sequence, for a family with occupancy queries; 0 leaves them out.
    occupancy_weight: float = 1.0
    #: OccVLA: the answer reasons (scene, history) before the meta action (Table 7).
    chain_of_thought: bool = True
    #: OccVLA: past meta actions in the prompt (t-5 .. t-1; fewer where the clip's history is shorter).
    past_meta_actions: int = 5
    #: How OccVLA's meta actions are labelled from the ego poses.
    meta_actions: MetaActionConfig = field(default_factory=MetaActionConfig)

    def __post_init__(self) -> None:
        if isinstance(self.meta_actions, dict):  # as an export's config.json holds it
            self.meta_actions = MetaActionConfig(**self.meta_actions)


def as_xy(points) -> tuple[tuple[float, float], ...]:
    """Waypoints (any (..., 2) array) as the tuples an ``Actions`` part holds."""
    return tuple((float(x), float(y)) for x, y in np.asarray(points, dtype=np.float64).reshape(-1, 2))


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
        i for i, b in enumerate(anchor.get("boxes", []))
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


def known_future(clip: Clip) -> np.ndarray | None:
    """The anchor's 3 s ego future (6, 2), or None unless all of it is known."""
    future, mask = ego_future(clip.anchor)
    return future if mask.all() else None


def planning(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """The ego's 3 s trajectory (6 waypoints, anchor ego frame) as action tokens."""
    future = known_future(clip)
    if future is None:
        return None
    return [*_context(clip, cfg), Text("Task: plan the ego trajectory."), Actions(as_xy(future), True)]


def forecast_after(prompt: list[Part], clip: Clip, cfg: TaskConfig) -> list[Part] | None:
    """``prompt``, then the next waypoint and the next scene alternating, ``forecast_frames``
    times; None unless the clip's future is known."""
    a = clip.anchor_index
    n = min(cfg.forecast_frames, int(clip.ann["future"]))
    future = known_future(clip)
    if future is None or n == 0:
        return None
    parts = list(prompt)
    for k in range(n):
        parts += [Actions(as_xy(future[k]), True), Scene(a + 1 + k, True)]
    return parts


def forecasting(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Alternate the next waypoint and the next scene, ``forecast_frames`` times."""
    return forecast_after([*_context(clip, cfg), Text("Task: forecast the scene.")], clip, cfg)


def question_parts(q: dict) -> list[Part]:
    return [Text(f"Question: {q['question']} Answer:"), Text(q["answer"], True)]


def questions_after(context: list[Part], clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """NuScenes-QA questions about the anchor frame after ``context``: one, or
    ``questions_per_sample`` packed as branches; None when the frame has none."""
    if not clip.qa:
        return None
    k = min(cfg.questions_per_sample, len(clip.qa))
    picked = [clip.qa[int(i)] for i in rng.choice(len(clip.qa), size=k, replace=False)]
    if k == 1:
        return [*context, *question_parts(picked[0])]
    return [*context] + [p for q in picked for p in (Branch(), *question_parts(q))]


def qa(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """NuScenes-QA questions about the anchor frame: one, or ``questions_per_sample`` packed."""
    return questions_after(_context(clip, cfg), clip, cfg, rng)


def every_question(clip: Clip, cfg: TaskConfig) -> list[list[Part]]:
    """One prompt per NuScenes-QA question of the anchor frame (evaluation asks them all)."""
    context = _context(clip, cfg)
    return [[*context, *question_parts(q)] for q in clip.qa]


def cot_planning(clip: Clip, cfg: TaskConfig, rng: np.random.Generator) -> list[Part] | None:
    """Chain of thought: narration, then the meta action, then the trajectory."""
    future = known_future(clip)
    if future is None or not clip.narration:
        return None
    # The narration ends with the meta action; older sidecars may lack it.
    text = clip.narration
    if parse_meta_action(text) is None:
        text = f"{text} {format_meta_action(clip.anchor['meta_action'])}"
    return [
        *_context(clip, cfg),
        Text("Task: describe the scene, then plan."),
        Text(text, True),
        Actions(as_xy(future), True),
    ]


TASKS: dict[str, Callable[[Clip, TaskConfig, np.random.Generator], list[Part] | None]] = {
    "detection": detection,
    "counting": counting,
    "prediction": prediction,
    "planning": planning,
    "forecasting": forecasting,
    "qa": qa,
    "cot_planning": cot_planning,
}

#: Tasks whose evaluation asks more than the one training draw: every item of the clip.
EVERY_ITEM: dict[str, Callable[[Clip, TaskConfig], list[list[Part]]]] = {"qa": every_question}


def validate_tasks(cfg: TaskConfig, key: str, builders: dict | None = None) -> None:
    """One line naming ``key`` when a task name or weight is wrong (tasks: ``builders``,
    the family's; OccLLaMA's by default)."""
    builders = builders or TASKS
    for name, weight in cfg.weights.items():
        if name not in builders:
            raise ConfigError(f"{key}.weights: unknown task '{name}'; tasks are {', '.join(builders)}")
        if weight < 0:
            raise ConfigError(f"{key}.weights.{name}: weight {weight} is negative")
    if not any(w > 0 for w in cfg.weights.values()):
        raise ConfigError(f"{key}.weights: no task has a positive weight")
    if cfg.questions_per_sample < 1:
        raise ConfigError(f"{key}.questions_per_sample: {cfg.questions_per_sample} must be at least 1")
    if cfg.occupancy_weight < 0:
        raise ConfigError(f"{key}.occupancy_weight: {cfg.occupancy_weight} is negative (paper: 1; 0 turns the occupancy queries off)")
    if cfg.past_meta_actions < 0:
        raise ConfigError(f"{key}.past_meta_actions: {cfg.past_meta_actions} is negative (paper: 5)")
    cfg.meta_actions.validate(f"{key}.meta_actions")


def sample_task(clip: Clip, cfg: TaskConfig, seed: int, token: str, builders: dict | None = None) -> tuple[str, list[Part]] | None:
    """Draw a task by weight (deterministic in ``seed`` and the sample token) and build it.

    ``builders`` are the family's tasks (OccLLaMA's by default). A task that does not apply to the clip (e.g. no moving object to predict) gives way to
    the next draw; None when none of the configured tasks applies (the caller skips and
    counts the clip).
    """
    rng = clip_rng(seed, token)
    names = [n for n, w in cfg.weights.items() if w > 0]
    if not names:
        raise ValueError("no task has a positive weight: give the task settings weights (engine.default_tasks fills a family's)")
    p = np.asarray([cfg.weights[n] for n in names], dtype=np.float64)
    for name in rng.choice(names, size=len(names), replace=False, p=p / p.sum()):
        parts = (builders or TASKS)[str(name)](clip, cfg, rng)
        if parts is not None:
            return str(name), parts
    return None


def corpus_texts(index, prompt_words: tuple[str, ...] = ()) -> Iterator[str]:
    """The text a world model's BPE tokenizer trains on: the train split's captions,
    narrations, questions and answers, and the task prompts' fixed words (these and a
    family's own ``prompt_words``)."""
    for scene in index.splits.get("train", []):
        if not index.has_frame_annotations(scene):
            continue
        for frame in index.frames(scene):
            yield frame.get("caption", "")
            yield frame.get("narration", "")
    for q in index.questions("train") or []:
        yield f"Question: {q['question']} Answer: {q['answer']}"
    yield from PROMPT_WORDS
    yield from prompt_words


#: Fixed words of the prompts above, so the tokenizer knows them even without sidecar text.
PROMPT_WORDS = (
    "Task: detect the nearest objects.", "Task: count the objects.", "Task: predict the future of the",
    "Task: plan the ego trajectory.", "Task: forecast the scene.", "Task: describe the scene, then plan.",
    "Command: turn left. turn right. go straight. Ego speed 0.0 m/s.", "Ego past:",
    "no objects", " ".join(c.replace("_", " ") for c in OBJECT_CLASSES), "0 1 2 3 4 5 6 7 8 9 10",
)

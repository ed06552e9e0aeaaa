"""Tasks: how a family turns a clip into prompt-answer parts, and what every family shares.

A task is a builder ``(clip, task_config, rng) -> parts | None`` (None: the task does not
apply to the clip), registered in a family's :class:`TaskSpec` with, optionally, the
items evaluation asks instead of the one training draw (every question of a frame) and
the scorer that grades its generated answers. The task settings are a dataclass that
extends :class:`TaskConfig`; this module also holds the prompt pieces several families
build from: NuScenes-QA questions (one, or several packed as branches), the alternation
of waypoints and future scenes, and the corpus a world model's text tokenizer learns.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from occtrain.data.clips import Actions, Branch, Clip, Part, Scene, Text, clip_rng, ego_future, text_of
from occtrain.data.schema import QAQuestion
from occtrain.errors import ConfigError
from occtrain.models.planning_heads import constant_acceleration, constant_velocity

Builder = Callable[[Clip, Any, np.random.Generator], "list[Part] | None"]
EveryItem = Callable[[Clip, Any], "list[list[Part]]"]


@dataclass
class TaskConfig:
    """What every family's task settings hold; a family's extend it."""

    #: Task name -> sampling weight; a task missing here is not used. Empty: the family's
    #: default tasks for the stage kind (``WorldSpec.default_tasks``). A recipe's mapping
    #: is the whole set: merged onto a non-empty default it could only add tasks.
    weights: dict[str, float] = field(default_factory=dict)
    #: History frames in the prompt, besides the anchor frame.
    context_frames: int = 4
    #: NuScenes-QA questions about one frame per training sequence (paper: 1). Above 1 they
    #: are packed as branches that share the frame's context and do not see each other, so
    #: each is learned exactly as alone, for a fraction of the compute.
    questions_per_sample: int = 1

    def validate(self, key: str) -> None:
        """One line naming ``key``'s sub-key when a setting cannot work (a family adds its own)."""
        if self.questions_per_sample < 1:
            raise ConfigError(f"{key}.questions_per_sample: {self.questions_per_sample} must be at least 1")
        if self.context_frames < 0:
            raise ConfigError(f"{key}.context_frames: {self.context_frames} is negative")


@dataclass
class ForecastTaskConfig(TaskConfig):
    """Task settings of a family that forecasts scenes alternating with waypoints."""

    #: Future scenes the forecast alternates with waypoints (6 = 3 s).
    forecast_frames: int = 6
    #: What the ego's future waypoints are written against. "none" (the papers): their
    #: positions. "constant_velocity": their offsets from driving on straight at the
    #: current speed (stated in the prompt), so the commonest token, no offset, is that
    #: baseline, and what the model learns is how the ego departs from it.
    #: "constant_acceleration": their offsets from driving on at the acceleration the past
    #: shows (``models.planning_heads.constant_acceleration``: from the speed now and the
    #: last move, no future), the strongest kinematic rule, so "no offset" already plans as
    #: well as the kinematics do.
    plan_prior: str = "none"

    def validate(self, key: str) -> None:
        super().validate(key)
        if self.forecast_frames < 1:
            raise ConfigError(f"{key}.forecast_frames: {self.forecast_frames} must be at least 1")
        if self.plan_prior not in PLAN_PRIORS:
            raise ConfigError(
                f"{key}.plan_prior: '{self.plan_prior}' is not one of {', '.join(PLAN_PRIORS)} (paper: none)"
            )


#: ``plan_prior`` values, the papers' first.
PLAN_PRIORS = ("none", "constant_velocity", "constant_acceleration")


def plan_base(clip: Clip, prior: str) -> np.ndarray | None:
    """The (6, 2) waypoints the ego's future is written against under ``prior`` (None: positions)."""
    if prior == "constant_velocity":
        return constant_velocity([clip.anchor])[0].numpy()
    if prior == "constant_acceleration":
        return constant_acceleration([clip.anchor])[0].numpy()
    return None


def ego_plan(future: np.ndarray, clip: Clip, prior: str, supervise: bool = True) -> Actions:
    """The ego's future waypoints as an answer block, written against ``prior``'s base."""
    base = plan_base(clip, prior)
    return Actions(as_xy(future), supervise, None if base is None else as_xy(base[: len(future)]))


@dataclass(frozen=True)
class TaskSpec:
    """One task of a family: its builder, the items evaluation asks (default: the one
    training draw) and the scorer of its generated answers (None: not scored)."""

    build: Builder
    every_item: EveryItem | None = None
    scorer: Any = None


def validate_tasks(cfg: TaskConfig, key: str, tasks: dict[str, TaskSpec]) -> None:
    """One line naming ``key`` when a task name or weight, or another setting, is wrong."""
    for name, weight in cfg.weights.items():
        if name not in tasks:
            raise ConfigError(f"{key}.weights: unknown task '{name}'; tasks are {', '.join(tasks)}")
        if weight < 0:
            raise ConfigError(f"{key}.weights.{name}: weight {weight} is negative")
    if not any(w > 0 for w in cfg.weights.values()):
        raise ConfigError(f"{key}.weights: no task has a positive weight")
    cfg.validate(key)


def sample_task(
    clip: Clip, cfg: TaskConfig, seed: int, token: str, tasks: dict[str, TaskSpec]
) -> tuple[str, list[Part]] | None:
    """Draw a task by weight (deterministic in ``seed`` and the sample token) and build it.

    A task that does not apply to the clip (e.g. no moving object to predict) gives way to
    the next draw; None when none of the configured tasks applies (the caller skips and
    counts the clip).
    """
    rng = clip_rng(seed, token)
    names = [n for n, w in cfg.weights.items() if w > 0]
    if not names:
        raise ValueError(
            "no task has a positive weight: give the task settings weights (the engine fills a family's defaults)"
        )
    p = np.asarray([cfg.weights[n] for n in names], dtype=np.float64)
    for name in rng.choice(names, size=len(names), replace=False, p=p / p.sum()):
        parts = tasks[str(name)].build(clip, cfg, rng)
        if parts is not None:
            return str(name), parts
    return None


# ----------------------------------------------------------------------------- shared prompt pieces


def as_xy(points: npt.ArrayLike) -> tuple[tuple[float, float], ...]:
    """Waypoints (any (..., 2) array) as the tuples an ``Actions`` part holds."""
    return tuple((float(x), float(y)) for x, y in np.asarray(points, dtype=np.float64).reshape(-1, 2))


def known_future(clip: Clip) -> np.ndarray | None:
    """The anchor's 3 s ego future (6, 2), or None unless all of it is known."""
    future, mask = ego_future(clip.anchor)
    return future if mask.all() else None


def forecast_after(prompt: list[Part], clip: Clip, frames: int, prior: str = "none") -> list[Part] | None:
    """``prompt``, then the next waypoint (written against ``prior``, see ``plan_prior``)
    and the next scene alternating, ``frames`` times; None unless the clip's future is known."""
    a = clip.anchor_index
    n = min(frames, int(clip.ann["future"]))
    future = known_future(clip)
    if future is None or n == 0:
        return None
    parts = list(prompt)
    base = plan_base(clip, prior)
    for k in range(n):
        parts += [Actions(as_xy(future[k]), True, None if base is None else as_xy(base[k])), Scene(a + 1 + k, True)]
    return parts


def question_parts(q: QAQuestion) -> list[Part]:
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


def each_question(context: list[Part], clip: Clip) -> list[list[Part]]:
    """One prompt per NuScenes-QA question of the anchor frame (evaluation asks them all)."""
    return [[*context, *question_parts(q)] for q in clip.qa]


def unpacked(parts: list[Part]) -> list[list[Part]]:
    """A draw's prompts one by one: with branches, the shared context then each branch
    alone (a branch is learned exactly as alone, so it is asked alone); else the draw."""
    starts = [i for i, p in enumerate(parts) if isinstance(p, Branch)]
    if not starts:
        return [parts]
    trunk = parts[: starts[0]]
    return [trunk + parts[a + 1 : b] for a, b in zip(starts, starts[1:] + [len(parts)])]


def question_of(parts: list[Part]) -> str:
    """The question of a single-question QA prompt."""
    return text_of(parts[-2]).removeprefix("Question: ").removesuffix(" Answer:")


# ----------------------------------------------------------------------------- the text tokenizer's corpus


#: Words of the driving context every family's prompts may hold (commands, ego state,
#: task phrases, object names, numbers): a world model's BPE tokenizer learns them even
#: where the data has no sidecar text.
COMMON_PROMPT_WORDS = (
    "Task: detect the nearest objects.",
    "Task: count the objects.",
    "Task: predict the future of the",
    "Task: plan the ego trajectory.",
    "Task: forecast the scene.",
    "Task: describe the scene, then plan.",
    "Command: turn left. turn right. go straight. Ego speed 0.0 m/s.",
    "Ego past:",
    "no objects",
    "car truck bus trailer construction vehicle pedestrian motorcycle bicycle barrier traffic cone",
    "0 1 2 3 4 5 6 7 8 9 10",
)


def corpus_texts(index: Any, prompt_words: tuple[str, ...] = ()) -> Iterator[str]:
    """The text a world model's BPE tokenizer trains on: the train split's captions,
    narrations, questions and answers, the common prompt words and a family's own."""
    for scene in index.splits.get("train", []):
        if not index.has_frame_annotations(scene):
            continue
        for frame in index.frames(scene):
            yield frame.get("caption", "")
            yield frame.get("narration", "")
    for q in index.questions("train") or []:
        yield f"Question: {q['question']} Answer: {q['answer']}"
    yield from COMMON_PROMPT_WORDS
    yield from prompt_words

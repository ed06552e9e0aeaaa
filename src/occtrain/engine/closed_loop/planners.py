"""A trained stage behind the wheel: the planner closed-loop driving asks at every planning frame.

A drivable stage kind (``Stage.driver``) answers with a :class:`StageDriver`: the world
model whose frozen encoders read each frame, and the stage's plan for a batch of clips
(the world model's ``plan`` operation, or a planner stage's ``waypoints``).
:func:`model_planner` turns it into the closed loop's planner: each planning frame is
recorded as a dataset frame, encoded into the engine's caches, and planned on as a clip
with the driven history. Until the world has that many frames, the expert drives, as the
logged history of an open-loop clip would have it. :class:`OpenLoopPlanner` is the same
stage scored open loop: its plans cannot change what the expert drives, so it records every
frame first and plans the scored ones afterwards, in batches.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from occtrain.core.protocols import Plans
from occtrain.data.clips import Clip
from occtrain.data.closed_loop_recording import DrivingWorld, EpisodeRecorder
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError, OcctrainError
from occtrain.formats.occ3d import FRAME_DT


def refuse_short_episodes(seconds: float, history: int, key: str) -> None:
    """An episode in which a stage never plans scores (and, in training, labels) the expert,
    not the stage: the expert drives its ``history`` frames first. Refused in one line naming
    ``key``, with the shortest episode in which the stage plans and follows its plan once."""
    least = (history + 1) * FRAME_DT
    if seconds < least:
        raise ConfigError(
            f"{key} {seconds:g}: the expert drives the first {history * FRAME_DT:g} s (the {history} frames of history "
            f"the stage's prompts read), so the stage would never drive; give {key} {least:g} or more"
        )


class NonFinitePlan(OcctrainError):
    """The stage answered waypoints that are not numbers: its weights, not the world, are at fault."""


@dataclass
class StageDriver:
    """What closed-loop driving needs of a trained stage."""

    #: The world model whose frozen encoders read the frames (a planner stage's teacher).
    engine: WorldModelEngine
    #: Clips -> their plans (``Plans.xy``: (B, 6, 2) waypoints in each anchor's ego frame).
    waypoints: Callable[[list[Clip]], Plans]

    def plans(self, clips: list[Clip]) -> Plans:
        """``waypoints``, refused in one line when one is not a number (NaN weights give NaN
        plans; followed, they would surface far away, as a frame the world cannot label)."""
        plans = self.waypoints(clips)
        bad = [i for i, xy in enumerate(plans.xy) if not np.isfinite(xy).all()]
        if bad:
            raise NonFinitePlan(
                f"the stage planned non-finite waypoints ({plans.xy[bad[0]].reshape(-1)[:4].tolist()}...) for sample "
                f"{clips[bad[0]].anchor['token']}; its export holds NaN or infinite weights, or they overflow: retrain "
                "the stage"
            )
        return plans

    @property
    def history(self) -> int:
        """Frames before the current one that the stage's prompts read."""
        return int(self.engine.tasks.context_frames)


def world_model_driver(engine: WorldModelEngine, where: str) -> StageDriver:
    """A world-model stage drives by its family's ``plan`` operation."""
    plan = engine.operation("plan")
    if plan is None:
        raise ConfigError(
            f"{where}: the '{engine.family}' world model has no plan operation; drive the run's planner stage instead"
        )

    def waypoints(clips: list[Clip]) -> Plans:
        return Plans.own(np.stack([np.asarray(plan(engine, clip), dtype=np.float64).reshape(-1, 2) for clip in clips]))

    return StageDriver(engine.eval(), waypoints)


@dataclass
class PlanCounts:
    """Who drove an episode's planning frames: the stage with a plan of its own, the stage's
    constant-velocity fallback (``Plans.fell_back``), or the expert (the history the
    stage's prompts read, before it plans). A score means little when ``planned`` is small."""

    planned: int = 0
    fell_back: int = 0
    expert: int = 0

    @property
    def frames(self) -> int:
        return self.planned + self.fell_back + self.expert


class StagePlanner:
    """The closed loop's planner for a stage (see the module docstring), counting who drove
    each planning frame (:class:`PlanCounts`)."""

    def __init__(self, driver: StageDriver, recorder: EpisodeRecorder):
        self.driver = driver
        self.recorder = recorder
        self.counts = PlanCounts()

    def __call__(self, world: DrivingWorld) -> np.ndarray | None:
        driver, recorder = self.driver, self.recorder
        index = recorder.record()
        driver.engine.add_samples(index, [(recorder.scene, recorder.token)])  # later frames read it as history
        if len(recorder.frames) <= driver.history:
            self.counts.expert += 1
            return None  # the expert drives the history the prompts read
        plans = driver.plans([recorder.clip(driver.history)])
        if plans.fell_back[0]:
            self.counts.fell_back += 1
        else:
            self.counts.planned += 1
        return plans.xy[0]


def model_planner(driver: StageDriver, recorder: EpisodeRecorder) -> StagePlanner:
    """The closed loop's planner for ``driver``, recording every planning frame with ``recorder``."""
    return StagePlanner(driver, recorder)


#: Frames an open-loop pass encodes and plans in one batch.
CHUNK = 16


class OpenLoopPlanner:
    """The stage open loop on an episode the expert drives: a planner that records each
    planning frame and answers nothing, then :meth:`plans` for the scored frames in batches
    (one batched decode per ``CHUNK`` frames instead of one per frame; each clip reads only
    the frames up to its anchor, as it would have when it was recorded)."""

    def __init__(self, driver: StageDriver, recorder: EpisodeRecorder):
        self.driver = driver
        self.recorder = recorder

    def __call__(self, world: DrivingWorld) -> None:
        self.recorder.record()

    def plans(self, scored: int) -> list[np.ndarray | None]:
        """The stage's plan at each of the first ``scored`` recorded frames (those with a
        whole logged future to meet); None for the history frames the expert drives. Frames
        are encoded and planned ``CHUNK`` at a time: a 40 s route is 81 frames."""
        recorder, history = self.recorder, self.driver.history
        frames = recorder.frames[:scored]
        if recorder.index is None or not frames:
            return []
        planned: list[np.ndarray | None] = [None] * min(history, len(frames))
        for start in range(0, len(frames), CHUNK):
            chunk = frames[start : start + CHUNK]
            self.driver.engine.add_samples(recorder.index, [(recorder.scene, f["token"]) for f in chunk])
            anchors = [k for k in range(start, start + len(chunk)) if k >= history]
            if anchors:
                planned.extend(self.driver.plans([recorder.clip(history, at=k) for k in anchors]).xy)
        return planned

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

from occtrain.data.clips import Clip
from occtrain.data.driving import EPISODE_SCENE, DrivingWorld, EpisodeRecorder, Planner
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError


@dataclass
class StageDriver:
    """What closed-loop driving needs of a trained stage."""

    #: The world model whose frozen encoders read the frames (a planner stage's teacher).
    engine: WorldModelEngine
    #: Clips -> (B, 6, 2) waypoints in each anchor's ego frame.
    waypoints: Callable[[list[Clip]], np.ndarray]

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

    def waypoints(clips: list[Clip]) -> np.ndarray:
        return np.stack([np.asarray(plan(engine, clip), dtype=np.float64).reshape(-1, 2) for clip in clips])

    return StageDriver(engine.eval(), waypoints)


def model_planner(driver: StageDriver, recorder: EpisodeRecorder) -> Planner:
    """The closed loop's planner for ``driver``, recording every planning frame with ``recorder``."""

    def plan(world: DrivingWorld) -> np.ndarray | None:
        index = recorder.record()
        driver.engine.add_samples(index, [(EPISODE_SCENE, recorder.token)])  # later frames read it as history
        if len(recorder.frames) <= driver.history:
            return None  # the expert drives the history the prompts read
        return driver.waypoints([recorder.clip(driver.history)])[0]

    return plan


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
            self.driver.engine.add_samples(recorder.index, [(EPISODE_SCENE, f["token"]) for f in chunk])
            anchors = [k for k in range(start, start + len(chunk)) if k >= history]
            if anchors:
                planned.extend(self.driver.waypoints([recorder.clip(history, at=k) for k in anchors]))
        return planned

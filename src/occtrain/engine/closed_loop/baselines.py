"""The drivers every stage is driven beside: the expert and the kinematic rules.

The expert is the simulator's own route follower (the IDM on its route, which generated
the data). The kinematic rules plan from the ego's state alone: straight ahead at the
current speed, at the acceleration of its last planning frame's move (as the open-loop
baseline of that name), or standing still.

Every driver gets the same start: a stage plans only once its prompts have their history
(``history`` planning frames, which the expert drives), so the rules wait as long. From
frame 0 there is no past, constant acceleration is constant velocity, and a stage that
planned none of its frames would be set against rules that drove all of theirs.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from occtrain.data.closed_loop_recording import STRIDE, DrivingWorld
from occtrain.engine.closed_loop.planners import PlanCounts
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.kinematics import constant_acceleration_path, past_acceleration

#: The baselines every stage is driven beside, in the order tables list them.
BASELINES = ("expert", "constant_velocity", "constant_acceleration", "stand_still")


def constant_velocity(world: DrivingWorld) -> np.ndarray:
    """Straight ahead at the current speed."""
    t = np.arange(1, FUTURE_STEPS + 1) * FRAME_DT
    return np.stack([world.ego.speed * t, np.zeros_like(t)], axis=1)


def constant_acceleration(world: DrivingWorld) -> np.ndarray:
    """Straight ahead from the current speed at the acceleration of the ego's past
    (``kinematics.past_acceleration`` over the last planning frame's move), as the
    open-loop baseline of the same name plans."""
    frames = world.log.states[::STRIDE]
    last_move = float(np.linalg.norm(world.ego.xy - frames[-2].xy)) if world.at_frame and len(frames) >= 2 else None
    speed = world.ego.speed
    x = constant_acceleration_path(speed, past_acceleration(speed, last_move), FUTURE_STEPS)
    return np.stack([x, np.zeros_like(x)], axis=1)


def stand_still(world: DrivingWorld) -> np.ndarray:
    return np.zeros((FUTURE_STEPS, 2))


RULES: dict[str, Callable[[DrivingWorld], np.ndarray]] = {
    "constant_velocity": constant_velocity,
    "constant_acceleration": constant_acceleration,
    "stand_still": stand_still,
}


class WarmRule:
    """A kinematic rule behind the wheel after the expert drove the first ``history``
    planning frames (what a stage's prompts read before it plans), counting who drove each."""

    def __init__(self, rule: Callable[[DrivingWorld], np.ndarray], history: int):
        self.rule, self.history = rule, history
        self.counts = PlanCounts()

    def __call__(self, world: DrivingWorld) -> np.ndarray | None:
        if world.step // STRIDE < self.history:
            self.counts.expert += 1
            return None
        self.counts.planned += 1
        return self.rule(world)


def baseline_planner(name: str, history: int) -> WarmRule | None:
    """Baseline ``name`` as a closed-loop planner with the same start as a stage reading
    ``history`` frames; None for the expert, whom ``drive_episode`` lets drive itself."""
    if name == "expert":
        return None
    if name not in RULES:
        raise ValueError(f"'{name}' is not a baseline; the baselines are {', '.join(BASELINES)}")
    return WarmRule(RULES[name], history)


__all__ = [
    "BASELINES",
    "RULES",
    "WarmRule",
    "baseline_planner",
    "constant_acceleration",
    "constant_velocity",
    "stand_still",
]

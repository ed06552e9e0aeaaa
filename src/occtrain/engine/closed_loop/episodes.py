"""Episodes: a planner behind the wheel of the simulator, closed loop or in its shadow.

The simulator (``data.closed_loop_recording.DrivingWorld``) steps the world and keeps score;
it holds no planner. :func:`drive_episode` is the one loop every closed-loop driver runs
(``occtrain drive``'s stages and baselines, a dagger stage's rollouts): it asks the planner
for waypoints at every planning frame and tracks the plan in between with the ego's
controller (``vehicle.PlanTracker`` through a kinematic bicycle). :func:`shadow_episode` is
open loop on the same routes: the expert drives, the planners only plan.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from occtrain.data.closed_loop_recording import (
    SIM_DT,
    Agents,
    DrivingWorld,
    PlanTracker,
    ViewFrame,
    bicycle_step,
)
from occtrain.data.geometry import global_to_ego
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.metrics.closed_loop_scores import EpisodeTrace

#: A planner in the loop: the world as it is now -> waypoints (FUTURE_STEPS, 2) in the ego
#: frame, FRAME_DT apart, or None for "not yet": the expert's plan is followed (a model
#: waits for the history its prompts read, and every driver gets that same start).
Planner = Callable[[DrivingWorld], np.ndarray | None]


def drive_episode(world: DrivingWorld, planner: Planner | None, views: list[ViewFrame] | None = None) -> EpisodeTrace:
    """Drive ``world`` to its end: replan every FRAME_DT and track the plan through the
    kinematic bicycle in between; without a planner the expert drives (the simulator's own
    route follower, exactly). ``views`` collects a bird's-eye frame per planning frame."""
    tracker, made_at = None, 0.0
    while not world.done:
        if planner is None:
            if views is not None and world.at_frame:
                views.append(world.view(world.expert_plan()))
            world.advance(None)
            continue
        if world.at_frame or tracker is None:
            answer = planner(world)
            plan = world.expert_plan() if answer is None else np.asarray(answer, dtype=np.float64).reshape(-1, 2)
            if views is not None:
                views.append(world.view(plan))
            tracker, made_at = PlanTracker(plan, world.ego, FRAME_DT), world.time
        accel, steer = tracker.controls(world.ego, world.time - made_at)
        world.advance(bicycle_step(world.ego, accel, steer, SIM_DT))
    if views is not None:
        for v in views:  # each picture shows what went wrong until the next one
            v.infractions = [i for i in world.log.infractions if v.time <= i.time < v.time + FRAME_DT]
    return world.trace()


@dataclass
class ShadowFrame:
    """One planning frame of a shadow episode: each planner's plan (ego frame; None before
    it plans), where the expert went next and who was around then, in that frame's ego frame."""

    plans: dict[str, np.ndarray | None]
    logged: np.ndarray  # (FUTURE_STEPS, 2)
    #: Per future frame, the agents as (N, 5) rows of x, y, length, width, yaw.
    agents: list[np.ndarray]


def shadow_episode(world: DrivingWorld, planners: dict[str, Planner]) -> list[ShadowFrame]:
    """Open loop on the route: the expert drives the whole episode, the planners plan at every
    planning frame without driving, and each plan meets what the expert did next. Frames
    without FUTURE_STEPS frames after them in the episode are left out."""
    plans: list[dict[str, np.ndarray | None]] = []
    poses: list[tuple[np.ndarray, float]] = []
    around: list[Agents] = []
    while True:
        if world.at_frame:
            answers = {name: planner(world) for name, planner in planners.items()}
            plans.append(
                {k: None if a is None else np.asarray(a, dtype=np.float64).reshape(-1, 2) for k, a in answers.items()}
            )
            poses.append((world.ego.xy.copy(), world.ego.yaw))
            around.append(world.agents())
        if world.done:
            break
        world.advance(None)
    frames = []
    for k in range(len(plans) - FUTURE_STEPS):
        xy, yaw = poses[k]
        later = range(k + 1, k + FUTURE_STEPS + 1)
        logged = global_to_ego(np.array([poses[j][0] for j in later]), xy, yaw)
        agents = []
        for j in later:
            a = around[j]
            local = global_to_ego(a.xy, xy, yaw)
            agents.append(np.column_stack([local, a.size[:, 0], a.size[:, 1], a.yaw - yaw]))
        frames.append(ShadowFrame(plans[k], logged, agents))
    return frames


__all__ = ["Planner", "ShadowFrame", "drive_episode", "shadow_episode"]

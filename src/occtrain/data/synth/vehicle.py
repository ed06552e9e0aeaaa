"""The driven ego: a kinematic bicycle and a controller that tracks a planned trajectory.

A planner answers every FRAME_DT with waypoints in its ego frame (x forward, y left, one
per FRAME_DT); between two answers the ego follows the latest plan: the speed profile it
implies by feedforward of the plan's acceleration plus a proportional correction, its path
by pure pursuit on the steering. Both are the textbook forms (Rajamani, "Vehicle Dynamics
and Control", ch. 2; Coulter, "Implementation of the Pure Pursuit Path Tracking Algorithm",
CMU-RI-TR-92-01), with the limits of a passenger car.

The feedforward is what lets a plan's speed change happen: with the proportional term
alone (gain 2/s, the plan replaced every 0.5 s) the ego realised about two thirds of a
planned acceleration before the next plan came (a planner re-planning 1 m/s^2 from its
speed drove 0.66), so every acceleration the past shows decayed frame by frame, and a
constant-acceleration plan read from that past was closer to constant velocity than the
planner meant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occtrain.data.geometry import ego_to_global, global_to_ego

#: Wheelbase (m) of the nuScenes ego (a Renault Zoe: 2.59 m).
WHEELBASE = 2.59
#: Steering angle limit (rad) and how fast it may change (rad/s).
MAX_STEER = 0.6
MAX_STEER_RATE = 1.0
#: Acceleration limits (m/s^2): the hardest braking and a passenger car's pull.
MIN_ACCEL, MAX_ACCEL = -6.0, 3.0
#: The speed controller closes this share of the speed error per second (on top of the
#: plan's own acceleration, fed forward).
SPEED_GAIN = 4.0
#: Pure pursuit looks this far ahead: LOOKAHEAD_TIME s at the current speed, at least LOOKAHEAD_MIN m.
LOOKAHEAD_MIN = 3.0
LOOKAHEAD_TIME = 0.8
#: A plan shorter than this (m) over its whole horizon means stand still.
STANDSTILL_PLAN = 0.5


@dataclass(frozen=True)
class EgoState:
    """The ego at one simulation step: global pose, speed and the last controls."""

    xy: np.ndarray  # (2,) global
    yaw: float
    speed: float
    accel: float = 0.0
    steer: float = 0.0

    @property
    def yaw_rate(self) -> float:
        return self.speed * float(np.tan(self.steer)) / WHEELBASE


def bicycle_step(state: EgoState, accel: float, steer: float, dt: float) -> EgoState:
    """One step of the kinematic bicycle (rear-axle reference, no slip), controls limited first."""
    accel = float(np.clip(accel, MIN_ACCEL, MAX_ACCEL))
    steer = float(np.clip(steer, state.steer - MAX_STEER_RATE * dt, state.steer + MAX_STEER_RATE * dt))
    steer = float(np.clip(steer, -MAX_STEER, MAX_STEER))
    speed = max(state.speed + accel * dt, 0.0)
    accel = (speed - state.speed) / dt  # what the car did: it does not reverse
    mean_v = (state.speed + speed) / 2
    yaw = state.yaw + mean_v * np.tan(steer) / WHEELBASE * dt
    heading = (state.yaw + yaw) / 2
    xy = state.xy + mean_v * dt * np.array([np.cos(heading), np.sin(heading)])
    return EgoState(xy, float(yaw), speed, accel, steer)


class PlanTracker:
    """Follows one plan: waypoints (K, 2) in the ego frame of ``origin``, ``dt`` s apart."""

    def __init__(self, plan: np.ndarray, origin: EgoState, dt: float):
        plan = np.asarray(plan, dtype=np.float64).reshape(-1, 2)
        self.dt = dt
        self.points = np.concatenate([origin.xy[None], ego_to_global(plan, origin.xy, origin.yaw)])
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.standstill = self.arc[-1] < STANDSTILL_PLAN
        self.times = np.arange(len(self.points)) * dt
        # The plan's speed profile: the speed it was made at, then each interval's mean speed
        # at the interval's middle (where a constant acceleration reaches it), held after.
        mean = np.maximum(np.diff(self.arc), 0.0) / dt
        self.speed_times = np.concatenate([[0.0], self.times[:-1] + dt / 2])
        self.speeds = np.concatenate([[origin.speed], mean])

    def target_speed(self, t: float) -> float:
        """The plan's speed ``t`` s after it was made."""
        return float(np.interp(t, self.speed_times, self.speeds))

    def target_accel(self, t: float) -> float:
        """The plan's acceleration ``t`` s after it was made (its speed profile's slope)."""
        k = int(np.clip(np.searchsorted(self.speed_times, t, side="right") - 1, 0, len(self.speeds) - 2))
        return float((self.speeds[k + 1] - self.speeds[k]) / (self.speed_times[k + 1] - self.speed_times[k]))

    def controls(self, state: EgoState, t: float) -> tuple[float, float]:
        """(acceleration, steering angle) for ``state``, ``t`` s after the plan was made."""
        if self.standstill:
            return MIN_ACCEL if state.speed > 0 else 0.0, state.steer
        accel = self.target_accel(t) + SPEED_GAIN * (self.target_speed(t) - state.speed)
        # Pure pursuit: a point LOOKAHEAD ahead along the plan from the ego's projection on it.
        seg_start, seg_vec = self.points[:-1], np.diff(self.points, axis=0)
        seg_len2 = np.maximum(np.sum(seg_vec**2, axis=1), 1e-9)
        u = np.clip(np.sum((state.xy - seg_start) * seg_vec, axis=1) / seg_len2, 0.0, 1.0)
        foot = seg_start + u[:, None] * seg_vec
        k = int(np.argmin(np.sum((foot - state.xy) ** 2, axis=1)))
        s_here = self.arc[k] + u[k] * np.sqrt(seg_len2[k])
        ahead = max(LOOKAHEAD_MIN, LOOKAHEAD_TIME * state.speed)
        s_goal = s_here + ahead
        if s_goal <= self.arc[-1]:
            goal = np.array([np.interp(s_goal, self.arc, self.points[:, i]) for i in (0, 1)])
        else:  # past the plan's end: continue along its last segment
            d = seg_vec[-1] / max(np.sqrt(seg_len2[-1]), 1e-9)
            goal = self.points[-1] + d * (s_goal - self.arc[-1])
        local = global_to_ego(goal, state.xy, state.yaw)
        dist2 = max(float(local @ local), 1e-6)
        steer = float(np.arctan(2.0 * WHEELBASE * local[1] / dist2))
        return accel, steer


def follow(state: EgoState, tracker: PlanTracker, t0: float, dt: float, steps: int) -> list[EgoState]:
    """``steps`` bicycle steps of ``dt`` following ``tracker`` from ``t0`` s after its plan was made."""
    out = []
    for i in range(steps):
        accel, steer = tracker.controls(state, t0 + i * dt)
        state = bicycle_step(state, accel, steer, dt)
        out.append(state)
    return out

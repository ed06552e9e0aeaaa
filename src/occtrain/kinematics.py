"""The ego's motion as known at a frame, from that frame and the ones before it only.

One definition for everyone who reads it: the synthetic world's annotator (the sidecar's
``ego_accel``), the closed loop's annotation of a driven frame, and the constant-acceleration
plan every planner is scored beside. An input that read the future (the acceleration the
expert was about to apply) would let a model look ahead in training and not in the closed
loop, where the same key then meant something else.
"""

from __future__ import annotations

import numpy as np

from occtrain.formats.occ3d import FRAME_DT


def past_acceleration(speed: float, last_move: float | None, dt: float = FRAME_DT) -> float:
    """Longitudinal acceleration (m/s^2) at a frame: the speed now against the mean speed of
    the last move (``last_move`` metres over ``dt`` s, centred ``dt / 2`` s ago); 0 without
    a past frame. Planned forward, it beat the speed difference to the previous frame on the
    embedded world (L2 0.264 against 0.277 m on the quickstart's val split, world v4): the
    last move's mean speed is half a frame more recent than the previous frame's speed."""
    if last_move is None:
        return 0.0
    return (float(speed) - float(last_move) / dt) / (dt / 2)


def constant_acceleration_path(speed: float, accel: float, steps: int, dt: float = FRAME_DT) -> np.ndarray:
    """(steps,) metres travelled at ``dt, 2 dt, ...`` at constant acceleration from ``speed``;
    braking stops at standstill (no reversing)."""
    t = np.arange(1, steps + 1) * dt
    if accel < 0 and speed > 0:
        t = np.minimum(t, speed / -accel)
    elif accel < 0:
        t = np.zeros_like(t)
    return speed * t + 0.5 * accel * t**2

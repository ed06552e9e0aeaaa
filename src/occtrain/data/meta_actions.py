"""OccVLA's meta actions (Sec. 3.3, App. D.2) labelled from ego poses alone.

A meta action is a speed action (accelerate / decelerate / maintain) and a direction
(straight, left, right, bear left, bear right, stop). The paper labels speed by the
ego's acceleration at the current step against +-1 km/h/s; its directions come from
GPT-4o over an HD map, which we replace by the heading change and lateral offset over
the next ``direction_window_s`` (the rule the synthetic world's sidecar also uses).

A frame's *future* meta action looks ahead; a *past* one (the t-5 .. t-1 of the OccVLA
prompt) is labelled with the poses up to the anchor only, so no past label reveals the
future the model is asked about.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from occtrain.data.geometry import global_to_ego
from occtrain.data.schema import (
    META_ACCEL_THRESHOLD,
    META_DIRECTIONS,
    META_SPEEDS,
    STOP_SPEED,
    MetaAction,
    MetaDirection,
    MetaSpeed,
)
from occtrain.errors import ConfigError
from occtrain.formats.occ3d import FRAME_DT

#: km/h per second -> m/s^2.
KMH_PER_S = 1000.0 / 3600.0


@dataclass
class MetaActionConfig:
    """How meta actions are labelled from poses (defaults: the paper's)."""

    #: |acceleration| above this many km/h per second is accelerate / decelerate (paper: 1).
    accel_threshold_kmh_s: float = 1.0
    #: The acceleration is the speed change between the ``speed_window_s`` before and after
    #: the frame (paper: "at the current timestep", one 0.5 s step).
    speed_window_s: float = 0.5
    #: Directions look this far ahead (the paper's planning horizon, 3 s).
    direction_window_s: float = 3.0
    turn_heading_deg: float = 30.0
    bear_heading_deg: float = 8.0
    bear_lateral_m: float = 1.0
    #: Speeds at or below this (m/s) over the speed window are "stop".
    stop_speed: float = STOP_SPEED

    def validate(self, where: str) -> None:
        for key in ("accel_threshold_kmh_s", "speed_window_s", "direction_window_s", "bear_lateral_m"):
            if getattr(self, key) <= 0:
                raise ConfigError(f"{where}.{key}: must be > 0, got {getattr(self, key)}")
        if not 0 < self.bear_heading_deg < self.turn_heading_deg:
            raise ConfigError(
                f"{where}: bear_heading_deg ({self.bear_heading_deg}) must lie in (0, turn_heading_deg = "
                f"{self.turn_heading_deg})"
            )

    def steps(self, seconds: float) -> int:
        return max(1, int(round(seconds / FRAME_DT)))


def speed_action(accel: float, threshold_ms2: float) -> MetaSpeed:
    """accelerate / decelerate / maintain for a longitudinal acceleration (m/s^2)."""
    if accel > threshold_ms2:
        return "accelerate"
    if accel < -threshold_ms2:
        return "decelerate"
    return "maintain"


def direction_action(
    heading_change_deg: float, lateral_m: float, stopped: bool, cfg: MetaActionConfig
) -> MetaDirection:
    """The direction for a heading change (degrees, left positive) and the end point's
    lateral offset (metres, left positive) over the direction window."""
    if stopped:
        return "stop"
    if abs(heading_change_deg) > cfg.turn_heading_deg:
        return "left" if heading_change_deg > 0 else "right"
    if abs(lateral_m) > cfg.bear_lateral_m:
        return "bear left" if lateral_m > 0 else "bear right"
    if abs(heading_change_deg) > cfg.bear_heading_deg:
        return "bear left" if heading_change_deg > 0 else "bear right"
    return "straight"


def _speeds(xy: np.ndarray) -> np.ndarray:
    """(T-1,): the speed over each 0.5 s step between consecutive poses."""
    return np.linalg.norm(np.diff(xy, axis=0), axis=1) / FRAME_DT


def label(poses: np.ndarray, i: int, cfg: MetaActionConfig, end: int | None = None) -> MetaAction | None:
    """The meta action at frame ``i`` of global poses (T, 3: x, y, yaw), reading poses up to
    index ``end`` (inclusive; default the last). None when the speed window does not fit:
    it needs ``speed_window`` steps on both sides of ``i``. The direction window is cut at
    ``end`` (at least one step)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    last = len(poses) - 1 if end is None else min(int(end), len(poses) - 1)
    n = cfg.steps(cfg.speed_window_s)
    if i - n < 0 or i + n > last:
        return None
    speeds = _speeds(poses[: last + 1, :2])
    before, after = speeds[i - n : i].mean(), speeds[i : i + n].mean()
    accel = (after - before) / (n * FRAME_DT)
    speed = speed_action(accel, cfg.accel_threshold_kmh_s * KMH_PER_S)
    k = min(cfg.steps(cfg.direction_window_s), last - i)
    stopped = bool(np.all(speeds[i : i + n] <= cfg.stop_speed))
    heading = float(np.rad2deg(np.angle(np.exp(1j * (poses[i + k, 2] - poses[i, 2])))))
    lateral = float(global_to_ego(poses[i + k, :2], poses[i, :2], poses[i, 2])[1])
    return {"speed": speed, "direction": direction_action(heading, lateral, stopped, cfg)}


#: The rule that writes a frame's ``meta_action`` in occtrain's sidecar, for the synthetic
#: world and for an imported release alike: the speed action from the speed change over the
#: next SIDECAR_SPEED_WINDOW_S against schema.META_ACCEL_THRESHOLD, "stop" while the speed
#: stays at or below STOP_SPEED over that window, and the direction over the next
#: SIDECAR_DIRECTION_WINDOW_S by these thresholds (turn above 30 degrees, bear above 8
#: degrees or 1 m sideways).
SIDECAR_SPEED_WINDOW_S = 1.0
SIDECAR_DIRECTION_WINDOW_S = 3.0
SIDECAR_RULES = MetaActionConfig(
    direction_window_s=SIDECAR_DIRECTION_WINDOW_S, turn_heading_deg=30.0, bear_heading_deg=8.0, bear_lateral_m=1.0
)


def sidecar_label(xy: np.ndarray, yaw: np.ndarray, speed: np.ndarray, i: int) -> MetaAction:
    """The sidecar's meta action at frame ``i`` of an ego's global positions (T, 2), unwrapped
    headings (T,) and speeds (T,) at the frames (see SIDECAR_RULES).

    The windows end at the last frame given: the synthetic world simulates past a scene's
    end so they never do there, while a release ends where its scene does, so its frames
    within 3 s of the end look only as far as the scene goes. The last frame, with nothing
    ahead, carries the label of the frame before it (a one-frame scene: "maintain", and
    "stop" or "straight" by its speed)."""
    last = len(speed) - 1
    if i >= last:
        if last > 0:
            return sidecar_label(xy, yaw, speed, last - 1)
        return {"speed": "maintain", "direction": "stop" if speed[0] <= STOP_SPEED else "straight"}
    n1 = min(SIDECAR_RULES.steps(SIDECAR_SPEED_WINDOW_S), last - i)
    n3 = min(SIDECAR_RULES.steps(SIDECAR_DIRECTION_WINDOW_S), last - i)
    accel = (speed[i + n1] - speed[i]) / (n1 * FRAME_DT)
    stopped = bool(np.all(speed[i : i + n1 + 1] <= STOP_SPEED))
    turn = float(np.rad2deg(yaw[i + n3] - yaw[i]))
    lateral = float(global_to_ego(xy[i + n3], xy[i], yaw[i])[1])
    return {
        "speed": speed_action(accel, META_ACCEL_THRESHOLD),
        "direction": direction_action(turn, lateral, stopped, SIDECAR_RULES),
    }


def past_labels(poses: np.ndarray, anchor: int, window: int, cfg: MetaActionConfig) -> list[MetaAction]:
    """The meta actions at frames ``anchor - window`` .. ``anchor - 1``, oldest first, each
    from the poses up to ``anchor`` (see the module docstring); frames too early to label
    are left out."""
    out = [label(poses, anchor - k, cfg, end=anchor) for k in range(window, 0, -1)]
    return [m for m in out if m is not None]


def commonest(index, split: str, cfg: MetaActionConfig) -> MetaAction | None:
    """The commonest future meta action over every labelled frame of ``split`` (a
    ``DatasetIndex``): the answer the meta-action baseline gives to every frame."""
    counts: Counter = Counter()
    for scene in index.splits.get(split, []):
        poses = np.asarray([index.ego_pose(scene, t) for t in index.scenes[scene]])
        for i in range(len(poses)):
            m = label(poses, i, cfg)
            if m is not None and i + cfg.steps(cfg.direction_window_s) < len(poses):
                counts[(m["speed"], m["direction"])] += 1
    if not counts:
        return None
    speed, direction = counts.most_common(1)[0][0]
    return {"speed": speed, "direction": direction}


__all__ = [
    "META_DIRECTIONS",
    "META_SPEEDS",
    "SIDECAR_DIRECTION_WINDOW_S",
    "SIDECAR_RULES",
    "SIDECAR_SPEED_WINDOW_S",
    "MetaActionConfig",
    "commonest",
    "direction_action",
    "label",
    "past_labels",
    "sidecar_label",
    "speed_action",
]

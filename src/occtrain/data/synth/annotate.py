"""Per-frame FrameAnnotation of a synthetic scene: ego state, plan labels, boxes, futures.

Trajectory conventions: ``ego_future[k]`` is the ego's position k+1 frames ahead in the
current ego frame and ``ego_past`` the last PAST_STEPS positions, oldest first. A waypoint
that falls outside the scene (before its first or after its last frame) has mask 0 and
is filled with [0, 0]; agent futures follow the same rule. The driving command and the
road context (``road``) are the caller's: both come from the ego's route
(``road_context.route_command`` and ``road_context.road_context``), in the synthesized
scene and in the closed loop alike.

The meta action looks at the ego's simulated motion, which runs FUTURE_STEPS frames past
the scene's end, so the last frames get labels too:

- speed: mean longitudinal acceleration over the next SPEED_WINDOW_S seconds against
  schema.META_ACCEL_THRESHOLD (accelerate / decelerate / maintain);
- direction: "stop" if the speed stays at or below schema.STOP_SPEED over the next
  SPEED_WINDOW_S seconds; otherwise over the next DIRECTION_WINDOW_S seconds a heading
  change above SIDECAR_RULES.turn_heading_deg is "left"/"right", a heading change above
  bear_heading_deg or a lateral offset of the end point above bear_lateral_m is
  "bear left"/"bear right" (lane changes, gentle curves), anything else "straight".

Box velocities are the objects' own velocities expressed in the ego frame's axes (the
ego's motion is not subtracted), as in nuScenes.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from occtrain.data.geometry import global_to_ego, rotate_to_ego
from occtrain.data.meta_actions import SIDECAR_DIRECTION_WINDOW_S, SIDECAR_SPEED_WINDOW_S, sidecar_label
from occtrain.data.meta_actions import SIDECAR_RULES as SIDECAR_RULES  # its direction thresholds, named here too
from occtrain.data.schema import Box, Command, Flag, FrameAnnotation, MetaAction, RoadContext
from occtrain.data.synth.catalog import TrackSet
from occtrain.data.synth.grid import GROUND_TOP_Z
from occtrain.formats.occ3d import CLASS_NAMES, FRAME_DT, FUTURE_STEPS, PAST_STEPS, RANGE_MAX
from occtrain.kinematics import past_acceleration

#: The meta action's windows, shared with an imported release's sidecar (``data.meta_actions``).
SPEED_WINDOW_S = SIDECAR_SPEED_WINDOW_S
DIRECTION_WINDOW_S = SIDECAR_DIRECTION_WINDOW_S
#: Scene start times are spread by seed so timestamps of different scenes do not overlap.
EPOCH_US = 1_600_000_000_000_000
SCENE_SLOT_US = 100_000_000


@dataclass
class EgoMotion:
    """The ego's global state at every frame of the scene and FUTURE_STEPS frames past its end."""

    xy: np.ndarray  # (T, 2)
    yaw: np.ndarray  # (T,) unwrapped
    speed: np.ndarray
    #: Longitudinal, as known at each frame (``past_accels``): never the command about to be applied.
    accel: np.ndarray
    yaw_rate: np.ndarray


def past_accels(xy: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """(T,) the longitudinal acceleration at each frame from that frame and the one before
    (``kinematics.past_acceleration``: the speed now against the last move's mean speed), 0
    at the first. The simulator's own acceleration is the command applied after the frame:
    a model reading it would read the next half second."""
    moves = [None, *np.linalg.norm(np.diff(np.asarray(xy, dtype=np.float64), axis=0), axis=1)]
    return np.array([past_acceleration(float(v), move) for v, move in zip(speed, moves)])


def sample_token(seed: int, index: int) -> str:
    """32 lowercase hex characters, a function of the scene seed and the frame index."""
    return hashlib.md5(f"occtrain-synth/{seed}/{index}".encode()).hexdigest()


def _r(x, nd: int = 4) -> list:
    """Rounded plain-Python (nested) list of an array, for compact deterministic JSON."""
    return np.round(np.asarray(x, dtype=np.float64), nd).tolist()


def meta_action(ego: EgoMotion, i: int) -> MetaAction:
    """OccVLA meta action of frame ``i`` (thresholds in the module docstring), by the
    sidecar's rule of ``data.meta_actions`` over the simulated motion (which runs past the
    scene's end, so no window is cut)."""
    return sidecar_label(ego.xy, ego.yaw, ego.speed, i)


def _relative(xy: np.ndarray, i: int, num_frames: int, pose_xy: np.ndarray, pose_yaw: float, offsets: range):
    """Points xy[i + k] (k in offsets) in the frame-i ego frame, [0, 0] and mask 0 outside the scene."""
    idx = np.array([i + k for k in offsets])
    valid = (idx >= 0) & (idx < num_frames)
    pts = np.zeros(xy.shape[:-2] + (len(idx), 2))
    if valid.any():
        pts[..., valid, :] = global_to_ego(xy[..., idx[valid], :], pose_xy, pose_yaw)
    return pts, valid.astype(int)


def _flags(mask: np.ndarray) -> list[Flag]:
    return [1 if m else 0 for m in mask]


def frame_annotation(
    scene: str,
    seed: int,
    i: int,
    num_frames: int,
    ego: EgoMotion,
    tracks: TrackSet,
    *,
    command: Command,
    road: RoadContext | None,
) -> FrameAnnotation:
    """The FrameAnnotation of frame ``i`` (caption and narration left empty for the text module),
    with the route's ``command`` and ``road`` context (none: the key is left out)."""
    pxy, pyaw = ego.xy[i], float(ego.yaw[i])
    future, fmask = _relative(ego.xy, i, num_frames, pxy, pyaw, range(1, FUTURE_STEPS + 1))
    past, pmask = _relative(ego.xy, i, num_frames, pxy, pyaw, range(-PAST_STEPS, 0))

    centre = global_to_ego(tracks.xy[:, i], pxy, pyaw)
    inside = np.flatnonzero(np.all(np.abs(centre) < RANGE_MAX[:2], axis=1))
    vel_ego = rotate_to_ego(tracks.velocity[inside, i], pyaw)
    yaw_ego = np.angle(np.exp(1j * (tracks.yaw[inside, i] - pyaw)))
    boxes: list[Box] = []
    for row, n in enumerate(inside):
        size = tracks.size[n]
        boxes.append(
            {
                "track_id": int(n),
                "category": CLASS_NAMES[int(tracks.cls[n])],
                "center": _r([centre[n, 0], centre[n, 1], GROUND_TOP_Z + size[2] / 2]),
                "size": _r(size),
                "yaw": round(float(yaw_ego[row]), 5),
                "velocity": _r(vel_ego[row]),
                "attribute": tracks.attribute(int(n), i),
            }
        )
    agent_future, amask = _relative(tracks.xy[inside], i, num_frames, pxy, pyaw, range(1, FUTURE_STEPS + 1))
    frame: FrameAnnotation = {
        "scene": scene,
        "token": sample_token(seed, i),
        "index": i,
        "timestamp": EPOCH_US + (seed % 10**6) * SCENE_SLOT_US + int(round(i * FRAME_DT * 1e6)),
        "ego_pose": {"translation": _r([pxy[0], pxy[1], 0.0]), "yaw": round(float(np.angle(np.exp(1j * pyaw))), 6)},
        "ego_speed": round(float(ego.speed[i]), 4),
        "ego_accel": round(float(ego.accel[i]), 4),
        "ego_yaw_rate": round(float(ego.yaw_rate[i]), 5),
        "command": command,
        "meta_action": meta_action(ego, i),
        "ego_future": _r(future),
        "ego_future_mask": _flags(fmask),
        "ego_past": _r(past),
        "ego_past_mask": _flags(pmask),
        "boxes": boxes,
        "agent_futures": _r(agent_future),
        "agent_future_mask": [_flags(amask) for _ in inside],
        "caption": "",
        "narration": "",
    }
    if road is not None:
        frame["road"] = road
    return frame

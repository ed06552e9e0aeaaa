"""The per-frame annotation record that the synthetic world writes and every reader returns.

A real Occ3D-nuScenes directory supplies the occupancy and ego poses; everything else
here comes from occtrain's sidecar files (``occtrain/<scene>.json``), which real data
may lack. All coordinates are metres in the *current* ego frame (x forward, y left)
unless a field says "global". Yaw is in radians, counter-clockwise from +x.
"""

from __future__ import annotations

from typing import TypedDict

from occtrain.nuscenes_qa import TEMPLATE_TYPES  # noqa: F401 - re-exported: question records use it

#: High-level driving command, as in ST-P3 / UniAD (decided from the future
#: trajectory's lateral offset at the last waypoint; see COMMAND_LATERAL_THRESHOLD).
COMMANDS: tuple[str, ...] = ("turn right", "turn left", "go straight")
COMMAND_LATERAL_THRESHOLD = 2.0  # metres of lateral offset at +3 s

#: OccVLA meta actions: a speed part and a direction part.
META_SPEEDS: tuple[str, ...] = ("accelerate", "decelerate", "maintain")
META_DIRECTIONS: tuple[str, ...] = ("straight", "left", "right", "bear left", "bear right", "stop")
#: |longitudinal acceleration| below this (m/s^2, averaged over the next 1 s) is "maintain".
META_ACCEL_THRESHOLD = 0.5
#: Ego speed (m/s) at or below which the ego is "stopped".
STOP_SPEED = 0.3

#: NuScenes-QA status answers (nuScenes attribute names without their prefix).
STATUS_VALUES: tuple[str, ...] = (
    "moving",
    "parked",
    "stopped",
    "standing",
    "with rider",
    "without rider",
)




class EgoPose(TypedDict):
    translation: list[float]  # global [x, y, z]
    yaw: float  # global heading


class MetaAction(TypedDict):
    speed: str  # one of META_SPEEDS
    direction: str  # one of META_DIRECTIONS


class Box(TypedDict):
    track_id: int  # stable across the frames of a scene
    category: str  # an Occ3D class name (CLASS_NAMES[0:11])
    center: list[float]  # [x, y, z], ego frame
    size: list[float]  # [length, width, height]
    yaw: float  # ego frame
    velocity: list[float]  # [vx, vy] m/s, ego frame
    attribute: str  # one of STATUS_VALUES, or "" for static objects (barrier, cone)


class FrameAnnotation(TypedDict):
    scene: str
    token: str  # sample token, unique in the dataset
    index: int  # position of the frame in its scene
    timestamp: int  # microseconds
    ego_pose: EgoPose
    ego_speed: float  # m/s
    ego_accel: float  # m/s^2, longitudinal
    ego_yaw_rate: float  # rad/s
    command: str  # one of COMMANDS
    meta_action: MetaAction
    ego_future: list[list[float]]  # FUTURE_STEPS x [x, y]
    ego_future_mask: list[int]  # 1 where the waypoint exists (scene end cuts it)
    ego_past: list[list[float]]  # PAST_STEPS x [x, y], oldest first
    ego_past_mask: list[int]
    boxes: list[Box]  # agents and objects inside the grid's x-y range
    agent_futures: list[list[list[float]]]  # per box: FUTURE_STEPS x [x, y], current ego frame
    agent_future_mask: list[list[int]]  # per box: FUTURE_STEPS x 0/1
    caption: str
    narration: str  # chain-of-thought: surroundings -> movers -> ego plan -> meta action


class QAQuestion(TypedDict):
    """One question in NuScenes-QA's own JSON format."""

    question: str
    answer: str
    sample_token: str
    template_type: str  # one of TEMPLATE_TYPES
    num_hop: int  # 0 or 1

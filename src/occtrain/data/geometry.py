"""Ego-frame geometry shared by the synthetic world, the readers and the checks.

Ego frame: x forward, y left, origin at the ego; yaw counter-clockwise from global +x.
"""

from __future__ import annotations

import numpy as np

from occtrain.data.schema import COMMAND_LATERAL_THRESHOLD


def rotate_to_ego(vec: np.ndarray, pose_yaw: float) -> np.ndarray:
    """Global vectors (..., 2), e.g. velocities, expressed in the axes of an ego with ``pose_yaw``."""
    c, s = np.cos(pose_yaw), np.sin(pose_yaw)
    v = np.asarray(vec, dtype=np.float64)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], axis=-1)


def global_to_ego(xy: np.ndarray, pose_xy: np.ndarray, pose_yaw: float) -> np.ndarray:
    """Global points (..., 2) -> the ego frame of an ego at ``pose_xy`` / ``pose_yaw``."""
    return rotate_to_ego(np.asarray(xy, dtype=np.float64) - pose_xy, pose_yaw)


def ego_to_global(xy: np.ndarray, pose_xy: np.ndarray, pose_yaw: float) -> np.ndarray:
    """Ego-frame points (..., 2) of an ego at ``pose_xy`` / ``pose_yaw`` -> global points."""
    c, s = np.cos(pose_yaw), np.sin(pose_yaw)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1) + pose_xy


def driving_command(future: np.ndarray, mask: np.ndarray) -> str:
    """ST-P3 / UniAD driving command from the lateral offset of the last valid future waypoint."""
    valid = np.flatnonzero(mask)
    if len(valid) == 0:
        return "go straight"
    y = np.asarray(future)[valid[-1], 1]
    if y > COMMAND_LATERAL_THRESHOLD:
        return "turn left"
    if y < -COMMAND_LATERAL_THRESHOLD:
        return "turn right"
    return "go straight"

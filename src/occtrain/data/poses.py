"""Poses as nuScenes stores them: a (w, x, y, z) rotation and a translation, as a 4x4
transform and as the heading the sidecars keep. Apart from ``data.geometry`` because the
dataset layout reads poses and the CLI imports the layout, which must not import torch."""

from __future__ import annotations

import math

import numpy as np

from occtrain.data.cameras import transform


def pose_matrix(pose: dict) -> np.ndarray:
    """The 4x4 transform of a ``{"rotation": (w, x, y, z), "translation": (x, y, z)}`` pose."""
    return transform(np.asarray(pose["rotation"], np.float64), np.asarray(pose["translation"], np.float64))


def yaw_from_quaternion(q: list[float]) -> float:
    """Heading of a (w, x, y, z) quaternion, as nuScenes stores rotations."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw: float) -> list[float]:
    """The (w, x, y, z) quaternion of a heading about the z axis."""
    return [math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)]

"""Ego-frame geometry shared by the synthetic world, the readers and the checks.

Ego frame: x forward, y left, origin at the ego; yaw counter-clockwise from global +x.
"""

from __future__ import annotations

import numpy as np
import torch

from occtrain.data.schema import COMMAND_LATERAL_THRESHOLD, Command
from occtrain.formats.occ3d import FREE, VOXEL_SIZE


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


def driving_command(future: np.ndarray, mask: np.ndarray) -> Command:
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


def voxel_shift(offset_xy: tuple[float, float]) -> tuple[int, int]:
    """A move of ``offset_xy`` metres in whole voxels, as ``moved_scene`` applies it."""
    di, dj = (round(float(v) / VOXEL_SIZE) for v in offset_xy)
    return di, dj


def moved_scene(semantics: torch.Tensor, offset_xy: tuple[float, float]) -> torch.Tensor:
    """A label volume (X, Y, Z) as an ego moved by ``offset_xy`` metres (its own axes, same
    heading) would see it if nothing else moved: shifted by whole voxels, free where the
    new view reaches past the old grid."""
    di, dj = voxel_shift(offset_xy)
    out = torch.full_like(semantics, FREE)
    nx, ny = semantics.shape[:2]
    if abs(di) >= nx or abs(dj) >= ny:
        return out
    # The voxel at index i of the moved view is the one at i + di of the current grid.
    src_i, dst_i = slice(max(di, 0), nx + min(di, 0)), slice(max(-di, 0), nx - max(di, 0))
    src_j, dst_j = slice(max(dj, 0), ny + min(dj, 0)), slice(max(-dj, 0), ny - max(dj, 0))
    out[dst_i, dst_j] = semantics[src_i, src_j]
    return out

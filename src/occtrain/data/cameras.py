"""Surround cameras: the nuScenes rig, their calibration, and projection between the ego
frame and each camera's pixels.

Frames: ego (x forward, y left, z up, metres), camera (OpenCV and nuScenes: x right, y down,
z forward along the optical axis), pixels (u right, v down, pixel centres at +0.5).
Calibration is what Occ3D's ``camera_sensor`` records hold: a 3 x 3 ``intrinsic`` and an
``extrinsic`` camera-to-ego ``translation`` + ``rotation`` quaternion (w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

#: The six nuScenes cameras, in the order every occtrain tensor stacks them.
CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
#: nuScenes' image size, which the rig below is calibrated for.
NUSCENES_SIZE = (900, 1600)  # (height, width)

#: (x, y, z in the ego frame, yaw in degrees, focal length in nuScenes pixels) of each camera,
#: rounded from the nuScenes calibration: about 70-degree views all around, the back camera
#: wider (about 110 degrees) at a shorter focal length.
_RIG = {
    "CAM_FRONT": (1.70, 0.02, 1.51, 0.0, 1266.4),
    "CAM_FRONT_RIGHT": (1.55, -0.49, 1.49, -55.0, 1260.8),
    "CAM_FRONT_LEFT": (1.52, 0.49, 1.51, 55.0, 1272.6),
    "CAM_BACK": (0.03, 0.00, 1.57, 180.0, 809.2),
    "CAM_BACK_LEFT": (1.04, 0.48, 1.49, 110.0, 1256.7),
    "CAM_BACK_RIGHT": (1.05, -0.48, 1.49, -110.0, 1259.5),
}


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2
    x = np.copysign(x, r[2, 1] - r[1, 2])
    y = np.copysign(y, r[0, 2] - r[2, 0])
    z = np.copysign(z, r[1, 0] - r[0, 1])
    return np.array([w, x, y, z])


def transform(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> np.ndarray:
    """The 4 x 4 homogeneous transform of a rotation (3 x 3 or a quaternion) and translation."""
    rot = np.asarray(rotation, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(rot) if rot.shape == (4,) else rot
    out[:3, 3] = translation
    return out


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: its name, image size, intrinsics and pose on the ego."""

    name: str
    height: int
    width: int
    intrinsic: np.ndarray  # (3, 3)
    cam_to_ego: np.ndarray  # (4, 4)

    @property
    def centre(self) -> np.ndarray:
        """The optical centre in the ego frame (3,)."""
        return self.cam_to_ego[:3, 3]

    @cached_property
    def ego_to_cam(self) -> np.ndarray:
        return np.linalg.inv(self.cam_to_ego)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ego-frame points (..., 3) -> pixel coordinates (..., 2), camera-z depth (...,) and
        whether each lands in the image in front of the camera (...,)."""
        p = np.asarray(points, dtype=np.float64)
        cam = p @ self.ego_to_cam[:3, :3].T + self.ego_to_cam[:3, 3]
        depth = cam[..., 2]
        safe = np.where(np.abs(depth) < 1e-9, 1e-9, depth)
        uvw = cam @ self.intrinsic.T
        uv = uvw[..., :2] / safe[..., None]
        inside = (
            (depth > 1e-6)
            & (uv[..., 0] >= 0)
            & (uv[..., 0] < self.width)
            & (uv[..., 1] >= 0)
            & (uv[..., 1] < self.height)
        )
        return uv, depth, inside

    def lift(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) at camera-z ``depth`` (...,) -> ego-frame points (..., 3)."""
        uv = np.asarray(uv, dtype=np.float64)
        rays = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1) @ np.linalg.inv(self.intrinsic).T
        cam = rays * np.asarray(depth, dtype=np.float64)[..., None]
        return cam @ self.cam_to_ego[:3, :3].T + self.cam_to_ego[:3, 3]

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit ego-frame directions (H, W, 3) through every pixel centre, and the cosine
        between each and the optical axis (H, W): camera-z depth = range x cosine."""
        v, u = np.meshgrid(np.arange(self.height) + 0.5, np.arange(self.width) + 0.5, indexing="ij")
        ends = self.lift(np.stack([u, v], axis=-1), np.ones(u.shape))
        dirs = ends - self.centre
        norm = np.linalg.norm(dirs, axis=-1, keepdims=True)
        return dirs / norm, 1.0 / norm[..., 0]


def nuscenes_rig(height: int, width: int) -> list[Camera]:
    """The six nuScenes cameras with intrinsics scaled to ``height`` x ``width`` images."""
    sy, sx = height / NUSCENES_SIZE[0], width / NUSCENES_SIZE[1]
    cams = []
    for name in CAMERA_NAMES:
        x, y, z, yaw_deg, focal = _RIG[name]
        yaw = np.deg2rad(yaw_deg)
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        k = np.array([[focal * sx, 0.0, width / 2], [0.0, focal * sy, height / 2], [0.0, 0.0, 1.0]])
        cams.append(Camera(name, height, width, k, transform(np.stack([right, down, forward], axis=1), [x, y, z])))
    return cams


__all__ = ["CAMERA_NAMES", "Camera", "matrix_to_quaternion", "nuscenes_rig", "quaternion_to_matrix", "transform"]

"""A camera as a dataset records it: the ``camera_sensor`` entry of Occ3D's annotations
(image path, intrinsics, extrinsic, ego pose) written and read back, and its images."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occtrain.data.cameras import Camera, matrix_to_quaternion
from occtrain.errors import DataError

#: Beside each synthetic image: per-pixel class (uint8, FREE for sky) and camera-z depth
#: (uint16 centimetres, 0 for sky), e.g. imgs/CAM_FRONT/<token>.png and <token>_class.png.
CLASS_SUFFIX, DEPTH_SUFFIX = "_class", "_depth"
DEPTH_SCALE = 100.0


def camera_record(cam: Camera, img_path: str, ego_pose: dict) -> dict:
    """A ``camera_sensor`` record as the released Occ3D files hold it (keyed by its channel;
    ``img_path`` relative to ``imgs/``)."""
    return {
        "img_path": img_path,
        "intrinsics": cam.intrinsic.tolist(),
        "extrinsic": {
            "translation": cam.cam_to_ego[:3, 3].tolist(),
            "rotation": matrix_to_quaternion(cam.cam_to_ego[:3, :3]).tolist(),
        },
        "ego_pose": ego_pose,
    }


@dataclass(frozen=True)
class CameraRecord:
    """One camera of one sample, read back: its image file and its calibration."""

    name: str  # CAM_FRONT, ... (the folder of its image)
    image: Path
    intrinsic: np.ndarray  # (3, 3)
    cam_to_ego: np.ndarray  # (4, 4)
    ego_to_global: np.ndarray  # (4, 4)

    @property
    def maps(self) -> tuple[Path, Path]:
        """Where the renderer's per-pixel class and depth maps of this image lie (synthetic data)."""
        return (
            self.image.with_name(f"{self.image.stem}{CLASS_SUFFIX}.png"),
            self.image.with_name(f"{self.image.stem}{DEPTH_SUFFIX}.png"),
        )

    def camera(self, height: int, width: int) -> Camera:
        return Camera(self.name, height, width, self.intrinsic, self.cam_to_ego)


def read_image(path: Path) -> np.ndarray:
    """An image file as uint8 (H, W, 3), or a single-channel PNG as its own dtype (H, W)."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise DataError(f"{path}: image not found; the dataset's camera_sensor records name it")
    try:
        with Image.open(path) as img:
            arr = np.asarray(img.convert("RGB") if img.mode in ("P", "RGBA", "CMYK", "YCbCr", "LA") else img)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise DataError(f"{path}: not a readable image ({err}); re-create it") from None
    return arr

"""Writing an Occ3D-layout dataset: one scene's files at a time (labels, camera images,
then its frame sidecar, which marks it complete), then the dataset-wide records; each file
written atomically, so a synthesis cut off anywhere resumes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.camera_records import CLASS_SUFFIX, DEPTH_SCALE, DEPTH_SUFFIX, camera_record
from occtrain.data.cameras import Camera
from occtrain.data.labels import validate_labels
from occtrain.data.layout import (
    ANNOTATIONS_FILE,
    DATASET_FILE,
    FRAMES_DIR,
    FRAMES_HINT,
    GTS_DIR,
    IMGS_DIR,
    LABELS_FILE,
    SPLITS,
    qa_file,
    read_json,
)
from occtrain.data.poses import quaternion_from_yaw
from occtrain.data.schema import FrameAnnotation, QAQuestion
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_bytes, atomic_write_json, atomic_write_npz, png_bytes


def scene_infos(scene: str, frames: list[FrameAnnotation], cameras: list[Camera] | None = None) -> dict[str, dict]:
    """The ``scene_infos`` entry of annotations.json for a scene's frames (as written by SceneFiles)."""
    infos = {}
    for i, f in enumerate(frames):
        x, y = f["ego_pose"]["translation"][:2]
        pose = {"translation": [x, y, 0.0], "rotation": quaternion_from_yaw(f["ego_pose"]["yaw"])}
        infos[f["token"]] = {
            "timestamp": f["timestamp"],
            "ego_pose": pose,
            "gt_path": f"{GTS_DIR}/{scene}/{f['token']}/{LABELS_FILE}",
            "prev": frames[i - 1]["token"] if i > 0 else "",
            "next": frames[i + 1]["token"] if i + 1 < len(frames) else "",
        }
        if cameras:
            infos[f["token"]]["camera_sensor"] = {
                cam.name: camera_record(cam, f"{cam.name}/{f['token']}.png", pose) for cam in cameras
            }
    return infos


class SceneFiles:
    """The files of one scene under a dataset root: each frame's labels and camera images,
    then the scene's frame sidecar, which marks the scene complete. What a synthesis
    worker process writes; :class:`DatasetWriter` adds the dataset-wide records."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def scene_done(self, scene: str) -> bool:
        return (self.root / FRAMES_DIR / f"{scene}.json").is_file()

    def write_labels(self, scene: str, token: str, arrays: dict[str, np.ndarray]) -> None:
        """Validate and atomically write one frame's ``labels.npz``."""
        path = self.root / GTS_DIR / scene / token / LABELS_FILE
        validate_labels(arrays, str(path))
        atomic_write_npz(path, arrays)

    def write_images(self, token: str, views: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]) -> None:
        """Write one frame's camera images (name, image (H, W, 3) uint8, classes (H, W) uint8,
        depth (H, W) metres) as PNGs under ``imgs/<name>/``, before the frame's scene completes."""
        for name, image, classes, depth in views:
            folder = self.root / IMGS_DIR / name
            atomic_write_bytes(folder / f"{token}.png", png_bytes(image))
            atomic_write_bytes(folder / f"{token}{CLASS_SUFFIX}.png", png_bytes(classes))
            centimetres = np.clip(np.round(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)
            atomic_write_bytes(folder / f"{token}{DEPTH_SUFFIX}.png", png_bytes(centimetres))

    def write_frames(self, scene: str, frames: list[FrameAnnotation]) -> None:
        """Write the scene's frame sidecar (after its labels): the scene is then complete."""
        atomic_write_json(self.root / FRAMES_DIR / f"{scene}.json", frames, indent=None)

    def read_scene(self, scene: str) -> list[FrameAnnotation]:
        """A completed scene's frames."""
        return read_json(
            self.root / FRAMES_DIR / f"{scene}.json", "frame annotations", list[FrameAnnotation], FRAMES_HINT
        )


class DatasetWriter(SceneFiles):
    """Writes a dataset in the Occ3D layout; refuses to mix into a different dataset.

    Scene by scene: labels first, then the scene's sidecar (which marks the scene
    complete), and ``annotations.json`` last (which marks the dataset complete), so an
    interrupted write resumes where it stopped and never leaves a readable half-dataset.
    """

    def __init__(self, root: str | Path, fingerprint: dict):
        super().__init__(root)
        self.fingerprint = fingerprint
        record = self.root / DATASET_FILE
        if record.is_file():
            existing = read_json(
                record, "dataset record", dict[str, Any], "delete that directory or choose another --out"
            )
            if existing != fingerprint:
                diff = sorted(k for k in set(existing) | set(fingerprint) if existing.get(k) != fingerprint.get(k))
                raise DataError(
                    f"{self.root}: already holds a different dataset (differs in {', '.join(diff)}); "
                    "choose another --out or delete that directory"
                )
        elif self.root.exists() and any(self.root.iterdir()):
            raise DataError(
                f"{self.root}: exists and is not an occtrain dataset; choose an empty or new --out directory"
            )
        atomic_write_json(record, fingerprint)
        self._scene_infos: dict[str, dict] = {}
        self._splits: dict[str, list[str]] = {s: [] for s in SPLITS}

    @property
    def complete(self) -> bool:
        return (self.root / ANNOTATIONS_FILE).is_file()

    def write_scene(
        self, scene: str, split: str, frames: list[FrameAnnotation], cameras: list[Camera] | None = None
    ) -> None:
        """Write the scene's frame sidecar (after its labels) and record it for the dataset's records."""
        self.write_frames(scene, frames)
        self.add_scene_info(scene, split, frames, cameras)

    def add_scene_info(
        self, scene: str, split: str, frames: list[FrameAnnotation], cameras: list[Camera] | None = None
    ) -> None:
        self._scene_infos[scene] = scene_infos(scene, frames, cameras)
        self._splits[split].append(scene)

    def finalize(self, questions: dict[str, list[QAQuestion]]) -> None:
        """Write the QA files and, last, annotations.json."""
        for split, qs in questions.items():
            atomic_write_json(
                self.root / qa_file(split), {"info": {"generator": "occtrain.synth", "split": split}, "questions": qs}
            )
        atomic_write_json(
            self.root / ANNOTATIONS_FILE,
            {f"{s}_split": names for s, names in self._splits.items()} | {"scene_infos": self._scene_infos},
            indent=None,
        )

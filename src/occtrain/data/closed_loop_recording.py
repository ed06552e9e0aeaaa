"""Closed-loop driving's data: the synthetic world driven step by step (the simulator, its
ego's controller and vehicle model), and each planning frame written as a stage reads a
dataset. The loop that drives it is the engine's (``engine.closed_loop``).

The closed loop's entry to the generator (``data/synth``), as ``data/synthesize.py`` is the
data synthesis's. An :class:`EpisodeRecorder` writes every planning frame of a
:class:`~occtrain.data.synth.closed_loop_world.DrivingWorld` into an Occ3D-layout directory with the
generator's own writers (labels, the six cameras) and keeps the frame annotations in
memory, so a stage reads a closed-loop frame through exactly the code that
reads its training frames (``DatasetIndex``, the frozen encoders' ``add_samples``), and
:meth:`EpisodeRecorder.clip` is the clip a stage plans on: the driven history, the frame
now, and a future nobody knows yet (driving on at constant velocity stands in for it).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occtrain.data.cameras import Camera, nuscenes_rig
from occtrain.data.clips import Clip
from occtrain.data.dataset_writer import SceneFiles, scene_infos
from occtrain.data.layout import ANNOTATIONS_FILE, FRAMES_DIR, DatasetIndex
from occtrain.data.schema import FrameAnnotation
from occtrain.data.synth.closed_loop_view import ViewFrame, save_gif
from occtrain.data.synth.closed_loop_world import MAX_SECONDS, STRIDE, Agents, DrivingWorld
from occtrain.data.synth.traffic import SIM_DT
from occtrain.data.synth.vehicle import PlanTracker, bicycle_step
from occtrain.formats.io import atomic_write_json
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS

#: The scene name of an episode's frames in its directory.
EPISODE_SCENE = "episode"


class _EpisodeIndex(DatasetIndex):
    """The episode so far as a dataset whose frame annotations stay in memory: rewriting the
    whole sidecar at every planning frame made recording quadratic in the episode's length
    (9 of the 16 s a 20 s route spent recording)."""

    def __init__(self, root: Path, annotations: dict, scene: str, frames: list[FrameAnnotation]):
        super().__init__(root, annotations)
        self._scene = scene
        self._frames = list(frames)

    def has_frame_annotations(self, scene: str) -> bool:
        return scene == self._scene or super().has_frame_annotations(scene)

    def frames(self, scene: str) -> list[FrameAnnotation]:
        if scene != self._scene:
            return super().frames(scene)
        return self._frames


class EpisodeRecorder:
    """Writes ``world``'s planning frames under ``root`` and indexes them as one val scene
    (``scene``); ``episode`` sets its frames' tokens apart from other episodes' on the same route."""

    def __init__(
        self,
        root: str | Path,
        world: DrivingWorld,
        camera_size: tuple[int, int] | None,
        episode: str = "",
        scene: str = EPISODE_SCENE,
    ):
        self.root = Path(root)
        self.world = world
        self.episode = episode
        self.scene = scene
        self.files = SceneFiles(self.root)
        self.camera_size = camera_size
        self.rig: list[Camera] = nuscenes_rig(*camera_size) if camera_size else []
        self.frames: list[FrameAnnotation] = []
        self.index: DatasetIndex | None = None

    def record(self) -> DatasetIndex:
        """Write the planning frame now (labels, cameras), keep its annotation, and index the episode so far."""
        world = self.world
        frame = world.frame_annotation(self.scene, self.episode)
        labels = world.render()
        self.files.write_labels(self.scene, frame["token"], labels)
        if self.rig:
            assert self.camera_size is not None
            views = world.cameras(labels["semantics"], *self.camera_size)
            self.files.write_images(
                frame["token"], [(c.name, v.image, v.classes, v.depth) for c, v in zip(self.rig, views)]
            )
        self.frames.append(frame)
        annotations = {
            "train_split": [],
            "val_split": [self.scene],
            "scene_infos": {self.scene: scene_infos(self.scene, self.frames, self.rig or None)},
        }
        self.index = _EpisodeIndex(self.root, annotations, self.scene, self.frames)
        return self.index

    @property
    def token(self) -> str:
        return self.frames[-1]["token"]

    def clip(self, history: int, at: int = -1) -> Clip:
        """The clip anchored at recorded frame ``at`` (the last by default) with ``history``
        frames before it (as many as there are) and FUTURE_STEPS future frames driven on at
        constant velocity: their tokens name no frame, and no prompt reads a future frame's
        scene, so a clip never reads what was recorded after its anchor."""
        if not self.frames:
            raise ValueError("record a frame before asking for its clip")
        end = at % len(self.frames) + 1
        frames = self.frames[max(0, end - 1 - history) : end]
        anchor = frames[-1]
        yaw = anchor["ego_pose"]["yaw"]
        x, y = anchor["ego_pose"]["translation"][:2]
        step = anchor["ego_speed"] * FRAME_DT
        future = [[x + k * step * np.cos(yaw), y + k * step * np.sin(yaw), yaw] for k in range(1, FUTURE_STEPS + 1)]
        ann = {
            "anchor": anchor,
            "tokens": [f["token"] for f in frames] + [f"{anchor['token']}+{k}" for k in range(1, FUTURE_STEPS + 1)],
            "ego_poses": [[*f["ego_pose"]["translation"][:2], f["ego_pose"]["yaw"]] for f in frames] + future,
            "history": len(frames) - 1,
            "future": FUTURE_STEPS,
            "split": "val",
        }
        return Clip(ann, [], anchor["narration"])


class RecordedDataset:
    """Frames a policy drove into, kept as one dataset in the Occ3D layout under ``root``:
    one train scene per driven route, its labels and cameras written as it is driven (an
    :class:`EpisodeRecorder` with the route's scene name), its frame sidecar when it ends
    (which marks it complete), and ``annotations.json`` listing the complete scenes,
    rewritten atomically after each. Closed-loop training's aggregate, read back as any
    dataset is (``DatasetIndex``, ``frame_clips``)."""

    def __init__(self, root: str | Path, rig: list[Camera] | None = None):
        self.root = Path(root)
        self.files = SceneFiles(self.root)
        self.rig = rig

    def write_index(self, scenes: list[str]) -> DatasetIndex:
        """``annotations.json`` of ``scenes`` (each complete), written atomically; the dataset opened."""
        infos = {}
        for scene in scenes:
            frames = json.loads((self.root / FRAMES_DIR / f"{scene}.json").read_text())
            infos[scene] = scene_infos(scene, frames, self.rig or None)
        atomic_write_json(
            self.root / ANNOTATIONS_FILE,
            {"train_split": list(scenes), "val_split": [], "scene_infos": infos},
            indent=None,
        )
        return DatasetIndex.open(self.root)


__all__ = [
    "EPISODE_SCENE",
    "MAX_SECONDS",
    "SIM_DT",
    "STRIDE",
    "Agents",
    "DrivingWorld",
    "EpisodeRecorder",
    "PlanTracker",
    "RecordedDataset",
    "ViewFrame",
    "bicycle_step",
    "save_gif",
]

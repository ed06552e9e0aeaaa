"""The Occ3D-nuScenes directory layout: its paths, and reading it (``DatasetIndex``).

```
ROOT/
  annotations.json                    Occ3D: train_split, val_split, scene_infos (ordered samples, ego poses)
  gts/<scene>/<sample_token>/labels.npz   semantics, mask_lidar, mask_camera (uint8, 200x200x16)
  occtrain/dataset.json               what generated the directory (its fingerprint)          [sidecar]
  occtrain/frames/<scene>.json        FrameAnnotation list: trajectories, boxes, text, ...     [sidecar]
  nuscenes_qa/NuScenes_<split>_questions.json   NuScenes-QA format                           [sidecar]
```

A real Occ3D-nuScenes download has the first two; the sidecars are occtrain's own. The
synthetic world is written through ``data.dataset_writer.DatasetWriter`` and read back through
:class:`DatasetIndex`, exactly like real data. Its neighbours: ``data.labels`` (the label
files), ``data.camera_records`` (a camera's record and images), ``data.identity`` (which
world a dataset is) and ``data.poses`` (poses as nuScenes stores them).
"""

from __future__ import annotations

import hashlib
import math
import posixpath
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.camera_records import DEPTH_SCALE, CameraRecord, read_image
from occtrain.data.cameras import CAMERA_NAMES
from occtrain.data.labels import load_labels
from occtrain.data.poses import pose_matrix, yaw_from_quaternion
from occtrain.data.schema import FrameAnnotation, Occ3DAnnotations, QAFile, QAQuestion
from occtrain.data.validate import first_problem
from occtrain.errors import DataError
from occtrain.formats.io import parse_json
from occtrain.formats.occ3d import FRAME_DT

ANNOTATIONS_FILE = "annotations.json"
GTS_DIR = "gts"
LABELS_FILE = "labels.npz"
SIDECAR_DIR = "occtrain"
DATASET_FILE = f"{SIDECAR_DIR}/dataset.json"
FRAMES_DIR = f"{SIDECAR_DIR}/frames"
QA_DIR = "nuscenes_qa"
SPLITS = ("train", "val")
IMGS_DIR = "imgs"


#: What to do about a bad file, after its one-line problem.
ANNOTATIONS_HINT = "fix that key, or re-download (Occ3D-nuScenes) or re-create (occtrain data synth) the dataset"
FRAMES_HINT = "re-create the sidecar with `occtrain data synth`, or delete it to train without the tasks it feeds"
QA_HINT = 'NuScenes-QA format is {"questions": [...]}; fix the file, or delete it to train without QA'


def qa_file(split: str) -> str:
    """Relative path of a split's NuScenes-QA question file."""
    return f"{QA_DIR}/NuScenes_{split}_questions.json"


# ----------------------------------------------------------------------------- reading


#: What a pose of a real log can be: a rotation is a unit quaternion (to this tolerance), a
#: translation lies within this many metres of the map's origin (nuScenes' maps are a few km
#: across), and the ego moves between consecutive samples at most this fast (m/s, 250 km/h):
#: a larger jump is a teleport, two logs spliced or a unit slip, and every trajectory, box and
#: moved scene built across it would be garbage.
QUATERNION_TOLERANCE = 1e-3
MAX_TRANSLATION = 1.0e6
MAX_EGO_SPEED = 70.0


def pose_problem(pose: dict) -> str | None:
    """What is wrong with a ``{"translation", "rotation"}`` pose: ``rotation [...] is not a
    unit quaternion ...`` (a key and what it holds), or None."""
    q = np.asarray(pose["rotation"], np.float64)
    norm = float(np.sqrt((q * q).sum()))
    if not math.isfinite(norm) or abs(norm - 1.0) > QUATERNION_TOLERANCE:
        return f"rotation {pose['rotation']} is not a unit quaternion (its norm is {norm:.4g})"
    t = np.asarray(pose["translation"], np.float64)
    if not np.isfinite(t).all() or np.abs(t).max() > MAX_TRANSLATION:
        return f"translation {pose['translation']} is not within {MAX_TRANSLATION:g} m of the origin"
    return None


def ego_pose_problems(scenes: dict[str, list[str]], infos: dict[str, dict[str, dict]], src: Path) -> Iterator[str]:
    """Every ego pose of ``scenes`` (samples in order) that is not a unit rotation and a
    finite, bounded translation, and every jump between consecutive samples faster than
    ``MAX_EGO_SPEED``: one line each, naming the sample in ``src``."""
    for scene, tokens in scenes.items():
        for token in tokens:
            problem = pose_problem(infos[scene][token]["ego_pose"])
            if problem:
                yield f"{src}: scene_infos.{scene}.{token}.ego_pose.{problem}; {ANNOTATIONS_HINT}"
        for before, token in zip(tokens, tokens[1:]):
            a, b = infos[scene][before], infos[scene][token]
            if pose_problem(a["ego_pose"]) or pose_problem(b["ego_pose"]):
                continue
            moved = math.dist(a["ego_pose"]["translation"][:2], b["ego_pose"]["translation"][:2])
            t0, t1 = sample_time(a), sample_time(b)
            seconds = max((t1 - t0) / 1e6 if t0 is not None and t1 is not None else 0.0, FRAME_DT)
            if moved > MAX_EGO_SPEED * seconds:
                yield (
                    f"{src}: scene_infos.{scene}.{token}.ego_pose is {moved:.1f} m from the sample before it "
                    f"({before}) after {seconds:g} s, faster than {MAX_EGO_SPEED:g} m/s: a jump no car makes; "
                    f"{ANNOTATIONS_HINT}"
                )


#: Digests of the JSON texts this process has found to conform to a schema, with the
#: schema's name. Every stage of a run reads the world's sidecars again (and a test session
#: reads one world hundreds of times); walking a scene's frames through their schema costs
#: far more than parsing them, and a text that conformed once conforms again.
_CONFORMING: set[tuple[str, bytes]] = set()


def read_json(path: Path, what: str, schema: Any = None, hint: str = "re-create the file") -> Any:
    """A JSON file, checked against ``schema`` when given; the first problem is one DataError line."""
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    try:
        text = path.read_text()
        data = parse_json(text)  # NaN/Infinity parse; the schema names the key that holds one
    except ValueError as err:
        raise DataError(f"{path}: not valid JSON ({err}); {hint}") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read it ({err.strerror})") from None
    if schema is not None:
        seen = (repr(schema), hashlib.blake2b(text.encode("utf-8", "surrogatepass")).digest())
        if seen not in _CONFORMING:
            problem = first_problem(data, schema)
            if problem:
                raise DataError(f"{path}: {problem}; {hint}")
            _CONFORMING.add(seen)
    return data


def sample_time(info: dict) -> int | None:
    """A sample's timestamp in microseconds: an int, or a string of digits (as Occ3D stores
    it); None for a timestamp that is not a number (Occ3D allows "timestamp (or token)")."""
    stamp = info.get("timestamp")
    if type(stamp) is int:
        return stamp
    if isinstance(stamp, str) and stamp.isascii() and stamp.isdigit():
        return int(stamp)
    return None


def _order_samples(scene: str, infos: dict[str, dict], source: Path) -> list[str]:
    """Samples of a scene in time order: by their prev/next links, else by timestamp."""
    tokens = list(infos)
    firsts = [t for t in tokens if not infos[t].get("prev")]
    if len(firsts) == 1:
        order, cur, seen = [], firsts[0], set()
        while cur and cur in infos and cur not in seen:  # a missing "next" ends the chain, as "" does
            order.append(cur)
            seen.add(cur)
            cur = infos[cur].get("next", "")
        if len(order) == len(tokens):
            return order
    stamps = {t: stamp for t in tokens if (stamp := sample_time(infos[t])) is not None}
    odd = next((t for t in tokens if t not in stamps), None)
    if odd is not None:
        raise DataError(
            f"{source}: scene_infos.{scene}.{odd}.timestamp is not a number of microseconds and the scene's "
            "prev/next links do not chain its samples, so their order is unknown; fix the links or the timestamps"
        )
    return sorted(tokens, key=lambda t: stamps[t])


def inside_root(rel: str) -> bool:
    """Whether a path read from a data file stays inside the directory it is relative to.

    Lexical: links are checked where each file is read (``DatasetIndex.within``), so opening
    a release of many files stats none of them."""
    if not rel or rel.startswith(("/", "\\")) or (len(rel) > 1 and rel[1] == ":"):
        return False
    return not posixpath.normpath(rel.replace("\\", "/")).startswith("..")


def generator_record(root: Path) -> dict | None:
    """occtrain's record of what generated the directory ``root`` (``occtrain/dataset.json``),
    if any; it is written first, so a synthesis cut off halfway has it too."""
    path = Path(root) / DATASET_FILE
    return read_json(path, "dataset record", dict[str, Any]) if path.is_file() else None


def dataset_root(path: str | Path) -> Path:
    """The dataset root that ``path`` names: itself, or the parent of its ``gts/`` directory."""
    path = Path(path)
    return path.parent if path.name == GTS_DIR and not (path / ANNOTATIONS_FILE).exists() else path


class DatasetIndex:
    """An Occ3D-layout dataset on disk: scene order, splits, labels and the optional sidecars."""

    def __init__(self, root: Path, annotations: dict, check_poses: bool = True):
        """``check_poses``: refuse the first ego pose that is not one (``ego_pose_problems``);
        ``data check``, which lists them all, opens without."""
        self.root = root
        src = root / ANNOTATIONS_FILE
        if not isinstance(annotations, dict) or "scene_infos" not in annotations:
            raise DataError(f"{src}: no 'scene_infos' key; is this an Occ3D annotations file?")
        problem = first_problem(annotations, Occ3DAnnotations)
        if problem:
            raise DataError(f"{src}: {problem}; {ANNOTATIONS_HINT}")
        self.scene_infos: dict[str, dict[str, dict]] = annotations["scene_infos"]
        self.scenes: dict[str, list[str]] = {
            scene: _order_samples(scene, infos, src) for scene, infos in self.scene_infos.items()
        }
        self.splits: dict[str, list[str]] = {}
        for split in SPLITS:
            names = annotations.get(f"{split}_split", [])
            unknown = [n for n in names if n not in self.scenes]
            if unknown:
                raise DataError(
                    f"{src}: {split}_split names scene '{unknown[0]}' that has no scene_infos entry; {ANNOTATIONS_HINT}"
                )
            self.splits[split] = list(names)
        self._scene_of = {tok: scene for scene, toks in self.scenes.items() for tok in toks}
        self._check_paths(src)
        if check_poses:
            problem = next(ego_pose_problems(self.scenes, self.scene_infos, src), None)
            if problem:
                raise DataError(problem)

    def _check_paths(self, src: Path) -> None:
        """Every gt_path and img_path names a file inside the root: one that points out of it
        (``../../etc/passwd``, ``/etc/passwd``) is never opened, however valid the file."""
        for scene, infos in self.scene_infos.items():
            for token, info in infos.items():
                paths = [("gt_path", info.get("gt_path"))]
                paths += [
                    (f"camera_sensor.{key}.img_path", r.get("img_path"))
                    for key, r in (info.get("camera_sensor") or {}).items()
                ]
                for key, rel in paths:
                    if rel is not None and not inside_root(rel):
                        raise DataError(
                            f"{src}: scene_infos.{scene}.{token}.{key} '{rel}' points outside the dataset root "
                            f"{self.root}; "
                            "paths in annotations.json are relative to the root"
                        )

    @classmethod
    def open(cls, path: str | Path, check_poses: bool = True) -> DatasetIndex:
        """Open a dataset root (or its ``gts/`` directory)."""
        path = dataset_root(path)
        if not path.is_dir():
            raise DataError(
                f"{path}: dataset directory not found; run `occtrain data synth --out {path}` or point at an "
                "Occ3D-nuScenes root"
            )
        ann = path / ANNOTATIONS_FILE
        if not ann.is_file():
            raise DataError(f"{ann}: annotations file not found; an Occ3D root holds annotations.json and gts/")
        if not ann.resolve().is_relative_to(path.resolve()):
            raise DataError(
                f"{ann}: a link out of the dataset root (to {ann.resolve()}); copy the file into the root, or link "
                "the whole root"
            )
        return cls(path, read_json(ann, "annotations file"), check_poses)

    # -- structure
    def scene_of(self, token: str) -> str:
        return self._scene_of[token]

    def samples(self, split: str | None = None) -> Iterator[tuple[str, str]]:
        """(scene, token) pairs in scene order, for one split or all scenes."""
        scenes = self.splits.get(split, []) if split else list(self.scenes)
        for scene in scenes:
            for token in self.scenes[scene]:
                yield scene, token

    def labels_path(self, scene: str, token: str) -> Path:
        rel = self.info(scene, token).get("gt_path") or f"{GTS_DIR}/{scene}/{token}/{LABELS_FILE}"
        return self.within(self.root / rel)

    def within(self, path: Path) -> Path:
        """``path``, refused in one line when a link takes it out of the root: as a gt_path
        outside it is (a dataset kept on another disk links its root, which may be a link)."""
        real = path.resolve()
        if not real.is_relative_to(self._real_root):
            raise DataError(
                f"{path}: a link out of the dataset root {self.root} (to {real}); copy the file into the root, or "
                "link the whole root (data.root may itself be a link)"
            )
        return path

    @cached_property
    def _real_root(self) -> Path:
        return self.root.resolve()

    def labels(self, scene: str, token: str) -> dict[str, np.ndarray]:
        return load_labels(self.labels_path(scene, token))

    def info(self, scene: str, token: str) -> dict:
        """The annotations.json record of a sample (checked against Occ3DSample on opening)."""
        try:
            return self.scene_infos[scene][token]
        except KeyError:
            raise DataError(f"{self.root / ANNOTATIONS_FILE}: no sample scene_infos.{scene}.{token}") from None

    @cached_property
    def has_cameras(self) -> bool:
        """Whether samples carry ``camera_sensor`` records and images exist for them.

        Any image of the first sample present means the dataset has cameras: then every
        folder the records name must exist (a deleted ``imgs/CAM_BACK`` is refused here,
        naming it, before a run writes anything), and a missing image is an error naming it
        later, never a quiet shard set without cameras."""
        first = next(self.samples(), None)
        records = self.info(*first).get("camera_sensor") if first else None
        if not records or not any(self.image_path(r["img_path"]).is_file() for r in records.values()):
            return False
        self._check_camera_folders()
        return True

    def _check_camera_folders(self) -> None:
        """Refuse a camera folder that no longer exists, naming it where the images would be.

        One stat per distinct folder, not per image: a release holds hundreds of thousands."""
        seen: set[str] = set()
        for scene, infos in self.scene_infos.items():
            for token, info in infos.items():
                for key, record in (info.get("camera_sensor") or {}).items():
                    folder = posixpath.dirname(record["img_path"])
                    if folder in seen:
                        continue
                    seen.add(folder)
                    if not (self.root / folder).is_dir() and not (self.root / IMGS_DIR / folder).is_dir():
                        raise DataError(
                            f"{self._image_base / folder}: camera folder not found, while "
                            f"{self.root / ANNOTATIONS_FILE} names "
                            f"images in it (scene_infos.{scene}.{token}.camera_sensor.{key}.img_path "
                            f"'{record['img_path']}'); "
                            "restore it (the release's images, or `occtrain data synth` for a synthetic world)"
                        )

    @cached_property
    def _image_base(self) -> Path:
        """Where this dataset's ``img_path`` values are relative to: the root (the README's
        form) or ``imgs/`` (the released files'), told by the first sample's images found."""
        first = next(self.samples(), None)
        records = (self.info(*first).get("camera_sensor") or {}) if first else {}
        for record in records.values():
            for base in (self.root, self.root / IMGS_DIR):
                if (base / record["img_path"]).is_file():
                    return base
        # No image to tell by: a path under imgs/ names itself; any other is the released form
        # when imgs/ exists.
        rel = next((r["img_path"] for r in records.values()), "")
        released = (self.root / IMGS_DIR).is_dir() and not rel.startswith(f"{IMGS_DIR}/")
        return self.root / IMGS_DIR if released else self.root

    def image_path(self, img_path: str) -> Path:
        """Where a record's ``img_path`` lies: relative to the root (the README's form), or
        to ``imgs/`` (the released files'). A missing image is named where this dataset's
        images lie, so its message points at the real place (``imgs/CAM_BACK/...``)."""
        direct = self.root / img_path
        in_imgs = self.root / IMGS_DIR / img_path
        if direct.is_file():
            return self.within(direct)
        return self.within(in_imgs if in_imgs.is_file() else self._image_base / img_path)

    def cameras(self, scene: str, token: str) -> list[CameraRecord]:
        """The sample's six cameras in CAMERA_NAMES order: records keyed by channel (the
        released files), or by camera token and named by their image's folder (the README)."""
        info = self.info(scene, token)
        records = info.get("camera_sensor")
        src = self.root / ANNOTATIONS_FILE
        if not records:
            raise DataError(
                f"{src}: sample scene_infos.{scene}.{token} has no camera_sensor; stages that read images (vision) "
                "need the cameras"
            )
        by_name = {}
        for key, r in records.items():  # the schema checked every record's keys on opening
            name = key if key in CAMERA_NAMES else Path(r["img_path"]).parent.name
            for pose in ("extrinsic", "ego_pose"):
                problem = pose_problem(r[pose])
                if problem:
                    raise DataError(
                        f"{src}: scene_infos.{scene}.{token}.camera_sensor.{key}.{pose} {problem}; {ANNOTATIONS_HINT}"
                    )
            intrinsic = r.get("intrinsics", r.get("intrinsic"))
            if intrinsic is None:
                raise DataError(
                    f"{src}: scene_infos.{scene}.{token}.camera_sensor.{key} has neither intrinsics nor intrinsic; a "
                    "camera needs its 3 x 3 matrix"
                )
            by_name[name] = CameraRecord(
                name,
                self.image_path(r["img_path"]),
                np.asarray(intrinsic, np.float64),
                pose_matrix(r["extrinsic"]),
                pose_matrix(r["ego_pose"]),
            )
        missing = [n for n in CAMERA_NAMES if n not in by_name]
        if missing:
            raise DataError(
                f"{src}: sample scene_infos.{scene}.{token} has no {missing[0]} camera (img_path folders: "
                f"{', '.join(sorted(by_name))})"
            )
        return [by_name[n] for n in CAMERA_NAMES]

    def images(self, scene: str, token: str) -> np.ndarray:
        """(6, H, W, 3) uint8: the sample's camera images in CAMERA_NAMES order."""
        imgs = [read_image(r.image) for r in self.cameras(scene, token)]
        shapes = {i.shape for i in imgs}
        if len(shapes) != 1 or len(imgs[0].shape) != 3:
            raise DataError(
                f"{self.root}: sample {token}'s camera images differ in size or are not RGB ({sorted(shapes)})"
            )
        return np.stack(imgs)

    def camera_targets(self, scene: str, token: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(classes (6, H, W) uint8, depth (6, H, W) float32 metres) written beside synthetic
        images; None for real data, which has neither."""
        out_cls, out_depth = [], []
        for r in self.cameras(scene, token):
            cls_path, depth_path = r.maps
            if not cls_path.is_file() or not depth_path.is_file():
                return None
            out_cls.append(read_image(cls_path))
            out_depth.append(read_image(depth_path).astype(np.float32) / DEPTH_SCALE)
        return np.stack(out_cls), np.stack(out_depth)

    def timestamp(self, scene: str, token: str) -> int | None:
        """Microseconds, or None where the annotations give a timestamp that is not a number."""
        return sample_time(self.info(scene, token))

    def ego_pose(self, scene: str, token: str) -> tuple[float, float, float]:
        """Global (x, y, yaw) of the ego at a sample."""
        pose = self.info(scene, token)["ego_pose"]  # its shape was checked on opening
        x, y = pose["translation"][:2]
        return float(x), float(y), yaw_from_quaternion(pose["rotation"])

    # -- sidecars
    @cached_property
    def generator(self) -> dict | None:
        """occtrain's record of what generated this directory, if any."""
        return generator_record(self.root)

    def has_frame_annotations(self, scene: str) -> bool:
        return (self.root / FRAMES_DIR / f"{scene}.json").is_file()

    def frames(self, scene: str) -> list[FrameAnnotation]:
        """The scene's FrameAnnotation sidecar, ordered like its samples; its first problem is a DataError."""
        path = self.root / FRAMES_DIR / f"{scene}.json"
        if not path.is_file():
            raise DataError(
                f"{path}: no frame annotations for scene '{scene}' (trajectories, boxes, text are occtrain sidecars)"
            )
        frames = read_json(self.within(path), "frame annotations", list[FrameAnnotation], FRAMES_HINT)
        tokens = [f["token"] for f in frames]
        if tokens != self.scenes.get(scene):
            raise DataError(
                f"{path}: frame tokens do not match the samples of scene_infos.{scene} in {ANNOTATIONS_FILE}; "
                f"{FRAMES_HINT}"
            )
        return frames

    def questions(self, split: str) -> list[QAQuestion] | None:
        """A split's NuScenes-QA questions, or None when the sidecar is absent."""
        path = self.root / qa_file(split)
        if not path.is_file():
            return None
        return read_json(self.within(path), "NuScenes-QA file", QAFile, QA_HINT)["questions"]

    def questions_by_sample(self, split: str) -> dict[str, list[QAQuestion]]:
        """A split's NuScenes-QA questions grouped by sample token (empty without the sidecar)."""
        grouped: dict[str, list[QAQuestion]] = {}
        for q in self.questions(split) or []:
            grouped.setdefault(q["sample_token"], []).append(q)
        return grouped

    def available_tasks(self) -> dict[str, str]:
        """Which training tasks this dataset supports; a reason for each one it does not."""
        scenes = list(self.scenes)
        lacking = [s for s in scenes if not self.has_frame_annotations(s)]
        has_frames = bool(scenes) and not lacking
        has_qa = all((self.root / qa_file(s)).is_file() for s in SPLITS if self.splits.get(s))
        who = (
            f"{len(lacking)} of {len(scenes)} scenes lack (first: {lacking[0]})"
            if 0 < len(lacking) < len(scenes)
            else "this dataset lacks"
        )
        sidecar = f"needs the {FRAMES_DIR}/<scene>.json sidecar, which {who}"
        tasks = {"reconstruction": "", "forecasting": "", "planning": ""}
        for task in ("detection", "counting", "prediction", "chain_of_thought", "meta_action", "caption"):
            tasks[task] = "" if has_frames else sidecar
        tasks["qa"] = "" if has_qa else f"needs {QA_DIR}/NuScenes_<split>_questions.json, which this dataset lacks"
        # An imported release's sidecars leave the text no release holds empty, and its
        # record says so (``absent``): a task that reads that text is not trained on "".
        absent = (self.generator or {}).get("absent") or {}
        for task, key in (("chain_of_thought", "narration"), ("caption", "caption")):
            if has_frames and key in absent:
                tasks[task] = f"needs the frames' {key}, which {FRAMES_DIR}/ leaves empty here ({absent[key]})"
        return tasks

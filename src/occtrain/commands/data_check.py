"""Validate a dataset directory or a shard directory, listing every problem with its file.

Neither check raises: whatever goes wrong becomes a problem line (the command prints them
all and exits 1). Facts that are not problems, such as the tasks a real Occ3D download
cannot train for want of occtrain's sidecars, go to ``note``.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.camera_records import read_image
from occtrain.data.geometry import global_to_ego
from occtrain.data.labels import load_labels
from occtrain.data.layout import (
    ANNOTATIONS_FILE,
    FRAMES_DIR,
    IMGS_DIR,
    QUATERNION_TOLERANCE,
    SPLITS,
    DatasetIndex,
    dataset_root,
    ego_pose_problems,
    qa_file,
)
from occtrain.data.schema import FrameAnnotation, Occ3DAnnotations, QAFile
from occtrain.data.shards import INDEX_FILE, decode_sample, iter_raw, leftover_rebuilds, read_index
from occtrain.data.validate import problems as schema_problems
from occtrain.errors import OcctrainError
from occtrain.formats.io import parse_json
from occtrain.formats.occ3d import FRAME_DT

POSE_TOLERANCE = 0.05  # metres between a sidecar waypoint and the pose it should equal
# nuScenes keyframes are picked from 20 Hz lidar sweeps, so real gaps are 0.45 or 0.55 s
# as often as 0.5 s; a dropped keyframe (1 s) or another rate (0.1 s) is what this catches.
GAP_TOLERANCE = 0.2 * FRAME_DT
#: Problems listed per file before the rest are summed up in one line.
MAX_PER_FILE = 20


def _guarded(run: Callable[[list[str]], None], where: str | Path) -> list[str]:
    """Run a check that appends to a list; anything it raises ends the list as one more line."""
    found: list[str] = []
    try:
        run(found)
    except OcctrainError as err:
        found.append(str(err).splitlines()[0])
    except Exception as err:  # an input no reader foresaw: still a line, never a traceback
        found.append(f"{where}: check stopped on {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}")
    return found


def _file_problems(path: Path, schema: Any) -> tuple[Any, list[str]]:
    """A JSON file's content and every way it differs from ``schema`` (capped at MAX_PER_FILE)."""
    try:
        data = parse_json(path.read_text())
    except (ValueError, OSError) as err:
        return None, [f"{path}: not valid JSON ({err}); re-create the file"]
    found = schema_problems(data, schema, limit=MAX_PER_FILE + 1)
    lines = [f"{path}: {p}" for p in found[:MAX_PER_FILE]]
    if len(found) > MAX_PER_FILE:
        lines.append(f"{path}: more problems than the {MAX_PER_FILE} listed; fix these and check again")
    return data, lines


# ----------------------------------------------------------------------------- datasets


def check_dataset(root: str | Path, note: Callable[[str], None] = print) -> list[str]:
    """Every problem of an Occ3D-layout dataset, each naming its file; empty when it is sound.

    ``note`` receives informational lines (the tasks that missing sidecars disable).
    """
    return _guarded(lambda found: _check_dataset(dataset_root(root), found, note), root)


def _check_dataset(root: Path, problems: list[str], note: Callable[[str], None]) -> None:
    ann = root / ANNOTATIONS_FILE
    try:
        index = DatasetIndex.open(root, check_poses=False)
    except OcctrainError as err:
        # A schema problem: list them all, not just the first that stopped the reader.
        listed = _file_problems(ann, Occ3DAnnotations)[1] if ann.is_file() else []
        problems.extend(listed or [str(err)])
        return
    for task_line in _disabled_tasks(index):
        note(task_line)
    checks_images = (root / IMGS_DIR).is_dir()
    if not checks_images:
        note(f"note: {root}: no {IMGS_DIR}/ camera images; stages that read cameras (vision) need them")
    train, val = set(index.splits["train"]), set(index.splits["val"])
    for scene in sorted(train & val):
        problems.append(f"{ann}: scene '{scene}' is in both train_split and val_split")
    owner: dict[str, str] = {}
    no_truth = 0
    problems.extend(ego_pose_problems(index.scenes, index.scene_infos, ann))
    for scene, tokens in index.scenes.items():
        problems.extend(_timing_problems(index, scene, tokens))
        for token in tokens:
            if token in owner:
                problems.append(
                    f"{ann}: sample token {token} is in both scene_infos.{owner[token]} and scene_infos.{scene}"
                )
            owner[token] = scene
            if checks_images:
                problems.extend(_guarded(partial(_check_cameras, index, scene, token), ann))
            path = index.labels_path(scene, token)
            if "gt_path" not in index.info(scene, token) and not path.exists():
                no_truth += 1  # a test split: Occ3D gives it no gt_path and no labels
                continue
            problems.extend(_guarded(partial(_check_labels, path), path))
    if no_truth:
        note(
            f"note: {no_truth} samples have no gt_path and no labels (a test split?); they cannot be trained or scored"
        )
    problems.extend(_sidecar_problems(index))
    for split in SPLITS:
        problems.extend(_guarded(partial(_check_questions, index, split), root / qa_file(split)))
    # Shards usually live inside their dataset (data.shards' default, ROOT/shards).
    problems.extend(leftover.problem() for leftover in leftover_rebuilds(root) if not leftover.running)


def _check_cameras(index: DatasetIndex, scene: str, token: str, problems: list[str]) -> None:
    """A sample's six cameras: records for each, readable RGB images of one size, and a
    calibration that fits them (positive focal lengths, principal point in the image,
    unit rotation)."""
    where = f"{index.root / ANNOTATIONS_FILE}: scene_infos.{scene}.{token}.camera_sensor"
    try:
        records = index.cameras(scene, token)
    except OcctrainError as err:
        problems.append(str(err))
        return
    sizes = set()
    for r in records:
        try:
            image = read_image(r.image)
        except OcctrainError as err:
            problems.append(str(err))
            continue
        if image.ndim != 3 or image.shape[2] != 3:
            problems.append(f"{r.image}: expected an RGB image, found shape {image.shape}")
            continue
        height, width = image.shape[:2]
        sizes.add((height, width))
        k = r.intrinsic
        if not (k[0, 0] > 0 and k[1, 1] > 0 and 0 <= k[0, 2] <= width and 0 <= k[1, 2] <= height):
            problems.append(
                f"{where} ({r.name}): intrinsic {k.round(2).tolist()} does not fit its {width}x{height} image"
            )
        if abs(np.linalg.det(r.cam_to_ego[:3, :3]) - 1.0) > QUATERNION_TOLERANCE:
            problems.append(f"{where} ({r.name}): extrinsic rotation is not a unit quaternion (w, x, y, z)")
    if len(sizes) > 1:
        problems.append(f"{where}: the six images differ in size ({', '.join(f'{w}x{h}' for h, w in sorted(sizes))})")


def _disabled_tasks(index: DatasetIndex) -> list[str]:
    """One note per reason, naming the tasks it disables."""
    by_reason: dict[str, list[str]] = {}
    for task, reason in index.available_tasks().items():
        if reason:
            by_reason.setdefault(reason, []).append(task)
    return [f"note: {index.root}: no {', '.join(tasks)} training: {reason}" for reason, tasks in by_reason.items()]


def _timing_problems(index: DatasetIndex, scene: str, tokens: list[str]) -> list[str]:
    stamps = [index.timestamp(scene, t) for t in tokens]
    if len(stamps) < 2 or any(s is None for s in stamps):
        return []  # Occ3D allows a token for a timestamp; the prev/next links gave the order
    ann = index.root / ANNOTATIONS_FILE
    gaps = np.diff(np.asarray(stamps, dtype=np.int64)).astype(np.float64) / 1e6
    if (gaps <= 0).any():
        return [f"{ann}: scene '{scene}' timestamps do not increase along its prev/next links"]
    if np.abs(gaps - FRAME_DT).max() > GAP_TOLERANCE:
        return [
            f"{ann}: scene '{scene}' frames are not {FRAME_DT} s apart (found {gaps.min():.3f}..{gaps.max():.3f} s)"
        ]
    return []


def _check_labels(path: Path, problems: list[str]) -> None:
    labels = load_labels(path)
    if labels["mask_camera"].all():
        problems.append(f"{path}: mask_camera is all ones; Occ3D masks mark what the cameras see")


def _sidecar_problems(index: DatasetIndex) -> list[str]:
    scenes = list(index.scenes)
    present = [s for s in scenes if index.has_frame_annotations(s)]
    problems: list[str] = []
    if present and len(present) < len(scenes):
        # Clips of those scenes would lack the fields the sidecar tasks train on.
        for scene in scenes:
            if scene not in present:
                problems.append(
                    f"{index.root / FRAMES_DIR / f'{scene}.json'}: missing while {len(present)} other scenes have "
                    "their "
                    "frame sidecar; write it or delete them all"
                )
    for scene in present:
        path = index.root / FRAMES_DIR / f"{scene}.json"
        listed = _file_problems(path, list[FrameAnnotation])[1]
        problems.extend(listed or _guarded(partial(_check_frames, index, scene, index.frames(scene)), path))
    return problems


def _check_frames(index: DatasetIndex, scene: str, frames: list[FrameAnnotation], problems: list[str]) -> None:
    """What the schema cannot say: a sidecar agrees with its scene and with the ego poses."""
    path = index.root / FRAMES_DIR / f"{scene}.json"
    tokens = index.scenes[scene]
    poses = [index.ego_pose(scene, t) for t in tokens]
    for i, frame in enumerate(frames):
        where = f"{path}: [{i}]"
        if frame["scene"] != scene or frame["index"] != i:
            problems.append(
                f"{where} says scene '{frame['scene']}' index {frame['index']}, but it is frame {i} of '{scene}'"
            )
        fut, mask = np.asarray(frame["ego_future"]), frame["ego_future_mask"]
        for k, valid in enumerate(mask):
            if valid and i + k + 1 < len(poses):
                want = global_to_ego(np.asarray(poses[i + k + 1][:2]), np.asarray(poses[i][:2]), poses[i][2])
                if np.abs(fut[k] - want).max() > POSE_TOLERANCE:
                    problems.append(
                        f"{where}.ego_future[{k}] {fut[k].round(2).tolist()} disagrees with the ego poses "
                        f"({want.round(2).tolist()})"
                    )
                    break
        boxes = len(frame["boxes"])
        for key in ("agent_futures", "agent_future_mask"):
            if len(frame[key]) != boxes:
                problems.append(f"{where}.{key} has {len(frame[key])} entries for {boxes} boxes")


def _check_questions(index: DatasetIndex, split: str, problems: list[str]) -> None:
    path = index.root / qa_file(split)
    if not path.is_file():
        return  # a missing QA file is a note (available_tasks), not a problem
    data, listed = _file_problems(path, QAFile)
    if listed:
        problems.extend(listed)
        return
    allowed = {t for s in index.splits[split] for t in index.scenes[s]}
    for i, q in enumerate(data["questions"]):
        if q["sample_token"] not in allowed:
            problems.append(
                f"{path}: questions[{i}].sample_token '{q['sample_token']}' is not a sample of the {split} split"
            )


# ----------------------------------------------------------------------------- shards


def check_shards(shards: str | Path) -> list[str]:
    """Every problem of a shard directory: missing or corrupt shards, bad entries, wrong counts."""
    return _guarded(lambda found: _check_shards(Path(shards), found), shards)


def _check_shards(shards: Path, problems: list[str]) -> None:
    problems.extend(
        leftover.problem()
        for leftover in leftover_rebuilds(shards.resolve().parent, shards.resolve().name)
        if not leftover.running
    )
    idx = read_index(shards)
    for kind, splits in idx["kinds"].items():
        for entries in splits.values():
            for entry in entries:
                url = shards / kind / entry["file"]
                if not url.is_file():
                    problems.append(f"{url}: listed in {INDEX_FILE} but missing")
                    continue
                counted: list[int] = []
                failed = _guarded(partial(_read_shard, url, counted), url)
                problems.extend(failed)
                if not failed and counted[0] != entry["samples"]:
                    problems.append(f"{url}: holds {counted[0]} samples, {INDEX_FILE} says {entry['samples']}")


def _read_shard(url: Path, counted: list[int], problems: list[str]) -> None:
    """Decode every sample of one shard (a problem raises); how many there were goes to ``counted``."""
    n = 0
    for raw in iter_raw(str(url)):
        decode_sample(raw)
        n += 1
    counted.append(n)


def looks_like_shards(path: str | Path) -> bool:
    return (Path(path) / INDEX_FILE).is_file()


__all__ = ["check_dataset", "check_shards", "looks_like_shards"]


def check(path: str | Path) -> int:
    """``occtrain data check PATH``: every problem of a dataset or shard directory printed,
    one a line, and the exit code: 0 when there is none, 1 otherwise."""
    import sys

    is_shards = looks_like_shards(path)
    problems = check_shards(path) if is_shards else check_dataset(path)
    for p in problems:
        print(p)
    what = "shards" if is_shards else "dataset"
    if problems:
        print(f"{len(problems)} problem(s) in {what} {path}", file=sys.stderr)
        return 1
    print(f"{what} {path}: ok")
    return 0

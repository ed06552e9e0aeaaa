"""Validate a dataset directory or a shard directory, listing every problem with its file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occtrain.data.geometry import global_to_ego
from occtrain.data.layout import ANNOTATIONS_FILE, FRAMES_DIR, DatasetIndex, load_labels, qa_file
from occtrain.data.schema import TEMPLATE_TYPES, FrameAnnotation
from occtrain.data.shards import INDEX_FILE, decode_sample, iter_raw, read_index
from occtrain.errors import DataError
from occtrain.occ3d import FRAME_DT

POSE_TOLERANCE = 0.05  # metres between a sidecar waypoint and the pose it should equal


def _check_frames(index: DatasetIndex, scene: str, frames: list[FrameAnnotation], problems: list[str]) -> None:
    path = index.root / FRAMES_DIR / f"{scene}.json"
    tokens = index.scenes[scene]
    poses = [index.ego_pose(scene, t) for t in tokens]
    for i, frame in enumerate(frames):
        where = f"{path} frame {i}"
        fut, mask = np.asarray(frame.get("ego_future", [])), frame.get("ego_future_mask", [])
        for k, valid in enumerate(mask):
            if valid and i + k + 1 < len(poses):
                want = global_to_ego(np.asarray(poses[i + k + 1][:2]), np.asarray(poses[i][:2]), poses[i][2])
                if np.abs(fut[k] - want).max() > POSE_TOLERANCE:
                    problems.append(f"{where}: ego_future[{k}] {fut[k].round(2).tolist()} disagrees with the ego poses ({want.round(2).tolist()})")
                    break
        if len(frame.get("agent_futures", [])) != len(frame.get("boxes", [])):
            problems.append(f"{where}: agent_futures has {len(frame.get('agent_futures', []))} entries for {len(frame.get('boxes', []))} boxes")


def check_dataset(root: str | Path) -> list[str]:
    """Every problem of an Occ3D-layout dataset, each naming its file; empty when it is sound."""
    try:
        index = DatasetIndex.open(root)
    except DataError as err:
        return [str(err)]
    problems: list[str] = []
    ann = index.root / ANNOTATIONS_FILE
    train, val = set(index.splits["train"]), set(index.splits["val"])
    for scene in sorted(train & val):
        problems.append(f"{ann}: scene '{scene}' is in both train_split and val_split")
    for scene, tokens in index.scenes.items():
        stamps = [index.scene_infos[scene][t].get("timestamp", 0) for t in tokens]
        gaps = np.diff(stamps) / 1e6
        if len(gaps) and (gaps <= 0).any():
            problems.append(f"{ann}: scene '{scene}' timestamps do not increase")
        elif len(gaps) and np.abs(gaps - FRAME_DT).max() > 0.1 * FRAME_DT:
            problems.append(f"{ann}: scene '{scene}' frames are not {FRAME_DT} s apart (found {gaps.min():.3f}..{gaps.max():.3f} s)")
        for token in tokens:
            path = index.labels_path(scene, token)
            try:
                labels = load_labels(path)
            except DataError as err:
                problems.append(str(err))
                continue
            if labels["mask_camera"].all():
                problems.append(f"{path}: mask_camera is all ones; Occ3D masks mark what the cameras see")
        if index.has_frame_annotations(scene):
            try:
                _check_frames(index, scene, index.frames(scene), problems)
            except DataError as err:
                problems.append(str(err))
    for split in ("train", "val"):
        try:
            qs = index.questions(split)
        except DataError as err:
            problems.append(str(err))
            continue
        if qs is None:
            continue
        allowed = {t for s in index.splits[split] for t in index.scenes[s]}
        qpath = index.root / qa_file(split)
        for i, q in enumerate(qs):
            if q["sample_token"] not in allowed:
                problems.append(f"{qpath}: question {i} names sample '{q['sample_token']}' outside the {split} split")
            if q["template_type"] not in TEMPLATE_TYPES:
                problems.append(f"{qpath}: question {i} has template_type '{q['template_type']}' (expected one of {', '.join(TEMPLATE_TYPES)})")
            if q["num_hop"] not in (0, 1):
                problems.append(f"{qpath}: question {i} has num_hop {q['num_hop']} (expected 0 or 1)")
    return problems


def check_shards(shards: str | Path) -> list[str]:
    """Every problem of a shard directory: missing or corrupt shards, bad entries, wrong counts."""
    shards = Path(shards)
    try:
        idx = read_index(shards)
    except DataError as err:
        return [str(err)]
    problems: list[str] = []
    for kind, splits in idx.get("kinds", {}).items():
        for split, entries in splits.items():
            for entry in entries:
                url = shards / kind / entry["file"]
                if not url.is_file():
                    problems.append(f"{url}: listed in {INDEX_FILE} but missing")
                    continue
                count = 0
                try:
                    for raw in iter_raw(str(url)):
                        decode_sample(raw)
                        count += 1
                except DataError as err:
                    problems.append(str(err))
                    continue
                if count != entry["samples"]:
                    problems.append(f"{url}: holds {count} samples, {INDEX_FILE} says {entry['samples']}")
    return problems


def looks_like_shards(path: str | Path) -> bool:
    return (Path(path) / INDEX_FILE).is_file()


__all__ = ["check_dataset", "check_shards", "looks_like_shards"]

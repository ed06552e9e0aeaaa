"""An occtrain dataset written as the public releases it stands in for, so each importer is
tested by a round trip (``occtrain data export nuscenes DIR --out OUT``)::

    OUT/nuscenes/<version>/*.json          the nuScenes v1.0 tables (all thirteen)
    OUT/nuscenes/can_bus/<scene>_pose.json the CAN bus expansion's pose messages, one per sample
    OUT/occ3d/annotations.json             the dataset's own (it is Occ3D's layout already)
    OUT/occ3d/gts/<scene>, OUT/occ3d/imgs  the dataset's, hard-linked (``files.place``)
    OUT/omnidrive/{desc,vqa,keywords}/<split>/<token>.json   OmniDrive-nuScenes' layout
    OUT/drivelm/v1_1_<split>_nus.json      DriveLM's layout
    OUT/nuscenes_qa/NuScenes_<split>_questions.json          NuScenes-QA's

What each frame's sidecar becomes: the ego pose an ego_pose record of every sample_data of
the sample (a LIDAR_TOP key frame, and each camera's with its image's path under
``samples/``); speed, acceleration and yaw rate a CAN bus message at the sample's time (``vel``
[speed, 0, 0], ``accel`` [acceleration, 0, 0], ``rotation_rate`` [0, 0, yaw rate]); each
track an instance (its category by ``categories.CLASS_TO_CATEGORY``) and each box a
sample_annotation (global translation and rotation, nuScenes' width, length, height, the
attribute, the visibility where the box has one, else an empty token: the world has none).
A track's positions that its boxes' agent futures give at samples where it has no box (it
is outside the grid there) are annotations too, with the size and heading of its nearest
box, so an instance's next links reach the samples its futures name.

The captions are OmniDrive's ``desc`` (the description), the frames' NuScenes-QA questions
its ``vqa`` pairs and DriveLM's perception QA, and the meta action OmniDrive's ``keywords``
and DriveLM's behavior answer. Not written: the lidar sweeps and camera images themselves
(the Occ3D layout carries the images), the maps (map.json is empty), the narration (no
release holds it), the number of lidar and radar points of a box (unknown to the world).
"""

from __future__ import annotations

import hashlib
import shutil
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.geometry import ego_to_global
from occtrain.data.layout import ANNOTATIONS_FILE, GTS_DIR, IMGS_DIR, SPLITS, DatasetIndex
from occtrain.data.poses import quaternion_from_yaw
from occtrain.data.releases.categories import ATTRIBUTES, CLASS_TO_CATEGORY, VISIBILITY_LEVELS, attribute_name
from occtrain.data.releases.files import place_tree
from occtrain.data.releases.nuscenes_tables import CAN_BUS_DIR, LIDAR, TABLES
from occtrain.data.releases.text_import import DRIVELM_BEHAVIOR_QUESTION, drivelm_file, omnidrive_file
from occtrain.data.schema import FrameAnnotation
from occtrain.data.text_formats import format_meta_action
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json
from occtrain.formats.occ3d import CLASS_NAMES, FUTURE_STEPS
from occtrain.progress import console, progress_bar

#: The subfolders of OUT, one per release.
NUSCENES_DIR, OCC3D_DIR, OMNIDRIVE_DIR, DRIVELM_DIR, NUSCENES_QA_DIR = (
    "nuscenes",
    "occ3d",
    "omnidrive",
    "drivelm",
    "nuscenes_qa",
)


def token(*parts: Any) -> str:
    """A deterministic 32-hex token, as nuScenes' look."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def _yaw_quaternion(yaw: float) -> list[float]:
    return [float(v) for v in quaternion_from_yaw(float(yaw))]


class _Tables:
    """The thirteen tables as they fill up, each a list of records."""

    def __init__(self) -> None:
        self.rows: dict[str, list[dict]] = {t: [] for t in TABLES}

    def add(self, table: str, record: dict) -> str:
        self.rows[table].append(record)
        return str(record["token"])


def _static_tables(t: _Tables, channels: list[str]) -> dict[str, str]:
    """sensor, category, attribute and visibility; the sensor token by channel."""
    sensors = {}
    for channel in channels:
        modality = "lidar" if channel == LIDAR else "camera"
        sensors[channel] = t.add(
            "sensor", {"token": token("sensor", channel), "channel": channel, "modality": modality}
        )
    for cls in CLASS_NAMES[:11]:
        name = CLASS_TO_CATEGORY[cls]
        t.add("category", {"token": token("category", name), "name": name, "description": f"Occ3D class {cls}"})
    for name in ATTRIBUTES:
        t.add("attribute", {"token": token("attribute", name), "name": name, "description": ""})
    for tok, level in VISIBILITY_LEVELS.items():
        t.add("visibility", {"token": tok, "level": level, "description": f"visibility of whole object is {level}"})
    return sensors


def _ego_pose(frame: FrameAnnotation) -> dict:
    return {
        "translation": [float(v) for v in frame["ego_pose"]["translation"]],
        "rotation": _yaw_quaternion(frame["ego_pose"]["yaw"]),
    }


def _calibrations(t: _Tables, scene: str, cams: dict[str, dict], sensors: dict[str, str]) -> dict[str, str]:
    """One calibrated_sensor per channel of the scene (the lidar at the ego's origin, each
    camera as its camera_sensor record holds it); their tokens by channel."""
    calib = {
        LIDAR: t.add(
            "calibrated_sensor",
            {
                "token": token("calibrated_sensor", scene, LIDAR),
                "sensor_token": sensors[LIDAR],
                "translation": [0.0, 0.0, 0.0],
                "rotation": [1.0, 0.0, 0.0, 0.0],
                "camera_intrinsic": [],
            },
        )
    }
    for channel, rec in sorted(cams.items()):
        calib[channel] = t.add(
            "calibrated_sensor",
            {
                "token": token("calibrated_sensor", scene, channel),
                "sensor_token": sensors[channel],
                "translation": rec["extrinsic"]["translation"],
                "rotation": rec["extrinsic"]["rotation"],
                "camera_intrinsic": rec.get("intrinsics", rec.get("intrinsic")),
            },
        )
    return calib


def _sample_data(t: _Tables, frame: FrameAnnotation, channel: str, calib: str, image: str, near: tuple) -> None:
    """One key-frame sample_data of a sample and its ego pose; ``near`` the tokens of the
    samples before and after it ("" at the scene's ends)."""
    sample = frame["token"]
    sd = token("sample_data", sample, channel)
    pose = t.add("ego_pose", {"token": token("ego_pose", sd), "timestamp": frame["timestamp"], **_ego_pose(frame)})
    t.add(
        "sample_data",
        {
            "token": sd,
            "sample_token": sample,
            "ego_pose_token": pose,
            "calibrated_sensor_token": calib,
            "timestamp": frame["timestamp"],
            "fileformat": "pcd" if channel == LIDAR else Path(image).suffix.lstrip("."),
            "is_key_frame": True,
            "height": 0,
            "width": 0,
            "filename": f"samples/{LIDAR}/{sample}.pcd.bin"
            if channel == LIDAR
            else f"samples/{channel}/{Path(image).name}",
            "prev": token("sample_data", near[0], channel) if near[0] else "",
            "next": token("sample_data", near[1], channel) if near[1] else "",
        },
    )


def _can_bus(frames: list[FrameAnnotation]) -> list[dict]:
    """A CAN bus pose message at each sample: the ego's speed, acceleration and yaw rate."""
    return [
        {
            "utime": f["timestamp"],
            "pos": [float(v) for v in f["ego_pose"]["translation"]],
            "orientation": _yaw_quaternion(f["ego_pose"]["yaw"]),
            "vel": [f["ego_speed"], 0.0, 0.0],
            "accel": [f["ego_accel"], 0.0, 0.0],
            "rotation_rate": [0.0, 0.0, f["ego_yaw_rate"]],
        }
        for f in frames
    ]


def _scene_tables(
    t: _Tables, index: DatasetIndex, scene: str, frames: list[FrameAnnotation], sensors: dict[str, str]
) -> list[dict]:
    """The scene's log, scene, samples, sample_data, ego poses, calibrations, instances and
    annotations; its CAN bus messages."""
    log = {"token": token("log", scene), "logfile": scene, "vehicle": "occtrain", "date_captured": ""}
    t.add("log", log | {"location": "occtrain"})
    scene_token = token("scene", scene)
    calib = _calibrations(t, scene, index.info(scene, frames[0]["token"]).get("camera_sensor") or {}, sensors)
    tokens = [f["token"] for f in frames]
    for k, frame in enumerate(frames):
        near = (tokens[k - 1] if k > 0 else "", tokens[k + 1] if k + 1 < len(tokens) else "")
        t.add(
            "sample",
            {
                "token": tokens[k],
                "timestamp": frame["timestamp"],
                "prev": near[0],
                "next": near[1],
                "scene_token": scene_token,
            },
        )
        records = index.info(scene, tokens[k]).get("camera_sensor") or {}
        for channel, cs in calib.items():
            _sample_data(t, frame, channel, cs, records.get(channel, {}).get("img_path", ""), near)
    _instances(t, scene, frames)
    t.add(
        "scene",
        {
            "token": scene_token,
            "log_token": log["token"],
            "nbr_samples": len(frames),
            "first_sample_token": tokens[0],
            "last_sample_token": tokens[-1],
            "name": scene,
            "description": "",
        },
    )
    return _can_bus(frames)


def _instances(t: _Tables, scene: str, frames: list[FrameAnnotation]) -> None:
    """One instance per track and one annotation per (track, sample) a box or a future places it at."""
    boxed: dict[int, dict[int, dict]] = defaultdict(dict)  # track -> frame -> global box
    placed: dict[int, dict[int, np.ndarray]] = defaultdict(dict)  # track -> frame -> global xy from a future
    for k, frame in enumerate(frames):
        pxy = np.asarray(frame["ego_pose"]["translation"][:2], dtype=np.float64)
        pyaw, pz = float(frame["ego_pose"]["yaw"]), float(frame["ego_pose"]["translation"][2])
        for b, box in enumerate(frame["boxes"]):
            xy = ego_to_global(np.asarray(box["center"][:2], dtype=np.float64), pxy, pyaw)
            boxed[box["track_id"]][k] = {"box": box, "xy": xy, "z": pz + box["center"][2], "yaw": pyaw + box["yaw"]}
            for j in range(FUTURE_STEPS):
                if frame["agent_future_mask"][b][j] and k + j + 1 < len(frames):
                    point = np.asarray(frame["agent_futures"][b][j], dtype=np.float64)
                    placed[box["track_id"]].setdefault(k + j + 1, ego_to_global(point, pxy, pyaw))
    for track in sorted(boxed):
        have = boxed[track]
        first = have[min(have)]["box"]
        category = CLASS_TO_CATEGORY[first["category"]]
        inst = token("instance", scene, track)
        at = sorted(set(have) | set(placed[track]))
        anns = [token("sample_annotation", scene, track, k) for k in at]
        for n, k in enumerate(at):
            near = have[k] if k in have else have[min(have, key=lambda b: (abs(b - k), b))]
            box = near["box"]
            xy = near["xy"] if k in have else placed[track][k]
            attr = attribute_name(box["attribute"], category)
            length, width, height = box["size"]
            t.add(
                "sample_annotation",
                {
                    "token": anns[n],
                    "sample_token": frames[k]["token"],
                    "instance_token": inst,
                    "visibility_token": next(
                        (tok for tok, lv in VISIBILITY_LEVELS.items() if lv == box.get("visibility")), ""
                    ),
                    "attribute_tokens": [token("attribute", attr)] if attr else [],
                    "translation": [float(xy[0]), float(xy[1]), float(near["z"])],
                    "size": [width, length, height],
                    "rotation": _yaw_quaternion(near["yaw"]),
                    "prev": anns[n - 1] if n > 0 else "",
                    "next": anns[n + 1] if n + 1 < len(anns) else "",
                },
            )
        t.add(
            "instance",
            {
                "token": inst,
                "category_token": token("category", category),
                "nbr_annotations": len(anns),
                "first_annotation_token": anns[0],
                "last_annotation_token": anns[-1],
            },
        )


def export_nuscenes(root: str | Path, out: str | Path, version: str = "v1.0-trainval", verbose: bool = True) -> dict:
    """Write the dataset at ``root`` as the releases (see the module docstring); counts of what was written."""
    start = time.perf_counter()
    index = DatasetIndex.open(root)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DataError(f"{out}: exists and is not empty; choose an empty or new --out directory")
    scenes = [s for split in SPLITS for s in index.splits.get(split, [])]
    lacking = [s for s in scenes if not index.has_frame_annotations(s)]
    if lacking:
        raise DataError(
            f"{index.root}: scene '{lacking[0]}' has no occtrain/frames sidecar, which the export writes the tables "
            "from; export a dataset with sidecars (occtrain data synth, or an import)"
        )
    frames = {s: index.frames(s) for s in scenes}  # every sidecar read (and checked) before anything is written
    split_of = {s: split for split in SPLITS for s in index.splits.get(split, [])}
    first = index.info(scenes[0], index.scenes[scenes[0]][0]).get("camera_sensor") or {}
    t = _Tables()
    sensors = _static_tables(t, [LIDAR, *sorted(first)])
    staging = out.with_name(f".{out.name}.partial")
    if staging.exists():
        shutil.rmtree(staging)
    nus = staging / NUSCENES_DIR
    with progress_bar(sum(len(f) for f in frames.values()), f"exporting {len(scenes)} scenes") as advance:
        for scene in scenes:
            messages = _scene_tables(t, index, scene, frames[scene], sensors)
            atomic_write_json(nus / CAN_BUS_DIR / f"{scene}_pose.json", messages, indent=None)
            advance(len(frames[scene]))
    for table, rows in t.rows.items():
        atomic_write_json(nus / version / f"{table}.json", rows, indent=None)
    occ3d = staging / OCC3D_DIR
    occ3d.mkdir(parents=True)
    shutil.copy2(index.root / ANNOTATIONS_FILE, occ3d / ANNOTATIONS_FILE)
    for scene in scenes:
        place_tree(index.root / GTS_DIR / scene, occ3d / GTS_DIR / scene)
    if (index.root / IMGS_DIR).is_dir():
        place_tree(index.root / IMGS_DIR, occ3d / IMGS_DIR)
    counts = _text_releases(index, staging, scenes, frames, split_of)
    if out.exists():
        _move_into(staging, out)
    else:
        staging.rename(out)
    summary = {"scenes": len(scenes), "frames": sum(len(f) for f in frames.values()), "version": version, **counts}
    summary |= {table: len(rows) for table, rows in t.rows.items()}
    if verbose:
        console.print(
            f"exported {summary['scenes']} scenes, {summary['frames']} frames ({summary['sample_annotation']} "
            f"annotations of {summary['instance']} instances, {counts['questions']} questions, {counts['captions']} "
            f"captions) in {time.perf_counter() - start:.1f}s -> {out}",
            markup=False,
        )
    return summary


def _move_into(staging: Path, out: Path) -> None:
    """``out`` exists empty: move the staged folders into it, then drop the staging folder."""
    for child in staging.iterdir():
        child.rename(out / child.name)
    staging.rmdir()


def _text_releases(
    index: DatasetIndex, out: Path, scenes: list[str], frames: dict[str, list[FrameAnnotation]], split_of: dict
) -> dict[str, int]:
    """OmniDrive, DriveLM and NuScenes-QA files from the frames' captions, meta actions and questions."""
    captions = questions = 0
    drivelm: dict[str, dict[str, Any]] = {s: {} for s in SPLITS}
    for split in SPLITS:
        qs = index.questions(split) or []
        by_sample: dict[str, list] = defaultdict(list)
        for q in qs:
            by_sample[q["sample_token"]].append(q)
        if qs:
            atomic_write_json(
                out / NUSCENES_QA_DIR / f"NuScenes_{split}_questions.json",
                {"info": {"exported_by": "occtrain data export nuscenes", "split": split}, "questions": qs},
            )
            questions += len(qs)
        for scene in scenes:
            if split_of[scene] != split:
                continue
            key_frames = {}
            for frame in frames[scene]:
                tok = frame["token"]
                pairs = [{"question": q["question"], "answer": q["answer"]} for q in by_sample.get(tok, [])]
                if frame.get("caption"):
                    atomic_write_json(
                        omnidrive_file(out / OMNIDRIVE_DIR, "desc", split, tok), {"description": frame["caption"]}
                    )
                    captions += 1
                if pairs:
                    atomic_write_json(omnidrive_file(out / OMNIDRIVE_DIR, "vqa", split, tok), pairs)
                action = format_meta_action(frame["meta_action"])
                atomic_write_json(omnidrive_file(out / OMNIDRIVE_DIR, "keywords", split, tok), action)
                key_frames[tok] = {
                    "key_object_infos": {},
                    "QA": {
                        "perception": [{"Q": p["question"], "A": p["answer"]} for p in pairs],
                        "prediction": [],
                        "planning": [],
                        "behavior": [{"Q": DRIVELM_BEHAVIOR_QUESTION, "A": action}],
                    },
                    "image_paths": {},
                }
            drivelm[split][token("scene", scene)] = {"scene_description": "", "key_frames": key_frames}
    for split, content in drivelm.items():
        if content:
            atomic_write_json(out / DRIVELM_DIR / drivelm_file(split), content, indent=None)
    return {"captions": captions, "questions": questions}

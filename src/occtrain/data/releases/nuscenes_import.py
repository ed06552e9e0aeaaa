"""An Occ3D-layout dataset with occtrain's frame sidecars, built from nuScenes and Occ3D-nuScenes.

``occtrain data import nuscenes --nuscenes ROOT --version V --occ3d OCC3D --out DIR`` writes::

    DIR/annotations.json             Occ3D's records of the version's scenes, verbatim, and its splits
    DIR/gts/...                      Occ3D's labels of those samples, where their gt_path puts them
    DIR/imgs/...                     Occ3D's camera images of those samples, where it has them (with the
                                     synthetic renderer's class and depth maps, for an exported world); else
                                     DIR/samples/CAM_*/..., nuScenes' key-frame images, and camera
                                     records built from its tables
    DIR/occtrain/dataset.json        what was imported from where, and which sidecar keys are absent
    DIR/occtrain/frames/<scene>.json FrameAnnotation per sample, from the nuScenes tables

Labels and images are hard links to the release's files (``files.place``: no second copy on
the disk, and inside the dataset's root, where a reader follows no link out of it), copies
where the filesystem refuses a hard link or ``copy=True`` asks.

Everything is read and checked first (every table, every reference the import follows, that
Occ3D's sample tokens are nuScenes' scene by scene, that every scene is in a split and has
its labels), so a broken release is one line and nothing is written. Then scene by scene,
each sidecar written atomically after its labels and images, so an interrupted import resumes at the first
scene without one; annotations.json is written last. The frames of a scene are a function of
the tables alone: the same release gives the same files.

What a frame holds, from the tables:

- ego pose, past and future waypoints: the key-frame LIDAR_TOP ego poses (Occ3D's own);
- speed and yaw rate: the CAN bus expansion's pose messages (``ROOT/can_bus/<scene>_pose.json``,
  ``vel`` and ``rotation_rate`` in the ego frame, the message nearest each sample) where the
  scene has them within 0.1 s of every sample, else the central difference of the densest
  ego poses around the sample (the LIDAR_TOP sweeps' at 20 Hz); the acceleration as the
  sidecar defines it (``kinematics.past_acceleration``: the speed now against the last move's);
- the driving command (``geometry.driving_command``) and the meta action
  (``meta_actions.sidecar_label``): the synthetic world's rules over these poses and speeds;
- boxes: every sample_annotation whose centre lies in the grid's x-y range, in the ego frame
  (nuScenes' width, length, height reordered to length, width, height), the category as
  Occ3D's class (``categories``), the instance's position in instance.json as track id, the
  visibility level, and the velocity as nuScenes' devkit derives it (the instance's previous
  and next annotations' positions over their time; [0, 0] for an instance annotated once),
  in the ego frame's axes;
- agent futures: the instance's annotations at the next six samples (mask 0 where it has none).

Absent, and said so in dataset.json's ``absent``: the caption and the narration (no release
holds them: ``occtrain data import omnidrive`` brings captions), and what the map would give
(route ahead, lead vehicle, stop lines), which is not built.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.data.camera_records import CLASS_SUFFIX, DEPTH_SUFFIX
from occtrain.data.geometry import driving_command, global_to_ego, rotate_to_ego
from occtrain.data.layout import ANNOTATIONS_FILE, DATASET_FILE, FRAMES_DIR, DatasetIndex
from occtrain.data.meta_actions import sidecar_label
from occtrain.data.poses import yaw_from_quaternion
from occtrain.data.releases.categories import box_class, status
from occtrain.data.releases.files import place_files
from occtrain.data.releases.nuscenes_tables import LIDAR, NuScenesTables, read_can_bus
from occtrain.data.schema import Box, Flag, FrameAnnotation
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json
from occtrain.formats.occ3d import FUTURE_STEPS, PAST_STEPS, RANGE_MAX
from occtrain.kinematics import past_acceleration
from occtrain.progress import console, progress_bar

GENERATOR = "occtrain.import.nuscenes"
FORMAT_VERSION = 1
#: Sidecar keys an import leaves empty, and what would fill them.
ABSENT = {
    "caption": "no nuScenes table holds one; `occtrain data import omnidrive` brings OmniDrive's descriptions",
    "narration": "no release holds occtrain's chain-of-thought narration",
    "road": "route ahead, lead vehicle and stop lines would come from the map expansion, which is not read",
}
#: The CAN bus message nearest a sample must lie this close to it (seconds).
CAN_BUS_TOLERANCE_S = 0.1
#: As nuScenes' devkit: no velocity from annotations further apart than this (seconds).
VELOCITY_MAX_DT_S = 1.5
CAMERA_PREFIX = "CAM_"


def _r(x: Any, nd: int = 4) -> Any:
    """Rounded plain-Python (nested) list, as the synthetic world writes its sidecars."""
    return np.round(np.asarray(x, dtype=np.float64), nd).tolist()


def _wrap(a: float) -> float:
    return float(np.angle(np.exp(1j * a)))


# ----------------------------------------------------------------------------- the plan


@dataclass(frozen=True)
class SceneJob:
    name: str
    split: str
    token: str  # nuScenes scene token


@dataclass
class Release:
    """The release read and checked: the tables, Occ3D's annotations and what to write."""

    tables: NuScenesTables
    occ3d: DatasetIndex
    jobs: list[SceneJob]
    cameras_from_tables: bool

    @property
    def fingerprint(self) -> dict:
        return {
            "generator": GENERATOR,
            "format_version": FORMAT_VERSION,
            "nuscenes_version": self.tables.version,
            "nuscenes": str(self.tables.root.resolve()),
            "occ3d": str(self.occ3d.root.resolve()),
        }


def read_release(nuscenes: str | Path, version: str, occ3d: str | Path) -> Release:
    """Read and check everything the import needs (see the module docstring); write nothing."""
    tables = NuScenesTables.open(nuscenes, version)
    index = DatasetIndex.open(occ3d)
    ann = index.root / ANNOTATIONS_FILE
    raw_splits = _split_keys(ann)
    split_of = {name: split for split, names in raw_splits.items() for name in names}
    jobs = []
    for scene in sorted(tables.tables["scene"].values(), key=lambda s: s["name"]):
        name = scene["name"]
        if name not in index.scenes:
            raise DataError(
                f"{ann}: scene_infos has no scene '{name}' of nuScenes {version}; point --occ3d at the Occ3D-nuScenes "
                "release of that version"
            )
        if name not in split_of:
            raise DataError(
                f"{ann}: scene '{name}' is in neither train_split nor val_split; occtrain trains on those two splits"
            )
        _check_tokens(tables, scene, index, ann)
        _check_gts(index, name)
        jobs.append(SceneJob(name, split_of[name], scene["token"]))
    if not jobs:
        raise DataError(f"{tables.path('scene')}: no scene; {version} holds none to import")
    order = {name: k for k, name in enumerate(raw_splits["train"] + raw_splits["val"])}
    jobs.sort(key=lambda j: order[j.name])
    first = index.info(jobs[0].name, index.scenes[jobs[0].name][0])
    return Release(tables, index, jobs, cameras_from_tables=not first.get("camera_sensor"))


def _split_keys(ann: Path) -> dict[str, list[str]]:
    """Occ3D's train_split and val_split (a release without one is refused, naming it)."""
    from occtrain.formats.io import parse_json

    data = parse_json(ann.read_bytes())  # DatasetIndex.open parsed and checked it already
    out = {}
    for split in ("train", "val"):
        key = f"{split}_split"
        if key not in data:
            raise DataError(
                f"{ann}: no '{key}' key; Occ3D-nuScenes' annotations.json lists its scenes by split (train_split, "
                "val_split); restore it from the release"
            )
        out[split] = list(data[key])
    return out


def _check_tokens(tables: NuScenesTables, scene: dict, index: DatasetIndex, ann: Path) -> None:
    """Occ3D's samples of the scene are nuScenes' samples, in the same order: name the first that is not."""
    name = scene["name"]
    ours = [s["token"] for s in tables.scene_samples(scene)]
    theirs = index.scenes[name]
    for k, (a, b) in enumerate(zip(theirs, ours)):
        if a != b:
            what = "is not a sample of" if a not in tables.tables["sample"] else f"is not frame {k} of"
            raise DataError(
                f"{ann}: scene_infos.{name}.{a} (frame {k}) {what} nuScenes {tables.version}'s {name} "
                f"(sample.json has '{b}' there); the Occ3D and nuScenes releases disagree, use matching versions"
            )
    if len(theirs) != len(ours):
        k = min(len(theirs), len(ours))
        missing = ours[k] if len(ours) > k else theirs[k]
        side = "annotations.json lacks" if len(ours) > k else "nuScenes has no"
        raise DataError(
            f"{ann}: scene_infos.{name}: {side} sample '{missing}' (frame {k}; Occ3D holds {len(theirs)} samples, "
            f"nuScenes {len(ours)}); the Occ3D and nuScenes releases disagree, use matching versions"
        )


def _check_gts(index: DatasetIndex, scene: str) -> None:
    for token in index.scenes[scene]:
        path = index.labels_path(scene, token)
        if not path.is_file():
            raise DataError(
                f"{path}: Occ3D labels not found (scene_infos.{scene}.{token}.gt_path); extract the release's gts/"
            )


# ----------------------------------------------------------------------------- frames


def _poses(records: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(timestamps us, xy (T, 2), yaw (T,) wrapped, translation (T, 3)) of ego_pose records."""
    t = np.array([p["timestamp"] for p in records], dtype=np.int64)
    trans = np.array([p["translation"] for p in records], dtype=np.float64).reshape(-1, 3)
    yaw = np.array([yaw_from_quaternion(p["rotation"]) for p in records], dtype=np.float64)
    return t, trans[:, :2], yaw, trans


def _pose_rates(track: list[dict], times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speed (m/s) and yaw rate (rad/s) at each of ``times`` from a pose track: the central
    difference of the poses on either side of the track's pose at that time."""
    t, xy, yaw, _ = _poses(track)
    speeds, rates = [], []
    for stamp in times:
        k = int(np.argmin(np.abs(t - stamp)))
        a, b = max(k - 1, 0), min(k + 1, len(t) - 1)
        dt = (t[b] - t[a]) / 1e6
        if dt <= 0:
            speeds.append(0.0)
            rates.append(0.0)
            continue
        speeds.append(float(np.linalg.norm(xy[b] - xy[a]) / dt))
        rates.append(_wrap(yaw[b] - yaw[a]) / dt)
    return np.array(speeds), np.array(rates)


def _can_bus_rates(messages: list[dict] | None, times: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Speed and yaw rate from the CAN bus message nearest each time, or None where a time
    has no message within CAN_BUS_TOLERANCE_S."""
    if not messages:
        return None
    utime = np.array([m["utime"] for m in messages], dtype=np.int64)
    speeds, rates = [], []
    for stamp in times:
        k = int(np.argmin(np.abs(utime - stamp)))
        if abs(int(utime[k]) - int(stamp)) > CAN_BUS_TOLERANCE_S * 1e6:
            return None
        vel = messages[k]["vel"]
        speeds.append(math.hypot(vel[0], vel[1]))
        rates.append(float(messages[k]["rotation_rate"][2]))
    return np.array(speeds), np.array(rates)


def _relative(points: np.ndarray, valid: np.ndarray, pose_xy: np.ndarray, pose_yaw: float) -> tuple[list, list[Flag]]:
    """Global points (N, 2) in an ego frame, [0, 0] and mask 0 where not valid."""
    out = np.zeros_like(points)
    if valid.any():
        out[valid] = global_to_ego(points[valid], pose_xy, pose_yaw)
    return _r(out), [1 if v else 0 for v in valid]


def _velocity(tables: NuScenesTables, ann: dict) -> np.ndarray:
    """Global (vx, vy) of an annotation from its neighbours in the instance's track, as
    nuScenes' devkit computes it (``box_velocity``: the previous and next annotations'
    positions over their time, one side at a track's ends, none across more than 1.5 s, 3 s
    centred); unlike the devkit, a centred span too long (the instance unseen on one side)
    falls back to the side within 1.5 s. [0, 0] where no neighbour is near enough (the
    devkit's NaN)."""
    anns, samples = tables.tables["sample_annotation"], tables.tables["sample"]

    def time(a: dict) -> float:
        return samples[a["sample_token"]]["timestamp"] / 1e6

    prev = anns.get(ann["prev"]) if ann["prev"] else None
    nxt = anns.get(ann["next"]) if ann["next"] else None
    spans = []
    if prev is not None and nxt is not None:
        spans.append((prev, nxt, 2 * VELOCITY_MAX_DT_S))
    spans += [(a, b, VELOCITY_MAX_DT_S) for a, b in ((ann, nxt), (prev, ann)) if a is not None and b is not None]
    for first, last, most in spans:
        dt = time(last) - time(first)
        if 0 < dt <= most:
            return (np.asarray(last["translation"][:2]) - np.asarray(first["translation"][:2])) / dt
    return np.zeros(2)


def scene_frames(
    tables: NuScenesTables, scene_token: str, can_bus: list[dict] | None
) -> tuple[list[FrameAnnotation], str]:
    """The FrameAnnotations of one scene and where its speeds came from ("can_bus" or "poses")."""
    scene = tables.get("scene", scene_token)
    samples = tables.scene_samples(scene)
    keys = [tables.key_frames[s["token"]][LIDAR] for s in samples]
    pose_records = [tables.get("ego_pose", sd["ego_pose_token"]) for sd in keys]
    _, xy, yaw, trans = _poses(pose_records)
    times = np.array([s["timestamp"] for s in samples], dtype=np.int64)
    pose_times = np.array([p["timestamp"] for p in pose_records], dtype=np.int64)
    rates = _can_bus_rates(can_bus, times)
    source = "can_bus"
    if rates is None:
        rates, source = _pose_rates(tables.lidar_poses[scene_token], pose_times), "poses"
    speed, yaw_rate = rates
    unwrapped = np.unwrap(yaw)
    n = len(samples)
    index_of = {s["token"]: k for k, s in enumerate(samples)}
    rotations = [np.asarray(p["rotation"], dtype=np.float64) for p in pose_records]

    frames: list[FrameAnnotation] = []
    for k, sample in enumerate(samples):
        pxy, pyaw = xy[k], float(yaw[k])
        fut_idx = np.arange(k + 1, k + FUTURE_STEPS + 1)
        past_idx = np.arange(k - PAST_STEPS, k)
        fut_valid, past_valid = fut_idx < n, past_idx >= 0
        future, fmask = _relative(xy[np.clip(fut_idx, 0, n - 1)], fut_valid, pxy, pyaw)
        past, pmask = _relative(xy[np.clip(past_idx, 0, n - 1)], past_valid, pxy, pyaw)
        last_move = float(np.linalg.norm(xy[k] - xy[k - 1])) if k > 0 else None
        dt = (times[k] - times[k - 1]) / 1e6 if k > 0 else 0.5
        boxes, futures, fut_masks = _boxes(tables, sample, index_of, samples, trans[k], rotations[k], pyaw)
        frames.append(
            {
                "scene": scene["name"],
                "token": sample["token"],
                "index": k,
                "timestamp": int(sample["timestamp"]),
                "ego_pose": {"translation": _r(trans[k]), "yaw": round(pyaw, 6)},
                "ego_speed": round(float(speed[k]), 4),
                "ego_accel": round(past_acceleration(float(speed[k]), last_move, dt), 4),
                "ego_yaw_rate": round(float(yaw_rate[k]), 5),
                "command": driving_command(np.asarray(future), np.asarray(fmask)),
                "meta_action": sidecar_label(xy, unwrapped, speed, k),
                "ego_future": future,
                "ego_future_mask": fmask,
                "ego_past": past,
                "ego_past_mask": pmask,
                "boxes": boxes,
                "agent_futures": futures,
                "agent_future_mask": fut_masks,
                "caption": "",
                "narration": "",
            }
        )
    return frames, source


def _boxes(
    tables: NuScenesTables,
    sample: dict,
    index_of: dict[str, int],
    samples: list[dict],
    ego_t: np.ndarray,
    ego_q: np.ndarray,
    ego_yaw: float,
) -> tuple[list[Box], list[list[list[float]]], list[list[Flag]]]:
    """The sample's boxes inside the grid (in the ego frame), their futures and masks."""
    from occtrain.data.cameras import quaternion_to_matrix

    to_ego = quaternion_to_matrix(ego_q).T
    anns = tables.tables["sample_annotation"]
    k = index_of[sample["token"]]
    rows = []
    for ann in tables.annotations_of.get(sample["token"], []):
        centre = to_ego @ (np.asarray(ann["translation"], dtype=np.float64) - ego_t)
        if not np.all(np.abs(centre[:2]) < RANGE_MAX[:2]):
            continue
        instance = tables.get("instance", ann["instance_token"])
        category = tables.get("category", instance["category_token"])["name"]
        cls = box_class(category) or "others"  # NuScenesTables.check refused any category without one
        w, length, h = ann["size"]
        attrs = [tables.get("attribute", a)["name"] for a in ann["attribute_tokens"]]
        box: Box = {
            "track_id": tables.instance_order[ann["instance_token"]],
            "category": cls,
            "center": _r(centre),
            "size": _r([length, w, h]),
            "yaw": round(_wrap(yaw_from_quaternion(ann["rotation"]) - ego_yaw), 5),
            "velocity": _r(rotate_to_ego(_velocity(tables, ann), ego_yaw)),
            "attribute": status(attrs[0]) if attrs else "",  # type: ignore[typeddict-item]
        }
        if ann["visibility_token"]:  # its level was checked on opening
            box["visibility"] = tables.get("visibility", ann["visibility_token"])["level"]  # type: ignore[typeddict-item]
        # The instance's positions at the next samples, along its next links.
        points, valid = np.zeros((FUTURE_STEPS, 2)), np.zeros(FUTURE_STEPS, dtype=bool)
        cur = ann
        while cur["next"] and cur["next"] in anns:
            cur = anns[cur["next"]]
            j = index_of.get(cur["sample_token"], -1) - k - 1
            if j >= FUTURE_STEPS or j < 0:
                break
            points[j], valid[j] = cur["translation"][:2], True
        fut, mask = _relative(points, valid, ego_t[:2], ego_yaw)
        rows.append((box["track_id"], box, fut, mask))
    rows.sort(key=lambda r: r[0])
    return [r[1] for r in rows], [r[2] for r in rows], [r[3] for r in rows]


def camera_sensor(tables: NuScenesTables, sample_token: str) -> dict[str, dict]:
    """A sample's ``camera_sensor`` records in the released Occ3D form, built from the tables
    (for an Occ3D root whose annotations hold none): img_path relative to the dataset root."""
    out = {}
    for channel, sd in sorted(tables.key_frames[sample_token].items()):
        if not channel.startswith(CAMERA_PREFIX):
            continue
        cs = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
        pose = tables.get("ego_pose", sd["ego_pose_token"])
        out[channel] = {
            "img_path": sd["filename"],
            "intrinsics": cs["camera_intrinsic"],
            "extrinsic": {"translation": cs["translation"], "rotation": cs["rotation"]},
            "ego_pose": {"translation": pose["translation"], "rotation": pose["rotation"]},
        }
    return out


# ----------------------------------------------------------------------------- writing


def _scene_files(release: Release, scene: str, out: Path) -> list[tuple[Path, Path]]:
    """(release file, its place in ``out``) of a scene's labels and camera images."""
    index, tables = release.occ3d, release.tables
    pairs = []
    for token in index.scenes[scene]:
        src = index.labels_path(scene, token)
        pairs.append((src, out / src.relative_to(index.root)))
        if release.cameras_from_tables:
            for sd in tables.key_frames[token].values():
                image = tables.root / sd["filename"]
                if tables.channel(sd).startswith(CAMERA_PREFIX) and image.is_file():
                    pairs.append((image, out / sd["filename"]))
            continue
        for record in (index.info(scene, token).get("camera_sensor") or {}).values():
            image = index.image_path(record["img_path"])
            # With the renderer's per-pixel class and depth beside it where the root has them
            # (an exported synthetic world; no real release does).
            for path in (image, *(image.with_name(f"{image.stem}{s}.png") for s in (CLASS_SUFFIX, DEPTH_SUFFIX))):
                if path.is_file():
                    pairs.append((path, out / path.relative_to(index.root)))
    return pairs


def _prepare_out(out: Path, fingerprint: dict) -> None:
    """Refuse an --out holding something else; an earlier import of the same release resumes."""
    from occtrain.formats.io import parse_json

    record = out / DATASET_FILE
    if record.is_file():
        try:
            existing = parse_json(record.read_bytes())
        except ValueError as err:
            raise DataError(f"{record}: not valid JSON ({err}); delete {out} and import again") from None
        mine = {k: existing.get(k) for k in fingerprint} if isinstance(existing, dict) else {}
        if mine != fingerprint:
            diff = sorted(k for k in fingerprint if mine.get(k) != fingerprint[k])
            raise DataError(
                f"{out}: already holds another dataset (differs in {', '.join(diff)}); choose another --out or "
                "delete it"
            )
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DataError(f"{out}: exists and is not an imported dataset; choose an empty or new --out directory")


def import_nuscenes(
    nuscenes: str | Path,
    version: str,
    occ3d: str | Path,
    out: str | Path,
    copy: bool = False,
    verbose: bool = True,
) -> dict:
    """Import a release into ``out`` (see the module docstring); the import's summary."""
    start = time.perf_counter()
    release = read_release(nuscenes, version, occ3d)
    out = Path(out)
    fingerprint = release.fingerprint
    _prepare_out(out, fingerprint)
    tables, index = release.tables, release.occ3d
    if not (out / DATASET_FILE).is_file():  # a resumed import keeps what a text import has filled since
        files = "copies" if copy else "hard links (copies across devices)"
        atomic_write_json(out / DATASET_FILE, dict(fingerprint, files=files, absent=dict(ABSENT)))
    sources: dict[str, str] = {}
    placed = 0
    todo = [j for j in release.jobs if not (out / FRAMES_DIR / f"{j.name}.json").is_file()]
    total = sum(len(index.scenes[j.name]) for j in release.jobs)
    with progress_bar(total, f"importing {len(release.jobs)} scenes of nuScenes {version}") as advance:
        advance(total - sum(len(index.scenes[j.name]) for j in todo))
        for job in todo:
            placed += place_files(_scene_files(release, job.name, out), copy)
            frames, sources[job.name] = scene_frames(tables, job.token, read_can_bus(tables.root, job.name))
            atomic_write_json(out / FRAMES_DIR / f"{job.name}.json", frames, indent=None)
            advance(len(frames))
    infos: dict[str, dict[str, dict]] = {}
    for job in release.jobs:
        infos[job.name] = {}
        for token in index.scenes[job.name]:
            info = dict(index.info(job.name, token))
            if release.cameras_from_tables:
                info["camera_sensor"] = camera_sensor(tables, token)
            infos[job.name][token] = info
    splits = {f"{s}_split": [j.name for j in release.jobs if j.split == s] for s in ("train", "val")}
    atomic_write_json(out / ANNOTATIONS_FILE, splits | {"scene_infos": infos}, indent=None)
    summary = {
        "scenes": len(release.jobs),
        "written": len(todo),
        "frames": total,
        "speeds_from_can_bus": sum(1 for s in sources.values() if s == "can_bus"),
        "speeds_from_poses": sum(1 for s in sources.values() if s == "poses"),
        "files_placed": placed,
        "cameras": "nuScenes' tables" if release.cameras_from_tables else "Occ3D's records",
    }
    if verbose:
        console.print(
            f"imported {summary['scenes']} scenes ({len(todo)} written, {len(release.jobs) - len(todo)} already "
            "there), "
            f"{total} frames in {time.perf_counter() - start:.1f}s -> {out}",
            markup=False,
        )
    return summary

"""The nuScenes v1.0 tables, read and checked without nuscenes-devkit.

A nuScenes release keeps its annotations as plain JSON, one list of records per table in
``ROOT/<version>/<table>.json`` (``v1.0-mini``, ``v1.0-trainval``, ...), each record keyed
by its ``token``; the schema is documented with the release (nuScenes' ``schema_nuscenes.md``):
scene, sample, sample_data, ego_pose, calibrated_sensor, sensor, sample_annotation,
instance, category, attribute, visibility, log and map. The CAN bus expansion adds
``ROOT/can_bus/<scene>_pose.json`` (a list of ``{utime, pos, orientation, vel, accel,
rotation_rate}`` messages, ``vel`` and ``rotation_rate`` in the ego frame).

Why no devkit: nuscenes-devkit 1.2.0 pins ``numpy<2.0`` while occtrain needs numpy 2 (torch,
transformers and scikit-learn of its pins), and pip's fallback, 1.1.11, needs a matplotlib
(3.5.3) that no longer builds. The tables are documented JSON and occtrain reads the few
keys it needs, so this module reads them itself: each table against a TypedDict of the keys
read (extra keys are allowed), then every reference the import follows, so a broken release
is one line naming its file, record and key before anything is written.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, NotRequired, TypedDict

from occtrain.data.releases.categories import VISIBILITY_LEVELS, box_class
from occtrain.data.schema import Quaternion, Vec3
from occtrain.data.validate import first_problem
from occtrain.errors import DataError
from occtrain.formats.io import parse_json

#: The versions an import reads: the test split has no Occ3D labels.
VERSIONS = ("v1.0-mini", "v1.0-trainval")
#: Every table of a v1.0 release, as the export writes them.
TABLES = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)
#: The tables the import reads (log and map are not: map-derived fields are not built).
READ_TABLES = tuple(t for t in TABLES if t not in ("log", "map"))
CAN_BUS_DIR = "can_bus"
LIDAR = "LIDAR_TOP"
FIX = "re-download or re-extract that nuScenes table"


class SceneRecord(TypedDict):
    token: str
    name: str
    first_sample_token: str
    last_sample_token: str
    log_token: NotRequired[str]
    nbr_samples: NotRequired[int]


class SampleRecord(TypedDict):
    token: str
    timestamp: int
    scene_token: str
    prev: str
    next: str


class SampleDataRecord(TypedDict):
    token: str
    sample_token: str
    ego_pose_token: str
    calibrated_sensor_token: str
    timestamp: int
    is_key_frame: bool
    filename: str
    prev: str
    next: str
    fileformat: NotRequired[str]
    width: NotRequired[int]
    height: NotRequired[int]


class EgoPoseRecord(TypedDict):
    token: str
    timestamp: int
    translation: Vec3
    rotation: Quaternion


class CalibratedSensorRecord(TypedDict):
    token: str
    sensor_token: str
    translation: Vec3
    rotation: Quaternion
    camera_intrinsic: list[list[float]]  # 3 x 3 for a camera, [] otherwise


class SensorRecord(TypedDict):
    token: str
    channel: str
    modality: str


class SampleAnnotationRecord(TypedDict):
    token: str
    sample_token: str
    instance_token: str
    visibility_token: str
    attribute_tokens: list[str]
    translation: Vec3  # global
    size: Vec3  # width, length, height (nuScenes' order)
    rotation: Quaternion  # global, w x y z
    prev: str
    next: str
    num_lidar_pts: NotRequired[int]
    num_radar_pts: NotRequired[int]


class InstanceRecord(TypedDict):
    token: str
    category_token: str
    nbr_annotations: NotRequired[int]
    first_annotation_token: NotRequired[str]
    last_annotation_token: NotRequired[str]


class CategoryRecord(TypedDict):
    token: str
    name: str
    description: NotRequired[str]


class AttributeRecord(TypedDict):
    token: str
    name: str
    description: NotRequired[str]


class VisibilityRecord(TypedDict):
    token: str
    level: str
    description: NotRequired[str]


class CanBusPose(TypedDict):
    utime: int
    vel: Vec3  # m/s, ego frame
    rotation_rate: Vec3  # rad/s, ego frame
    pos: NotRequired[Vec3]
    orientation: NotRequired[Quaternion]
    accel: NotRequired[Vec3]


SCHEMAS: dict[str, Any] = {
    "scene": SceneRecord,
    "sample": SampleRecord,
    "sample_data": SampleDataRecord,
    "ego_pose": EgoPoseRecord,
    "calibrated_sensor": CalibratedSensorRecord,
    "sensor": SensorRecord,
    "sample_annotation": SampleAnnotationRecord,
    "instance": InstanceRecord,
    "category": CategoryRecord,
    "attribute": AttributeRecord,
    "visibility": VisibilityRecord,
    "log": dict[str, Any],
    "map": dict[str, Any],
}


def read_json(path: Path, what: str, fix: str) -> Any:
    """A JSON file; missing, unreadable or broken is one DataError line naming it."""
    if not path.is_file():
        raise DataError(f"{path}: {what} not found; {fix}")
    try:
        return parse_json(path.read_bytes())
    except ValueError as err:
        raise DataError(f"{path}: not valid JSON ({err}); {fix}") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read it ({err.strerror}); {fix}") from None


def read_table(folder: Path, table: str) -> list[dict]:
    """One table's records, checked against its schema (the first problem names its key)."""
    path = folder / f"{table}.json"
    records = read_json(path, f"nuScenes table '{table}'", FIX)
    schema: Any = list[SCHEMAS[table]]  # type: ignore[valid-type]
    problem = first_problem(records, schema)
    if problem:
        raise DataError(f"{path}: {problem}; {FIX}")
    return records


def _is_rotation(q: list[float]) -> bool:
    return math.fsum(v * v for v in q) > 1e-12


@dataclass
class NuScenesTables:
    """The tables of one release version, indexed by token, with every reference the
    import follows checked (see the module docstring)."""

    root: Path
    version: str
    tables: dict[str, dict[str, dict]] = field(repr=False)

    @classmethod
    def open(cls, root: str | Path, version: str, tables: Iterable[str] = READ_TABLES) -> NuScenesTables:
        root = Path(root)
        folder = root / version
        if not root.is_dir():
            raise DataError(f"{root}: nuScenes root not found; --nuscenes names the folder that holds {version}/")
        if not folder.is_dir():
            found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
            raise DataError(
                f"{folder}: no {version} tables in the nuScenes root (it holds "
                f"{', '.join(found) or 'no v1.0-* folder'}); "
                "pass the --version it holds, or extract that version there"
            )
        indexed = {}
        for table in tables:
            records = read_table(folder, table)
            by_token = {r["token"]: r for r in records} if table not in ("log", "map") else {}
            if table not in ("log", "map") and len(by_token) != len(records):
                seen: set[str] = set()
                dup = ""
                for r in records:
                    if r["token"] in seen:
                        dup = r["token"]
                        break
                    seen.add(r["token"])
                raise DataError(f"{folder / (table + '.json')}: token '{dup}' names two records; {FIX}")
            indexed[table] = by_token
        out = cls(root, version, indexed)
        out.check()
        return out

    def path(self, table: str) -> Path:
        return self.root / self.version / f"{table}.json"

    def get(self, table: str, token: str) -> dict:
        return self.tables[table][token]

    # ------------------------------------------------------------------------- checks

    def _ref(self, table: str, record: dict, key: str, target: str) -> None:
        token = record[key]
        if token not in self.tables[target]:
            raise DataError(
                f"{self.path(table)}: {table} '{record['token']}'.{key} '{token}' is not in {target}.json; {FIX}"
            )

    def check(self) -> None:
        """Every reference the import follows resolves, and every rotation is one."""
        t = self.tables
        for scene in t["scene"].values():
            for key in ("first_sample_token", "last_sample_token"):
                self._ref("scene", scene, key, "sample")
        for sample in t["sample"].values():
            self._ref("sample", sample, "scene_token", "scene")
        for sd in t["sample_data"].values():
            self._ref("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
            self._ref("sample_data", sd, "ego_pose_token", "ego_pose")
            if sd["sample_token"] not in t["sample"]:
                self._ref("sample_data", sd, "sample_token", "sample")
        for cs in t["calibrated_sensor"].values():
            self._ref("calibrated_sensor", cs, "sensor_token", "sensor")
        for inst in t["instance"].values():
            self._ref("instance", inst, "category_token", "category")
        for ann in t["sample_annotation"].values():
            self._ref("sample_annotation", ann, "sample_token", "sample")
            self._ref("sample_annotation", ann, "instance_token", "instance")
            if ann["visibility_token"]:
                self._ref("sample_annotation", ann, "visibility_token", "visibility")
            for k, tok in enumerate(ann["attribute_tokens"]):
                if tok not in t["attribute"]:
                    raise DataError(
                        f"{self.path('sample_annotation')}: sample_annotation '{ann['token']}'.attribute_tokens[{k}] "
                        f"'{tok}' is not in attribute.json; {FIX}"
                    )
        for table in ("ego_pose", "calibrated_sensor", "sample_annotation"):
            for rec in t[table].values():
                if not _is_rotation(rec["rotation"]):
                    raise DataError(
                        f"{self.path(table)}: {table} '{rec['token']}'.rotation is {rec['rotation']}, a zero "
                        "quaternion and no rotation; fix that record (w, x, y, z) or remove it"
                    )
        for level in t["visibility"].values():
            if level["level"] not in VISIBILITY_LEVELS.values():
                raise DataError(
                    f"{self.path('visibility')}: visibility '{level['token']}'.level '{level['level']}' is not one of "
                    f"nuScenes' levels ({', '.join(VISIBILITY_LEVELS.values())}); {FIX}"
                )
        for used in sorted({inst["category_token"] for inst in t["instance"].values()}):
            name = t["category"][used]["name"]
            if box_class(name) is None:
                raise DataError(
                    f"{self.path('category')}: category '{used}'.name '{name}', which instances use, is not a nuScenes "
                    f"v1.0 annotation category, so it has no Occ3D class; {FIX}"
                )
        for sample in t["sample"].values():  # every sample has the pose the import reads
            if LIDAR not in self.key_frames.get(sample["token"], {}):
                raise DataError(
                    f"{self.path('sample_data')}: sample '{sample['token']}' (scene "
                    f"'{t['scene'][sample['scene_token']]['name']}') has no key-frame {LIDAR} sample_data, so no ego "
                    f"pose; {FIX}"
                )

    # ------------------------------------------------------------------------- derived

    @cached_property
    def channels(self) -> dict[str, str]:
        """calibrated_sensor token -> its sensor's channel (CAM_FRONT, LIDAR_TOP, ...)."""
        sensors = self.tables["sensor"]
        return {tok: sensors[cs["sensor_token"]]["channel"] for tok, cs in self.tables["calibrated_sensor"].items()}

    def channel(self, sd: dict) -> str:
        return self.channels[sd["calibrated_sensor_token"]]

    @cached_property
    def key_frames(self) -> dict[str, dict[str, dict]]:
        """sample token -> channel -> its key-frame sample_data (what the devkit calls ``sample['data']``)."""
        out: dict[str, dict[str, dict]] = {}
        for sd in self.tables["sample_data"].values():
            if sd["is_key_frame"]:
                out.setdefault(sd["sample_token"], {})[self.channel(sd)] = sd
        return out

    @cached_property
    def lidar_poses(self) -> dict[str, list[dict]]:
        """scene token -> the ego poses of every LIDAR_TOP sample_data of the scene (key
        frames and sweeps), in time order: the densest pose track a release gives."""
        samples = self.tables["sample"]
        poses = self.tables["ego_pose"]
        out: dict[str, list[dict]] = {}
        for sd in self.tables["sample_data"].values():
            if self.channel(sd) == LIDAR and sd["sample_token"] in samples:
                scene = samples[sd["sample_token"]]["scene_token"]
                out.setdefault(scene, []).append(poses[sd["ego_pose_token"]])
        for track in out.values():
            track.sort(key=lambda p: p["timestamp"])
        return out

    @cached_property
    def annotations_of(self) -> dict[str, list[dict]]:
        """sample token -> its sample_annotation records, in table order."""
        out: dict[str, list[dict]] = {}
        for ann in self.tables["sample_annotation"].values():
            out.setdefault(ann["sample_token"], []).append(ann)
        return out

    @cached_property
    def instance_order(self) -> dict[str, int]:
        """instance token -> its position in instance.json: a box's track id (stable across
        the frames of a scene, and unique in the release)."""
        return {tok: k for k, tok in enumerate(self.tables["instance"])}

    def scene_samples(self, scene: dict) -> list[dict]:
        """A scene's samples in time order, by its first sample and the ``next`` links."""
        samples = self.tables["sample"]
        out, token, seen = [], scene["first_sample_token"], set()
        while token:
            if token in seen or token not in samples:
                raise DataError(
                    f"{self.path('sample')}: the next links of scene '{scene['name']}' "
                    f"{'loop' if token in seen else f'name sample {token!r}, which is not in the table'}; {FIX}"
                )
            seen.add(token)
            sample = samples[token]
            if sample["scene_token"] != scene["token"]:
                raise DataError(
                    f"{self.path('sample')}: sample '{token}'.scene_token is not scene '{scene['name']}', whose next "
                    f"links reach it; {FIX}"
                )
            out.append(sample)
            token = sample["next"]
        if out[-1]["token"] != scene["last_sample_token"]:
            raise DataError(
                f"{self.path('scene')}: scene '{scene['name']}'.last_sample_token is not where its samples' next links "
                f"end ('{out[-1]['token']}'); {FIX}"
            )
        return out

    def scenes_by_name(self) -> dict[str, dict]:
        return {s["name"]: s for s in self.tables["scene"].values()}


def read_can_bus(root: Path, scene: str) -> list[dict] | None:
    """A scene's CAN bus pose messages in time order (``ROOT/can_bus/<scene>_pose.json``),
    or None where the expansion holds none for it (nuScenes lacks it for some scenes)."""
    path = root / CAN_BUS_DIR / f"{scene}_pose.json"
    if not path.is_file():
        return None
    messages = read_json(path, "CAN bus pose file", "re-extract the CAN bus expansion")
    problem = first_problem(messages, list[CanBusPose])
    if problem:
        raise DataError(f"{path}: {problem}; re-extract the CAN bus expansion")
    return sorted(messages, key=lambda m: m["utime"])

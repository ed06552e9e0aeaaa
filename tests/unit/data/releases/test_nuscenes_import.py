"""The nuScenes import on a release written by hand to the documented v1.0 schema (one scene
of eight samples, LIDAR_TOP sweeps between them, a car, a pedestrian and two animals) beside
an Occ3D root of the same tokens: each sidecar field against the value worked out by hand."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import hand_labels
from occtrain.data.layout import DatasetIndex
from occtrain.data.meta_actions import sidecar_label
from occtrain.data.poses import quaternion_from_yaw
from occtrain.data.releases.nuscenes_import import import_nuscenes, read_release, scene_frames
from occtrain.data.releases.nuscenes_tables import NuScenesTables, read_can_bus
from occtrain.errors import DataError

VERSION = "v1.0-mini"
N = 8
HEADING = math.pi / 2  # the ego drives along global +y
T0 = 1_530_000_000_000_000


def tok(*parts: object) -> str:
    return "-".join(str(p) for p in parts).ljust(8, "x")


def ego_xy(t_s: float) -> list[float]:
    return [100.0, 50.0 + 5.0 * t_s, 0.0]  # 5 m/s


def car_xy(k: int) -> list[float]:
    return [98.0, 60.0 + 3.5 * k, 0.8]  # 7 m/s along +y, 2 m to the ego's left (global -x)


def write_release(root: Path) -> Path:
    """A nuScenes v1.0 release as its schema documents it: every table a JSON list of records."""
    samples = [tok("sample", k) for k in range(N)]
    t: dict[str, list[dict]] = {name: [] for name in ("scene", "sample", "sample_data", "ego_pose", "log", "map")}
    t["sensor"] = [
        {"token": "s-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
        {"token": "s-front", "channel": "CAM_FRONT", "modality": "camera"},
    ]
    t["calibrated_sensor"] = [
        {
            "token": "cs-lidar",
            "sensor_token": "s-lidar",
            "translation": [0.9, 0, 1.8],
            "rotation": [1, 0, 0, 0],
            "camera_intrinsic": [],
        },
        {
            "token": "cs-front",
            "sensor_token": "s-front",
            "translation": [1.7, 0, 1.5],
            "rotation": [0.5, -0.5, 0.5, -0.5],
            "camera_intrinsic": [[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]],
        },
    ]
    t["scene"] = [
        {
            "token": "sc",
            "log_token": "log",
            "nbr_samples": N,
            "first_sample_token": samples[0],
            "last_sample_token": samples[-1],
            "name": "scene-0061",
            "description": "hand-made",
        }
    ]
    t["log"] = [
        {
            "token": "log",
            "logfile": "n015",
            "vehicle": "n015",
            "date_captured": "2018-07-24",
            "location": "singapore-onenorth",
        }
    ]
    lidar = []  # key frames and sweeps, 4 Hz
    for k in range(N):
        t["sample"].append(
            {
                "token": samples[k],
                "timestamp": T0 + 500_000 * k,
                "scene_token": "sc",
                "prev": samples[k - 1] if k else "",
                "next": samples[k + 1] if k + 1 < N else "",
            }
        )
        for sweep in (0, 1) if k + 1 < N else (0,):
            lidar.append((k, sweep))
    for n, (k, sweep) in enumerate(lidar):
        stamp = T0 + 500_000 * k + 250_000 * sweep
        pose = tok("pose", "lidar", n)
        t["ego_pose"].append(
            {
                "token": pose,
                "timestamp": stamp,
                "translation": ego_xy((stamp - T0) / 1e6),
                "rotation": quaternion_from_yaw(HEADING),
            }
        )
        t["sample_data"].append(
            {
                "token": tok("sd", "lidar", n),
                "sample_token": samples[k],
                "ego_pose_token": pose,
                "calibrated_sensor_token": "cs-lidar",
                "timestamp": stamp,
                "fileformat": "pcd",
                "is_key_frame": sweep == 0,
                "height": 0,
                "width": 0,
                "filename": f"{'samples' if sweep == 0 else 'sweeps'}/LIDAR_TOP/{n}.pcd.bin",
                "prev": tok("sd", "lidar", n - 1) if n else "",
                "next": tok("sd", "lidar", n + 1) if n + 1 < len(lidar) else "",
            }
        )
    for k in range(N):
        pose = tok("pose", "cam", k)
        t["ego_pose"].append(
            {
                "token": pose,
                "timestamp": T0 + 500_000 * k + 10_000,
                "translation": ego_xy(0.5 * k + 0.01),
                "rotation": quaternion_from_yaw(HEADING),
            }
        )
        t["sample_data"].append(
            {
                "token": tok("sd", "cam", k),
                "sample_token": samples[k],
                "ego_pose_token": pose,
                "calibrated_sensor_token": "cs-front",
                "timestamp": T0 + 500_000 * k + 10_000,
                "fileformat": "jpg",
                "is_key_frame": True,
                "height": 900,
                "width": 1600,
                "filename": f"samples/CAM_FRONT/{k}.jpg",
                "prev": tok("sd", "cam", k - 1) if k else "",
                "next": tok("sd", "cam", k + 1) if k + 1 < N else "",
            }
        )
    t["category"] = [
        {"token": f"c-{name}", "name": name, "description": ""}
        for name in ("vehicle.car", "human.pedestrian.child", "animal")
    ]
    t["attribute"] = [
        {"token": f"a-{name}", "name": name, "description": ""}
        for name in ("vehicle.moving", "pedestrian.sitting_lying_down")
    ]
    t["visibility"] = [
        {"token": str(i), "level": lv, "description": ""}
        for i, lv in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"), 1)
    ]
    t["instance"], t["sample_annotation"] = [], []

    def track(
        name: str, category: str, at: dict[int, list[float]], size: list[float], yaw: float, attr: list[str], vis: str
    ) -> None:
        anns = [tok("ann", name, k) for k in at]
        for n, (k, xyz) in enumerate(at.items()):
            t["sample_annotation"].append(
                {
                    "token": anns[n],
                    "sample_token": samples[k],
                    "instance_token": f"i-{name}",
                    "visibility_token": vis,
                    "attribute_tokens": [f"a-{a}" for a in attr],
                    "translation": xyz,
                    "size": size,
                    "rotation": quaternion_from_yaw(yaw),
                    "prev": anns[n - 1] if n else "",
                    "next": anns[n + 1] if n + 1 < len(anns) else "",
                    "num_lidar_pts": 12,
                    "num_radar_pts": 0,
                }
            )
        t["instance"].append(
            {
                "token": f"i-{name}",
                "category_token": f"c-{category}",
                "nbr_annotations": len(anns),
                "first_annotation_token": anns[0],
                "last_annotation_token": anns[-1],
            }
        )

    track("car", "vehicle.car", {k: car_xy(k) for k in range(N)}, [1.9, 4.5, 1.6], HEADING, ["vehicle.moving"], "4")
    track(
        "ped",
        "human.pedestrian.child",
        {k: [103.0, 52.0, 0.5] for k in range(3)},
        [0.5, 0.6, 1.2],
        0.3,
        ["pedestrian.sitting_lying_down"],
        "2",
    )
    track("far", "animal", {0: [100.0, 130.0, 0.3]}, [0.3, 0.8, 0.5], 0.0, [], "1")  # 80 m ahead: off the grid
    track("cat", "animal", {4: [99.0, 65.0, 0.2]}, [0.3, 0.6, 0.3], 0.0, [], "")
    folder = root / VERSION
    folder.mkdir(parents=True)
    for name, rows in t.items():
        (folder / f"{name}.json").write_text(json.dumps(rows))
    return root


def write_occ3d(root: Path, nuscenes: Path) -> Path:
    """Occ3D-nuScenes' annotations.json and gts/ for the release's samples."""
    samples = json.loads((nuscenes / VERSION / "sample.json").read_text())
    infos = {}
    for k, s in enumerate(samples):
        infos[s["token"]] = {
            "timestamp": str(s["timestamp"]),
            "ego_pose": {"translation": ego_xy(0.5 * k), "rotation": quaternion_from_yaw(HEADING)},
            "prev": s["prev"],
            "next": s["next"],
            "gt_path": f"gts/scene-0061/{s['token']}/labels.npz",
        }
        path = root / "gts" / "scene-0061" / s["token"] / "labels.npz"
        path.parent.mkdir(parents=True)
        np.savez_compressed(path, **hand_labels(k))
    (root / "annotations.json").write_text(
        json.dumps({"train_split": ["scene-0061"], "val_split": [], "scene_infos": {"scene-0061": infos}})
    )
    return root


@pytest.fixture
def release(tmp_path: Path) -> tuple[Path, Path]:
    nus = write_release(tmp_path / "nuscenes")
    return nus, write_occ3d(tmp_path / "occ3d", nus)


def frames_of(nus: Path, can_bus: list[dict] | None = None) -> list[dict]:
    tables = NuScenesTables.open(nus, VERSION)
    frames, _ = scene_frames(tables, "sc", can_bus)
    return frames


def test_the_ego_comes_from_the_poses(release) -> None:
    frames = frames_of(release[0])
    assert [f["index"] for f in frames] == list(range(N))
    assert all(f["ego_speed"] == pytest.approx(5.0) for f in frames)  # the sweeps' central difference
    assert all(f["ego_yaw_rate"] == 0.0 and f["ego_accel"] == pytest.approx(0.0, abs=1e-6) for f in frames)
    assert frames[2]["ego_future"][:2] == [[2.5, 0.0], [5.0, 0.0]]  # along the ego's own x
    assert frames[2]["ego_future_mask"] == [1, 1, 1, 1, 1, 0] and frames[2]["ego_past_mask"] == [0, 0, 1, 1]
    assert frames[2]["ego_past"][2:] == [[-5.0, 0.0], [-2.5, 0.0]]
    assert frames[2]["ego_pose"] == {"translation": [100.0, 55.0, 0.0], "yaw": pytest.approx(HEADING)}
    assert {f["command"] for f in frames} == {"go straight"}
    assert {(m := f["meta_action"])["speed"] + "/" + m["direction"] for f in frames} == {"maintain/straight"}
    assert frames[0]["caption"] == frames[0]["narration"] == ""


def test_the_can_bus_gives_speed_and_yaw_rate_where_it_covers_every_sample(release) -> None:
    messages = [
        {
            "utime": T0 + 500_000 * k + 20_000,
            "vel": [6.0, 0.5, 0.0],
            "rotation_rate": [0.0, 0.0, 0.1],
            "pos": [0, 0, 0],
            "orientation": [1, 0, 0, 0],
            "accel": [0, 0, 0],
        }
        for k in range(N)
    ]
    frames = frames_of(release[0], messages)
    assert all(f["ego_speed"] == pytest.approx(math.hypot(6.0, 0.5), abs=1e-4) for f in frames)
    assert all(f["ego_yaw_rate"] == pytest.approx(0.1) for f in frames)
    gap = messages[:3] + messages[4:]  # a sample 0.5 s from any message: the poses instead
    assert all(f["ego_speed"] == pytest.approx(5.0) for f in frames_of(release[0], gap))


def test_boxes_are_in_the_ego_frame_with_occ3d_classes_tracks_and_futures(release) -> None:
    frames = frames_of(release[0])
    car, ped = frames[0]["boxes"]  # the animal 80 m ahead is off the grid
    assert car == {
        "track_id": 0,
        "category": "car",
        "center": [10.0, 2.0, 0.8],
        "size": [4.5, 1.9, 1.6],
        "yaw": 0.0,
        "velocity": [7.0, 0.0],
        "attribute": "moving",
        "visibility": "v80-100",
    }
    assert ped["track_id"] == 1 and ped["category"] == "pedestrian" and ped["attribute"] == "standing"
    assert ped["center"][:2] == [2.0, -3.0] and ped["velocity"] == [0.0, 0.0] and ped["visibility"] == "v40-60"
    assert ped["yaw"] == pytest.approx(0.3 - HEADING, abs=1e-5)
    assert frames[0]["agent_future_mask"] == [[1] * 6, [1, 1, 0, 0, 0, 0]]
    assert frames[0]["agent_futures"][0][0] == [13.5, 2.0]  # the car at the next sample, in this frame
    assert frames[0]["agent_futures"][1][:2] == [[2.0, -3.0], [2.0, -3.0]]
    cat = [b for b in frames[4]["boxes"] if b["track_id"] == 3]
    assert cat[0]["category"] == "others" and cat[0]["velocity"] == [0.0, 0.0] and "visibility" not in cat[0]
    assert frames[7]["agent_future_mask"] == [[0] * 6]  # the car at the scene's last sample


def test_the_windows_end_with_the_scene() -> None:
    """A release ends where its scene does: windows are cut there, and the last frame carries
    the label before it; the world simulates past its end, so its windows never are."""
    xy = np.array([[0.5 * k * (k > 6) + 3.0 * k, 0.0] for k in range(10)])  # speeds up at the end
    yaw, speed = np.zeros(10), np.array([6.0] * 7 + [8.0, 10.0, 12.0])
    assert sidecar_label(xy, yaw, speed, 6)["speed"] == "accelerate"  # the 1 s window holds 7 and 8
    assert sidecar_label(xy, yaw, speed, 8)["speed"] == "accelerate"  # cut to 0.5 s: 10 -> 12
    assert sidecar_label(xy, yaw, speed, 9) == sidecar_label(xy, yaw, speed, 8)
    assert sidecar_label(xy[:1], yaw[:1], np.array([0.1]), 0) == {"speed": "maintain", "direction": "stop"}


def test_the_import_writes_the_layout_and_links_occ3ds_files(release, tmp_path: Path) -> None:
    nus, occ3d = release
    summary = import_nuscenes(nus, VERSION, occ3d, tmp_path / "ds", verbose=False)
    assert summary["scenes"] == 1 and summary["frames"] == N and summary["speeds_from_poses"] == 1
    assert summary["cameras"] == "nuScenes' tables" and summary["files_placed"] == N  # the labels: no image here
    ds = DatasetIndex.open(tmp_path / "ds")
    first = ds.scenes["scene-0061"][0]
    assert ds.labels_path("scene-0061", first).samefile(occ3d / "gts" / "scene-0061" / first / "labels.npz")  # linked
    assert ds.labels("scene-0061", ds.scenes["scene-0061"][3])["semantics"].shape == (200, 200, 16)
    info = ds.info("scene-0061", ds.scenes["scene-0061"][0])
    assert info["camera_sensor"]["CAM_FRONT"]["img_path"] == "samples/CAM_FRONT/0.jpg"  # Occ3D had none
    assert info["camera_sensor"]["CAM_FRONT"]["intrinsics"][0][0] == 1266.4
    assert ds.frames("scene-0061")[0]["boxes"][0]["category"] == "car"
    assert "narration" in ds.available_tasks()["chain_of_thought"]
    assert read_can_bus(nus, "scene-0061") is None


def test_occ3d_camera_records_stay_as_the_release_has_them(release, tmp_path: Path) -> None:
    nus, occ3d = release
    ann = json.loads((occ3d / "annotations.json").read_text())
    record = {
        "img_path": "CAM_FRONT/x.jpg",
        "intrinsics": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "extrinsic": {"translation": [0, 0, 0], "rotation": [1, 0, 0, 0]},
        "ego_pose": {"translation": [0, 0, 0], "rotation": [1, 0, 0, 0]},
    }
    for info in ann["scene_infos"]["scene-0061"].values():
        info["camera_sensor"] = {"CAM_FRONT": record}
    (occ3d / "annotations.json").write_text(json.dumps(ann))
    (occ3d / "imgs" / "CAM_FRONT").mkdir(parents=True)
    (occ3d / "imgs" / "CAM_FRONT" / "x.jpg").write_bytes(b"an image")
    import_nuscenes(nus, VERSION, occ3d, tmp_path / "ds", verbose=False)
    out = json.loads((tmp_path / "ds" / "annotations.json").read_text())
    assert out["scene_infos"] == ann["scene_infos"]  # verbatim
    assert (tmp_path / "ds" / "imgs" / "CAM_FRONT" / "x.jpg").samefile(occ3d / "imgs" / "CAM_FRONT" / "x.jpg")


@pytest.mark.parametrize(
    "table, change, says",
    [
        ("sample", lambda rows: rows[2].update(next=rows[2]["token"]), "loop"),
        ("scene", lambda rows: rows[0].update(last_sample_token=rows[0]["first_sample_token"]), "last_sample_token"),
        ("instance", lambda rows: rows.append(dict(rows[0])), "names two records"),
        ("ego_pose", lambda rows: rows[0].update(rotation=[0, 0, 0, 0]), "zero quaternion"),
        ("sample_annotation", lambda rows: rows[0].update(attribute_tokens=["nope"]), "attribute_tokens[0] 'nope'"),
        ("category", lambda rows: rows[0].update(name="vehicle.spaceship"), "'vehicle.spaceship', which instances"),
        ("visibility", lambda rows: rows[3].update(level="v90-100"), "'v90-100' is not one of"),
    ],
)
def test_a_broken_table_is_one_line_naming_it(release, table: str, change, says: str, tmp_path: Path) -> None:
    nus, occ3d = release
    path = nus / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    change(rows)
    path.write_text(json.dumps(rows))
    with pytest.raises(DataError, match=None) as err:
        import_nuscenes(nus, VERSION, occ3d, tmp_path / "ds", verbose=False)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert VERSION in str(err.value)
    assert not (tmp_path / "ds").exists()


def test_a_scene_occ3d_lacks_is_named(release) -> None:
    nus, occ3d = release
    ann = json.loads((occ3d / "annotations.json").read_text())
    ann["scene_infos"]["scene-0062"] = ann["scene_infos"].pop("scene-0061")
    ann["train_split"] = ["scene-0062"]
    (occ3d / "annotations.json").write_text(json.dumps(ann).replace("gts/scene-0061", "gts/scene-0062"))
    with pytest.raises(DataError, match="scene_infos has no scene 'scene-0061'"):
        read_release(nus, VERSION, occ3d)

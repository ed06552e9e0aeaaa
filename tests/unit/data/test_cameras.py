"""Cameras: the rig's geometry, the renderer against an independent ray walk, the mask, the
Occ3D release layout on disk, and shards that carry the six views."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from occtrain.data.cameras import CAMERA_NAMES, matrix_to_quaternion, nuscenes_rig, quaternion_to_matrix
from occtrain.data.synth.grid import GROUND_LAYER
from occtrain.formats.occ3d import CLASS_INDEX, FREE, GRID_SHAPE, RANGE_MIN, VOXEL_SIZE

GROUND_CLASSES = [CLASS_INDEX[c] for c in ("driveable_surface", "other_flat", "sidewalk", "terrain")]

H, W = 72, 128


@pytest.fixture(scope="module")
def frame():
    """One frame of a generated scene: its labels and its six rendered views."""
    from occtrain.data.synth import generate_scene

    scene = generate_scene("scene-cams", seed=11, num_frames=8)
    labels = scene.render(6)
    return scene, labels, scene.cameras(6, labels["semantics"], H, W)


# ----------------------------------------------------------------------------- geometry


def test_the_rig_is_nuscenes_like():
    cams = nuscenes_rig(H, W)
    assert [c.name for c in cams] == list(CAMERA_NAMES)
    fov = {c.name: np.degrees(2 * np.arctan(c.width / 2 / c.intrinsic[0, 0])) for c in cams}
    assert 60 < fov["CAM_FRONT"] < 70 and fov["CAM_BACK"] > 85  # the back camera is the wide one
    heading = {c.name: np.degrees(np.arctan2(c.cam_to_ego[1, 2], c.cam_to_ego[0, 2])) for c in cams}
    assert heading["CAM_FRONT"] == pytest.approx(0) and heading["CAM_FRONT_LEFT"] == pytest.approx(55)
    assert abs(heading["CAM_BACK"]) == pytest.approx(180)
    front = cams[0]
    # nuScenes' CAM_FRONT extrinsic rotation is about (0.5, -0.5, 0.5, -0.5): x right, y down, z forward.
    np.testing.assert_allclose(matrix_to_quaternion(front.cam_to_ego[:3, :3]), [0.5, -0.5, 0.5, -0.5], atol=1e-9)


def test_projection_and_lifting_round_trip():
    rng = np.random.default_rng(0)
    for cam in nuscenes_rig(H, W):
        q = matrix_to_quaternion(cam.cam_to_ego[:3, :3])
        np.testing.assert_allclose(quaternion_to_matrix(q), cam.cam_to_ego[:3, :3], atol=1e-12)
        uv = rng.uniform([0, 0], [cam.width, cam.height], (200, 2))
        depth = rng.uniform(0.5, 80.0, 200)
        points = cam.lift(uv, depth)
        back, d, inside = cam.project(points)
        np.testing.assert_allclose(back, uv, atol=1e-8)
        np.testing.assert_allclose(d, depth, atol=1e-8)
        assert inside.all()
        behind, _, seen = cam.project(2 * cam.centre - points)  # mirrored through the centre: behind it
        assert not seen.any()


# ----------------------------------------------------------------------------- rendering


def _first_voxel_by_plane_crossings(
    origin: np.ndarray, dirs: np.ndarray, occupied: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(flat index of the first occupied voxel or -1, distance entering it) of each ray, by a
    method independent of the renderer: every crossing of a voxel plane along the ray,
    sorted, and the voxel holding each midpoint between consecutive crossings."""
    ts = []
    for axis in range(3):
        planes = RANGE_MIN[axis] + VOXEL_SIZE * np.arange(GRID_SHAPE[axis] + 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (planes[None] - origin[axis]) / dirs[:, axis : axis + 1]
        ts.append(np.where(np.isfinite(t) & (t > 0), t, np.inf))
    t = np.sort(np.concatenate([np.zeros((len(dirs), 1)), *ts], axis=1), axis=1)
    mid = (t[:, :-1] + t[:, 1:]) / 2
    valid = np.isfinite(mid)
    p = origin + dirs[:, None, :] * np.where(valid, mid, 0)[..., None]
    idx = np.floor((p - RANGE_MIN) / VOXEL_SIZE).astype(np.int64)
    inside = valid & np.all((idx >= 0) & (idx < GRID_SHAPE), axis=-1)
    flat = (idx[..., 0] * GRID_SHAPE[1] + np.clip(idx[..., 1], 0, GRID_SHAPE[1] - 1)) * GRID_SHAPE[2] + np.clip(
        idx[..., 2], 0, GRID_SHAPE[2] - 1
    )
    flat = np.where(inside, np.clip(flat, 0, occupied.size - 1), 0)
    hit = inside & occupied.reshape(-1)[flat]
    first = np.argmax(hit, axis=1)
    any_hit = hit.any(axis=1)
    rows = np.arange(len(dirs))
    return np.where(any_hit, flat[rows, first], -1), np.where(any_hit, t[rows, first], np.inf)


def test_every_pixel_shows_the_first_occupied_voxel_on_its_ray(frame):
    _, labels, views = frame
    sem = labels["semantics"]
    for cam, view in zip(nuscenes_rig(H, W), views):
        dirs, cos = cam.pixel_rays()
        # The ground is a plane under everything: a ray ends where it enters the ground layer,
        # labelled there or not; only a labelled voxel is "in the grid".
        surface = sem != FREE
        surface[..., GROUND_LAYER] = True
        voxel, entry = _first_voxel_by_plane_crossings(cam.centre, dirs.reshape(-1, 3), surface)
        labelled = (voxel >= 0) & (sem.reshape(-1)[np.maximum(voxel, 0)] != FREE)
        in_grid = view.in_grid.reshape(-1)
        assert np.array_equal(in_grid, labelled), cam.name
        assert np.array_equal(view.first_voxel.reshape(-1)[in_grid], voxel[in_grid]), cam.name
        assert np.array_equal(view.classes.reshape(-1)[in_grid], sem.reshape(-1)[voxel[in_grid]]), cam.name
        # The depth map is camera-z depth of the point where the ray enters that voxel.
        np.testing.assert_allclose(
            view.depth.reshape(-1)[in_grid], (entry * cos.reshape(-1))[in_grid], rtol=1e-5, atol=1e-4
        )


def test_rendered_depth_lifts_onto_the_voxel_the_pixel_shows(frame):
    _, labels, views = frame
    for cam, view in zip(nuscenes_rig(H, W), views):
        v, u = np.nonzero(view.in_grid)
        points = cam.lift(np.stack([u + 0.5, v + 0.5], axis=-1), view.depth[v, u])
        idx = np.stack(np.unravel_index(view.first_voxel[v, u], GRID_SHAPE), axis=-1)
        lo = RANGE_MIN + idx * VOXEL_SIZE
        # On the voxel's surface: inside its box, up to the float error of the entry face.
        assert np.all(points >= lo - 1e-3) and np.all(points <= lo + VOXEL_SIZE + 1e-3), cam.name


def test_sky_ground_and_colours(frame):
    _, _, views = frame
    for view in views:
        sky = view.classes == FREE
        assert (view.depth[sky] == 0).all() and (view.depth[~sky] > 0).all()
        beyond = ~view.in_grid & ~sky
        # The ground plane met where no sweep labelled it, or past the grid: the map's ground class.
        assert np.isin(view.classes[beyond], GROUND_CLASSES).all()
        assert view.image.dtype == np.uint8 and view.image.shape == (H, W, 3)
    front = views[0]
    assert (front.classes == FREE)[: H // 4].mean() > 0.3  # sky at the top of the front view
    assert len(np.unique(front.image.reshape(-1, 3), axis=0)) > 50  # shading, not flat class colours


@pytest.mark.parametrize("size, least", [((H, W), 0.99), ((90, 160), 0.95), ((54, 96), 0.95)])
def test_the_cameras_first_voxels_are_in_mask_camera(frame, size, least):
    """mask_camera is what the cameras see of what the lidar observed: of the voxels the
    images show that the lidar observed, the mask holds all at the default size (the
    mask's rays are the images' own) and nearly all at other sizes."""
    scene, labels, views = frame
    views = views if size == (H, W) else scene.cameras(6, labels["semantics"], *size)
    first = np.unique(np.concatenate([v.first_voxel[v.in_grid] for v in views]))
    first = first[labels["mask_lidar"].reshape(-1)[first] == 1]
    seen = labels["mask_camera"].reshape(-1)[first]
    assert len(first) > 500
    assert seen.mean() >= least, f"{seen.mean():.4f} of {len(first)} first-hit voxels in mask_camera"


def test_rendering_is_deterministic(frame):
    scene, labels, views = frame
    again = scene.cameras(6, labels["semantics"], H, W)
    for a, b in zip(views, again):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)


def test_lane_markings_and_signal_colours(frame):
    from occtrain.data.synth.camera_render import lane_markings, signal_colours
    from occtrain.data.synth.roads import LANE_WIDTH

    scene = frame[0]
    road = next(r for r in scene.net.roads[0] if r.lanes == 2 and r.median == 0)  # seed 11 has such roads
    crossing = scene.net.roads[1]
    gap = [
        (a.centre + a.half_width + 20, b.centre - b.half_width - 20)
        for a, b in zip(crossing, crossing[1:])
        if b.centre - b.half_width - a.centre - a.half_width > 60
    ][0]
    x = np.linspace(*gap, 400)
    centre = lane_markings(scene.net, np.stack([x, np.full_like(x, road.centre + road.median / 2)], axis=1))
    between = lane_markings(
        scene.net, np.stack([x, np.full_like(x, road.centre + road.median / 2 + LANE_WIDTH / 2)], axis=1)
    )
    assert (centre == 2).all() and (between == 0).all()  # a solid yellow line, bare lane beside it
    divider = lane_markings(
        scene.net, np.stack([x, np.full_like(x, road.centre + road.median / 2 + LANE_WIDTH)], axis=1)
    )
    assert 0.2 < (divider == 1).mean() < 0.5  # dashed: 3 m painted in every 9 m
    signals = scene.static.signals
    assert len(signals) and signals.shape[1] == 9
    states = np.array([signal_colours(scene.static, signals[:, :2], t) for t in np.arange(0, 60, 0.5)])
    assert set(np.unique(states)) == {0, 1, 2}  # red, amber and green all occur within a minute


# ----------------------------------------------------------------------------- on disk and in shards


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from occtrain.config import SynthConfig
    from occtrain.data.synthesize import synthesize

    root = tmp_path_factory.mktemp("camworld") / "world"
    synthesize(root, SynthConfig(train_scenes=1, val_scenes=1, frames_per_scene=3, seed=2), verbose=False)
    return root


def test_the_release_layout_reads_back(world):
    from occtrain.data.layout import DatasetIndex

    index = DatasetIndex.open(world)
    assert index.has_cameras
    scene, token = next(index.samples("val"))
    records = index.cameras(scene, token)
    assert [r.name for r in records] == list(CAMERA_NAMES)
    assert all(r.image == world / "imgs" / r.name / f"{token}.png" for r in records)
    # Written as the released files hold them: keyed by channel, intrinsics, img_path under imgs/.
    raw = json.loads((world / "annotations.json").read_text())["scene_infos"][scene][token]["camera_sensor"]
    assert list(raw) == list(CAMERA_NAMES)
    entry = raw["CAM_FRONT"]
    assert set(entry) == {"img_path", "intrinsics", "extrinsic", "ego_pose"} and set(entry["extrinsic"]) == {
        "translation",
        "rotation",
    }
    assert (
        entry["img_path"] == f"CAM_FRONT/{token}.png"
        and len(entry["intrinsics"]) == 3
        and len(entry["extrinsic"]["rotation"]) == 4
    )
    rig = {c.name: c for c in nuscenes_rig(H, W)}
    for r in records:
        np.testing.assert_allclose(r.intrinsic, rig[r.name].intrinsic, atol=1e-9)
        np.testing.assert_allclose(r.cam_to_ego, rig[r.name].cam_to_ego, atol=1e-9)
        x, y, yaw = index.ego_pose(scene, token)
        np.testing.assert_allclose(r.ego_to_global[:2, 3], [x, y])
        point = np.array([[10.0, 2.0, 1.0]])  # the record projects as the rig's camera does
        np.testing.assert_allclose(r.camera(H, W).project(point)[0], rig[r.name].project(point)[0])
    images = index.images(scene, token)
    classes, depth = index.camera_targets(scene, token)
    assert images.shape == (6, H, W, 3) and classes.shape == depth.shape == (6, H, W)
    assert classes.max() <= FREE and (depth[classes == FREE] == 0).all()


def test_the_readme_form_of_camera_records_reads_alike(world, tmp_path):
    """The Occ3D README's form (records keyed by a camera token, ``intrinsic``, ``img_path``
    from the root) gives the same cameras as the released files' form."""
    import shutil

    from occtrain.data.layout import DatasetIndex

    copy = tmp_path / "world"
    shutil.copytree(world, copy)
    ann = json.loads((copy / "annotations.json").read_text())
    for samples in ann["scene_infos"].values():
        for token, info in samples.items():
            info["camera_sensor"] = {
                f"{token}-{name.lower()}": {
                    "img_path": f"imgs/{r['img_path']}",
                    "intrinsic": r["intrinsics"],
                    "extrinsic": r["extrinsic"],
                    "ego_pose": r["ego_pose"],
                }
                for name, r in info["camera_sensor"].items()
            }
    (copy / "annotations.json").write_text(json.dumps(ann))
    released, readme = DatasetIndex.open(world), DatasetIndex.open(copy)
    scene, token = next(released.samples("val"))
    assert readme.has_cameras
    for a, b in zip(released.cameras(scene, token), readme.cameras(scene, token)):
        assert a.name == b.name and a.image.relative_to(world) == b.image.relative_to(copy)
        assert np.array_equal(a.intrinsic, b.intrinsic) and np.array_equal(a.cam_to_ego, b.cam_to_ego)
    assert np.array_equal(readme.images(scene, token), released.images(scene, token))


def test_shards_carry_the_views_only_to_stages_that_read_them(world, tmp_path):
    from occtrain.data.datamodule import COLLATE
    from occtrain.data.layout import DatasetIndex
    from occtrain.data.shards import make_pipeline, shard_urls, write_shards

    write_shards(world, tmp_path / "shards", samples_per_shard=2, history=1, future=1)
    index = DatasetIndex.open(world)
    for kind in ("frames", "clips"):
        urls, total = shard_urls(tmp_path / "shards", kind, "val")
        plain = next(iter(make_pipeline(urls, train=False, total=total)))
        assert not any(k.startswith("cam") for k in plain)  # never decoded
        sample = next(iter(make_pipeline(urls, train=False, total=total, cameras=True)))
        batch = COLLATE[kind]([sample])
        scene = index.scene_of(sample["__key__"])
        assert np.array_equal(batch["images"][0].numpy(), index.images(scene, sample["__key__"]))
        classes, depth = index.camera_targets(scene, sample["__key__"])
        assert np.array_equal(batch["cam_class"][0].numpy(), classes)
        np.testing.assert_allclose(batch["cam_depth"][0].numpy(), depth)
        np.testing.assert_allclose(
            batch["intrinsics"][0, 0].numpy(), index.cameras(scene, sample["__key__"])[0].intrinsic, rtol=1e-6
        )


def test_data_check_names_a_broken_camera_image_and_calibration(world, tmp_path, capsys):
    import shutil

    from occtrain.cli import main
    from occtrain.data.layout import DatasetIndex

    copy = tmp_path / "world"
    shutil.copytree(world, copy)
    index = DatasetIndex.open(copy)
    scene, token = next(index.samples("train"))
    broken = index.cameras(scene, token)[3].image
    broken.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    ann = json.loads((copy / "annotations.json").read_text())
    record = ann["scene_infos"][scene][token]["camera_sensor"]["CAM_FRONT"]
    record["intrinsics"][0][2] = 5000.0  # principal point far outside a 128-pixel-wide image
    (copy / "annotations.json").write_text(json.dumps(ann))
    assert main(["data", "check", str(copy)]) == 1
    out, err = capsys.readouterr()
    assert f"{broken}: not a readable image" in out
    assert (
        f"scene_infos.{scene}.{token}.camera_sensor (CAM_FRONT): intrinsic" in out
        and "does not fit its 128x72 image" in out
    )
    assert err.strip() == f"2 problem(s) in dataset {copy}"

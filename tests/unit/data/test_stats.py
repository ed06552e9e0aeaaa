"""occtrain.data.stats and `occtrain data stats`: voxel statistics pinned on a hand-counted frame."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import write_hand_dataset
from occtrain.cli import main
from occtrain.data.layout import DatasetIndex
from occtrain.data.stats import _Counts, class_rows, dataset_stats, pick_frames, reference_class_shares
from occtrain.errors import DataError
from occtrain.formats.occ3d import CLASS_INDEX, FREE, GRID_SHAPE, OCC3D_TRAIN_VOXELS


def hand_frame() -> dict[str, np.ndarray]:
    """4 occupied voxels in 3 columns: two of car at (0, 0), driveable surface at (1, 0),
    manmade up at layer 5 of (2, 2). The lidar saw those 4 and 4 free voxels; the camera
    saw the two car voxels and one free voxel the lidar did not."""
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[0, 0, 0:2] = CLASS_INDEX["car"]
    sem[1, 0, 0] = CLASS_INDEX["driveable_surface"]
    sem[2, 2, 5] = CLASS_INDEX["manmade"]
    lidar = (sem != FREE).astype(np.uint8)
    lidar[5, 5, 0:4] = 1
    camera = np.zeros(GRID_SHAPE, np.uint8)
    camera[0, 0, 0:2] = 1
    camera[9, 9, 9] = 1
    return {"semantics": sem, "mask_lidar": lidar, "mask_camera": camera}


def test_one_frame_counted_by_hand() -> None:
    counts = _Counts()
    counts.add(hand_frame())
    s = counts.result(Path("x"), "val")
    assert s.frames == 1
    assert s.occupied == pytest.approx(4 / 640_000)
    assert s.occupied_columns == pytest.approx(3 / 40_000) and s.voxels_per_column == pytest.approx(4 / 3)
    assert s.low_layers == pytest.approx(3 / 4)
    assert (
        s.per_layer[0] == pytest.approx(2 / 40_000)
        and s.per_layer[5] == pytest.approx(1 / 40_000)
        and s.per_layer[2] == 0
    )
    assert s.mask_lidar == pytest.approx(8 / 640_000) and s.mask_camera == pytest.approx(3 / 640_000)
    assert s.camera_inside_lidar == pytest.approx(2 / 3)
    assert s.occupied_in_lidar == pytest.approx(4 / 8) and s.occupied_in_camera == pytest.approx(2 / 3)
    assert (
        s.class_shares["car"] == 0.5
        and s.class_shares["driveable_surface"] == 0.25
        and s.class_shares["manmade"] == 0.25
    )
    assert sum(s.class_shares.values()) == pytest.approx(1.0)


def test_shares_are_means_over_frames_and_classes_pooled() -> None:
    counts = _Counts()
    counts.add(hand_frame())
    empty = {k: np.zeros(GRID_SHAPE, np.uint8) for k in ("mask_lidar", "mask_camera")}
    counts.add({"semantics": np.full(GRID_SHAPE, FREE, np.uint8), **empty})
    s = counts.result(Path("x"), "val")
    assert s.occupied == pytest.approx(4 / 640_000 / 2)  # the empty frame counts once
    assert s.low_layers == pytest.approx(3 / 4 / 2)
    assert s.class_shares["car"] == 0.5  # pooled: the empty frame adds no voxel


def test_the_reference_shares_are_the_release_counts() -> None:
    """The figures the issue quotes: driveable surface 32.0 %, vegetation 21.1 %, car 3.0 %."""
    ref = reference_class_shares()
    assert ref["driveable_surface"] == pytest.approx(0.320, abs=5e-4)
    assert ref["vegetation"] == pytest.approx(0.211, abs=5e-4)
    assert ref["car"] == pytest.approx(0.030, abs=5e-4)
    assert len(OCC3D_TRAIN_VOXELS) == 18 and sum(ref.values()) == pytest.approx(1.0)
    assert [r[0] for r in class_rows(_hand_stats())][:3] == ["driveable_surface", "vegetation", "manmade"]


def _hand_stats():
    counts = _Counts()
    counts.add(hand_frame())
    return counts.result(Path("x"), "val")


def test_frames_spread_evenly_over_the_split(tmp_path: Path) -> None:
    index = DatasetIndex.open(write_hand_dataset(tmp_path / "ds", train=1, val=2, frames=5))
    every = list(index.samples("val"))
    assert pick_frames(index, "val", -1) == every and pick_frames(index, "val", 99) == every
    assert pick_frames(index, "val", 4) == [every[0], every[3], every[6], every[9]]
    with pytest.raises(DataError, match="--frames 0: count at least 1 frame"):
        pick_frames(index, "val", 0)


def test_the_command_prints_both_tables_and_writes_what_it_printed(tmp_path: Path, capsys) -> None:
    root = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=4)
    out, chart = tmp_path / "stats.json", tmp_path / "chart.png"
    assert main(["data", "stats", str(root), "--frames", "-1", "--json", str(out), "--chart", str(chart)]) == 0
    printed = capsys.readouterr().out
    assert "occupied share of all voxels" in printed and "Occ3D-nuScenes train" in printed
    saved = json.loads(out.read_text())
    expected = dataset_stats(root, "val", -1)
    assert saved["frames"] == 4 and saved["occupied"] == pytest.approx(expected.occupied)
    assert saved["reference"]["frame"]["occupied"] == 0.061
    assert f"{100 * expected.occupied:.1f} %" in printed
    assert chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

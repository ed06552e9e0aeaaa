"""The baselines every forecast and meta action is scored beside, on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from occtrain.core.scorers import FORECAST_BASELINES, forecast_baselines, last_past_meta_action
from occtrain.data.clips import Clip
from occtrain.data.geometry import moved_scene
from occtrain.data.meta_actions import MetaActionConfig, past_labels
from occtrain.formats.occ3d import CLASS_INDEX, FRAME_DT, FREE, MOVABLE_CLASSES, VOXEL_SIZE
from occtrain.metrics import ForecastMetric

CAR, ROAD = CLASS_INDEX["car"], CLASS_INDEX["driveable_surface"]


def test_a_moved_scene_shows_what_was_ahead_one_voxel_nearer_and_free_at_the_far_edge():
    scene = torch.full((6, 5, 2), FREE, dtype=torch.long)
    scene[4, 2, 0] = CAR  # 2 voxels ahead of index 2
    scene[0, 1, 1] = ROAD  # at the back edge: leaves the view when the ego drives on
    moved = moved_scene(scene, (VOXEL_SIZE, 0.0))  # one voxel forward
    assert moved[3, 2, 0] == CAR and moved[4, 2, 0] == FREE
    assert (moved[-1] == FREE).all()  # beyond the old grid
    assert int((moved != FREE).sum()) == 1  # the road cell at x index 0 left the view
    left = moved_scene(scene, (0.0, 2 * VOXEL_SIZE))  # two voxels to the left: things move right
    assert left[4, 0, 0] == CAR
    assert torch.equal(moved_scene(scene, (0.0, 0.0)), scene)
    assert (moved_scene(scene, (100.0, 0.0)) == FREE).all()


def test_forecast_baselines_copy_paste_the_reconstruction_and_move_the_exact_scene_at_the_ego_speed():
    current = torch.full((50, 4, 2), FREE, dtype=torch.long)
    current[30, 2, 0] = CAR
    reconstruction = torch.full_like(current, ROAD)
    speed = 2 * VOXEL_SIZE / FRAME_DT  # two voxels a frame
    prior = torch.full_like(current, ROAD)
    prior[0, 0, 0] = CAR
    through = []  # what went through the scene encoder: the moved scenes at the scored steps only

    def tokenizer(labels: torch.Tensor) -> torch.Tensor:
        through.append(labels.clone())
        return torch.where(labels == CAR, ROAD, labels)  # a tokenizer that loses cars

    out = forecast_baselines(
        current, reconstruction, {"ego_speed": speed}, steps=3, prior=prior, through=tokenizer, scored=[0, 2]
    )
    assert set(out) == set(FORECAST_BASELINES) - {
        "baseline_true_future_reconstruction_forecast",
        "baseline_cv_moved_movers_reconstruction_forecast",
    }  # the ceilings need the future
    assert all(v.shape == (1, 3, 50, 4, 2) for v in out.values())
    assert len(through) == 1 and torch.equal(through[0], out["baseline_cv_moved_forecast"][0, [0, 2]])
    moved_reconstruction = out["baseline_cv_moved_reconstruction_forecast"][0]
    assert (moved_reconstruction[1] == FREE).all() and not (moved_reconstruction[[0, 2]] == CAR).any()
    assert all(torch.equal(out["baseline_prior_forecast"][0, t], prior) for t in range(3))  # no input at all
    assert set(forecast_baselines(current, reconstruction, {"ego_speed": speed}, steps=3)) == set(
        FORECAST_BASELINES[:3]
    )
    assert torch.equal(out["baseline_copy_forecast"][0, 2], current)
    assert (out["baseline_copy_reconstruction_forecast"] == ROAD).all()
    for t in range(3):  # after t+1 frames the car is 2 (t+1) voxels nearer
        moved = out["baseline_cv_moved_forecast"][0, t]
        assert moved[30 - 2 * (t + 1), 2, 0] == CAR and int((moved == CAR).sum()) == 1


def test_forecast_movable_miou_is_the_mean_over_the_movable_classes_present_per_horizon():
    target = torch.full((1, 2, 4, 1, 1), FREE, dtype=torch.long)
    target[0, :, 0] = CAR
    target[0, :, 1] = CLASS_INDEX["pedestrian"]
    target[0, :, 2] = ROAD
    pred = target.clone()
    pred[0, 1, 1] = FREE  # the pedestrian missed at the second frame
    m = ForecastMetric(horizons=(0, 1), subsets={"movable": MOVABLE_CLASSES})
    m.update(pred, target)
    out = m.compute()
    assert out["movable_mIoU"]["0.5s"] == 100.0 and out["movable_mIoU"]["1s"] == 50.0  # car 100, pedestrian 0
    assert out["movable_mIoU"]["avg"] == 75.0
    assert float(out["mIoU"]["1s"]) == pytest.approx(
        1600.0 / 17
    )  # occworld: classes absent from both score 100; pedestrian 0
    plain = ForecastMetric(horizons=(0, 1))
    plain.update(pred, target)
    assert "movable_mIoU" not in plain.compute()


def _poses(speeds: list[float]) -> np.ndarray:
    x = np.concatenate([[0.0], np.cumsum(np.asarray(speeds) * FRAME_DT)])
    return np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)


def test_repeating_the_last_past_meta_action_reads_the_poses_up_to_the_anchor_only():
    poses = _poses([10.0] * 5 + [4.0] * 6)  # brakes right after the anchor (frame 5)
    clip = Clip({"anchor": {"token": "t"}, "ego_poses": poses.tolist(), "history": 5}, [], "")
    last = last_past_meta_action(clip)
    assert last == past_labels(poses, 5, 5, MetaActionConfig())[-1]
    assert last["speed"] == "maintain"
    start = Clip({"anchor": {"token": "t"}, "ego_poses": poses.tolist(), "history": 0}, [], "")
    assert last_past_meta_action(start) is None


def test_the_ceilings_are_the_true_future_through_the_tokenizer_and_the_moved_present_with_the_true_agents():
    """What a forecast in the tokenizer's codes can reach: the future through it; and the
    moved present (static world right) with the future's agents pasted in, through it."""
    current = torch.full((50, 4, 2), FREE, dtype=torch.long)
    current[30, 2, 0], current[10, 1, 0] = CAR, ROAD
    future = current[None].repeat(3, 1, 1, 1)
    future[:, 30, 2, 0], future[:, 40, 3, 0] = FREE, CAR  # the car drove off to (40, 3)
    through = []

    def tokenizer(labels: torch.Tensor) -> torch.Tensor:
        through.append(len(labels))
        return labels  # a perfect tokenizer

    out = forecast_baselines(
        current,
        current,
        {"ego_speed": 0.0},  # the ego stands: the moved present is the present
        steps=3,
        through=tokenizer,
        scored=[0, 2],
        future=future,
        future_reconstruction=future,
    )
    assert through == [4]  # the moved and the pasted volumes of both scored steps, in one pass
    pasted = out["baseline_cv_moved_movers_reconstruction_forecast"][0]
    assert torch.equal(pasted[[0, 2]], future[[0, 2]]) and (pasted[1] == FREE).all()
    assert torch.equal(out["baseline_true_future_reconstruction_forecast"][0], future)

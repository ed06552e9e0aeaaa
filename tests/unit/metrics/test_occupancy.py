"""Occupancy and forecasting metrics on hand-computed tiny grids, plus a 2-process DDP run of every metric."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import torch.distributed as dist

from conftest import free_port, two_ranks
from occtrain.formats.occ3d import CLASS_NAMES, FREE
from occtrain.metrics import CaptionMetric, ForecastMetric, OccupancyMetric, PlanningMetric, QAMetric, confusion_matrix


def vol(*labels: int) -> torch.Tensor:
    """A [1, N, 1, 1] label volume: N voxels in a row."""
    return torch.tensor(labels, dtype=torch.long).reshape(1, -1, 1, 1)


# The shared case: voxels v0..v5 as (ground truth -> prediction)
#   v0: car(4) -> car, v1: car -> driveable(11), v2: driveable -> driveable, v3: free -> free,
#   v4: car -> free (outside the camera mask), v5: free -> pedestrian(7) (outside the camera mask)
GT = vol(4, 4, 11, FREE, 4, FREE)
PRED = vol(4, 11, 11, FREE, FREE, 7)
CAMERA = vol(1, 1, 1, 1, 0, 0).bool()


def test_confusion_matrix_counts_pairs_inside_the_mask():
    cm = confusion_matrix(PRED, GT, CAMERA)
    assert cm.sum() == 4
    assert cm[4, 4] == 1 and cm[4, 11] == 1 and cm[11, 11] == 1 and cm[FREE, FREE] == 1


def test_occ3d_masked_hand_case():
    m = OccupancyMetric("occ3d")
    m.update(PRED, GT, CAMERA)
    r = m.compute()
    # inside the mask: car TP=1 FN=1 -> 1/2; driveable TP=1 FP=1 -> 1/2; every other class absent
    # from both sides -> NaN, skipped: mIoU = (50 + 50) / 2 = 50
    assert r["convention"] == "occ3d"
    assert r["per_class"]["car"].item() == pytest.approx(50.0)
    assert r["per_class"]["driveable_surface"].item() == pytest.approx(50.0)
    assert math.isnan(r["per_class"]["pedestrian"].item())
    assert r["mIoU"].item() == pytest.approx(50.0)
    # geometry: occupied v0, v1, v2 on both sides -> 3 / 3
    assert r["IoU"].item() == pytest.approx(100.0)
    assert r["samples"].item() == 1
    assert list(r["per_class"]) == list(CLASS_NAMES[:FREE])


def test_occ3d_unmasked_counts_every_voxel_and_a_class_only_predicted_scores_zero():
    m = OccupancyMetric("occ3d", use_mask=False)
    m.update(PRED, GT)
    r = m.compute()
    # car TP=1 FN=2 -> 1/3; pedestrian TP=0 FP=1 -> 0; driveable 1/2: mIoU = (33.33 + 0 + 50) / 3 = 27.78
    assert r["per_class"]["car"].item() == pytest.approx(100 / 3)
    assert r["per_class"]["pedestrian"].item() == 0.0
    assert r["mIoU"].item() == pytest.approx((100 / 3 + 0 + 50) / 3)
    # geometry: TP = v0, v1, v2; FP = v5; FN = v4 -> 3 / 5
    assert r["IoU"].item() == pytest.approx(60.0)


def test_occworld_absent_ground_truth_class_scores_one_even_when_predicted():
    m = OccupancyMetric("occworld")
    m.update(PRED, GT)
    r = m.compute()
    # car 1/3, driveable 1/2; pedestrian has no ground truth -> 1 although predicted once;
    # the 14 other classes -> 1: mIoU = (1/3 + 1/2 + 15) / 17
    assert r["convention"] == "occworld"
    assert r["per_class"]["pedestrian"].item() == pytest.approx(100.0)
    assert r["mIoU"].item() == pytest.approx(100 * (1 / 3 + 1 / 2 + 15) / 17)
    assert r["IoU"].item() == pytest.approx(60.0)


def test_all_free_scene_is_nan_for_occ3d_and_100_for_occworld():
    free = vol(FREE, FREE, FREE)
    occ3d, occworld = OccupancyMetric("occ3d", use_mask=False), OccupancyMetric("occworld")
    occ3d.update(free, free)
    occworld.update(free, free)
    a, b = occ3d.compute(), occworld.compute()
    assert math.isnan(a["mIoU"].item()) and math.isnan(a["IoU"].item())
    assert b["mIoU"].item() == pytest.approx(100.0) and b["IoU"].item() == pytest.approx(100.0)


def test_counts_accumulate_over_the_dataset_not_per_sample():
    m = OccupancyMetric("occ3d", use_mask=False)
    m.update(vol(4, FREE), vol(4, 4))  # car IoU 1/2 on its own
    m.update(vol(4, FREE), vol(4, FREE))  # car IoU 1 on its own
    # summed: car TP=2 FN=1 -> 2/3 (a per-sample mean would give 3/4)
    assert m.compute()["mIoU"].item() == pytest.approx(200 / 3)
    assert m.compute()["samples"].item() == 2


def test_occupancy_refuses_bad_input():
    with pytest.raises(ValueError, match="occworld convention counts every voxel"):
        OccupancyMetric("occworld").update(PRED, GT, CAMERA)
    with pytest.raises(ValueError, match="needs mask_camera"):
        OccupancyMetric("occ3d").update(PRED, GT)
    with pytest.raises(ValueError, match="outside 0..17"):
        OccupancyMetric("occ3d", use_mask=False).update(vol(18, 0), vol(0, 0))
    with pytest.raises(ValueError, match="differs from target shape"):
        OccupancyMetric("occ3d", use_mask=False).update(vol(1, 2, 3), vol(1, 2))
    with pytest.raises(ValueError, match="unknown convention"):
        OccupancyMetric("semantickitti")


def test_uint8_mask_and_labels_as_the_data_pipeline_gives_them():
    m = OccupancyMetric("occ3d")
    m.update(PRED.to(torch.uint8), GT.to(torch.uint8), CAMERA.to(torch.uint8))
    assert m.compute()["mIoU"].item() == pytest.approx(50.0)


def forecast_case() -> tuple[torch.Tensor, torch.Tensor]:
    """Two voxels (car, free) at every one of 6 future frames; the forecast varies by frame."""
    target = torch.tensor([4, FREE]).reshape(1, 1, 2, 1, 1).repeat(1, 6, 1, 1, 1)
    pred = target.clone()
    pred[0, 3] = FREE  # frame 3 (2 s): the car vanishes
    pred[0, 5] = 4  # frame 5 (3 s): the car grows into the free voxel
    return pred, target


def test_forecast_per_horizon_hand_case():
    pred, target = forecast_case()
    m = ForecastMetric()
    m.update(pred, target)
    r = m.compute()
    # 1 s: perfect -> mIoU 100, IoU 100
    # 2 s: car TP=0 FN=1 -> 0, 16 classes without ground truth -> 1: mIoU = 16/17; IoU 0
    # 3 s: car TP=1 FP=1 -> 1/2: mIoU = (0.5 + 16) / 17; IoU = 1 / 2
    assert r["convention"] == "occworld"
    assert r["mIoU"]["1s"].item() == pytest.approx(100.0)
    assert r["mIoU"]["2s"].item() == pytest.approx(100 * 16 / 17)
    assert r["mIoU"]["3s"].item() == pytest.approx(100 * 16.5 / 17)
    assert r["mIoU"]["avg"].item() == pytest.approx((100 + 100 * 16 / 17 + 100 * 16.5 / 17) / 3)
    assert [r["IoU"][k].item() for k in ("1s", "2s", "3s")] == pytest.approx([100.0, 0.0, 50.0])
    assert r["IoU"]["avg"].item() == pytest.approx(50.0)


def test_forecast_invalid_frames_are_not_counted():
    pred, target = forecast_case()
    other = target.clone()
    other_pred = target.clone()
    other_pred[0, 5] = 0  # garbage at 3 s, but that frame is past the scene's end
    valid = torch.tensor([[True] * 6, [True] * 5 + [False]])
    m = ForecastMetric()
    m.update(torch.cat([pred, other_pred]), torch.cat([target, other]), valid)
    r = m.compute()
    # 3 s sees only the first sample: unchanged from the hand case
    assert r["mIoU"]["3s"].item() == pytest.approx(100 * 16.5 / 17)
    assert r["frames"]["3s"].item() == 1 and r["frames"]["1s"].item() == 2
    # 2 s now sums both samples: car TP=1 FN=1 -> 1/2: mIoU = (0.5 + 16) / 17, IoU = 1/2
    assert r["mIoU"]["2s"].item() == pytest.approx(100 * 16.5 / 17)
    assert r["IoU"]["2s"].item() == pytest.approx(50.0)


def test_forecast_refuses_too_short_forecasts():
    with pytest.raises(ValueError, match="horizon index 5"):
        ForecastMetric().update(
            torch.zeros(1, 4, 2, 1, 1, dtype=torch.long), torch.zeros(1, 4, 2, 1, 1, dtype=torch.long)
        )


# ----------------------------------------------------------------------------- DDP


def ddp_data() -> dict:
    """Five samples for every metric; rank 0 takes the first three, rank 1 the last two."""
    g = torch.Generator().manual_seed(0)
    sem_pred = torch.randint(0, 18, (5, 6, 5, 2), generator=g)
    sem_gt = torch.randint(0, 18, (5, 6, 5, 2), generator=g)
    mask = torch.rand(5, 6, 5, 2, generator=g) > 0.3
    fc_pred = torch.randint(0, 18, (5, 6, 3, 3, 1), generator=g)
    fc_gt = torch.randint(0, 18, (5, 6, 3, 3, 1), generator=g)
    plan_gt = torch.cumsum(torch.rand(5, 6, 2, generator=g) * 3, dim=1)
    plan_pred = plan_gt + torch.randn(5, 6, 2, generator=g)
    plan_mask = torch.ones(5, 6, dtype=torch.bool)
    plan_mask[4, 4:] = False
    agents = [[np.array([[float(plan_gt[b, t, 0]) + 1.0, 1.5, 4.0, 2.0, 0.2]]) for t in range(6)] for b in range(5)]
    qa = (
        ["yes", "no", "2", "car", "yes"],
        ["yes", "yes", 2, "car", "no"],
        ["exist", "exist", "count", "object", "comparison"],
        [0, 1, 0, 1, 0],
    )
    captions = (
        ["a car ahead", "a bus turns", "nothing", "rain", "a car ahead"],
        [["a car is ahead"], ["the bus turns left"], ["empty road"], ["it rains"], ["a car is ahead"]],
        ["s0", "s1", "s2", "s3", "s0"],
    )  # the last repeats s0, as a padding sampler does
    return dict(
        sem=(sem_pred, sem_gt, mask),
        fc=(fc_pred, fc_gt),
        plan=(plan_pred, plan_gt, plan_mask, agents),
        qa=qa,
        cap=captions,
    )


def run_all(rows: slice) -> dict:
    d = ddp_data()
    occ, fc, plan, qa, cap = OccupancyMetric("occ3d"), ForecastMetric(), PlanningMetric(), QAMetric(), CaptionMetric()
    occ.update(*(x[rows] for x in d["sem"]))
    fc.update(*(x[rows] for x in d["fc"]))
    p, g, m, a = d["plan"]
    plan.update(p[rows], g[rows], m[rows], a[rows])
    qa.update(*(x[rows] for x in d["qa"]))
    cap.update(*(x[rows] for x in d["cap"]))
    results = {"occ": occ.compute(), "fc": fc.compute(), "plan": plan.compute(), "qa": qa.compute()}
    results["cap"] = cap.samples()
    idle = CaptionMetric()  # only the first three samples: on two processes, rank 1 never updates
    if rows.start == 0:
        idle.update(*(x[:3] for x in d["cap"]))
    results["cap_idle"] = idle.samples()
    # Metrics only some processes update (fewer items than ranks): every process must still
    # join each compute, or the others wait for ever.
    from torchmetrics import MeanMetric

    from occtrain.metrics import compute_metrics

    some = {"plan_first_three": PlanningMetric(), "mean": MeanMetric(), "never": MeanMetric()}
    if rows.start == 0:
        some["plan_first_three"].update(p[:3], g[:3], m[:3], a[:3])
    some["mean"].update(torch.arange(rows.start, rows.stop, dtype=torch.float32))
    results["some_ranks"] = compute_metrics("val", some)
    from occtrain.commands.score import to_json

    return to_json(results)


def _worker(rank: int, port: int, out: str) -> None:
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    try:
        result = run_all(slice(0, 3) if rank == 0 else slice(3, 5))
        if rank == 0:
            with open(out, "w") as fh:
                json.dump(result, fh)
    finally:
        dist.destroy_process_group()


def assert_same(a, b, path: str = "") -> None:
    """Equal trees; floats to 1e-12 relative (a sum over two processes adds in another order), the rest exactly."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            assert_same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-12, abs=1e-12), path
    else:
        assert a == b, path


def test_two_process_ddp_equals_single_process(tmp_path):
    out = tmp_path / "ddp.json"
    two_ranks(_worker, free_port(), str(out))
    ddp = json.loads(out.read_text())
    single = json.loads(json.dumps(run_all(slice(0, 5))))
    assert_same(ddp, single)
    assert ddp["occ"]["samples"] == 5 and ddp["plan"]["samples"] == 5 and ddp["qa"]["questions"] == 5
    assert sorted(ddp["cap"]) == ["s0", "s1", "s2", "s3"]  # the repeated s0 counts once
    assert "val/never" not in ddp["some_ranks"] and ddp["some_ranks"]["val/mean"] == 2.0
    assert ddp["some_ranks"]["val/plan_first_three_samples"] == 3
    assert sorted(ddp["cap_idle"]) == ["s0", "s1", "s2"]


def test_the_movable_class_miou_averages_the_classes_that_occur():
    """Three car voxels, two found and one missed, one free voxel called a car: car IoU 2 / 4.
    Pedestrians occur on neither side and do not count (OccWorld's mIoU would score them 100)."""
    from occtrain.formats.occ3d import CLASS_INDEX

    gt = torch.full((1, 2, 2, 2), FREE)
    gt[0, 0, 0, 0] = gt[0, 0, 0, 1] = gt[0, 0, 1, 0] = CLASS_INDEX["car"]
    pred = torch.full_like(gt, FREE)
    pred[0, 0, 0, 0] = pred[0, 0, 0, 1] = pred[0, 1, 1, 1] = CLASS_INDEX["car"]
    metric = OccupancyMetric("occworld", subsets={"movable": ("car", "pedestrian")})
    metric.update(pred, gt)
    assert float(metric.compute()["movable_mIoU"]) == pytest.approx(50.0)
    empty = OccupancyMetric("occworld", subsets={"movable": ("pedestrian",)})
    empty.update(pred, gt)
    assert torch.isnan(empty.compute()["movable_mIoU"])

"""SparseOccVLA's parts by hand: point-set losses and voxelization, projection and the
distillation's sampling, spatial-aware attention, the forecaster, the world model's
sequence, the DDIM planner, the OmniDrive reader."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from builders import write_omnidrive
from occtrain.data.cameras import nuscenes_rig
from occtrain.errors import ConfigError, DataError
from occtrain.formats.occ3d import FREE, GRID_SHAPE
from occtrain.models.point_sets import chamfer_distance, occupied_points, sigmoid_focal_loss, voxel_centres, voxelize
from occtrain.models.projection import project, sample_views

# ----------------------------------------------------------------------------- point sets


def test_chamfer_distance_by_hand():
    """pred {(0,0,0), (2,0,0)} and gt {(1,0,0), (5,0,0)}: pred -> gt nearest squared distances
    1 and 1; gt -> pred 1 and 9. Sum 12; mean 1 + 5 = 6. A padded gt point is ignored."""
    pred = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]]], requires_grad=True)
    gt = torch.tensor([[[1.0, 0, 0], [5.0, 0, 0], [100.0, 0, 0]]])
    valid = torch.tensor([[True, True, False]])
    total, match = chamfer_distance(pred, gt, valid, reduction="sum")
    assert total.item() == pytest.approx(12.0)
    assert match.tolist() == [[0, 0]]  # both predicted points' nearest real gt point is (1, 0, 0)
    mean, _ = chamfer_distance(pred, gt, valid, reduction="mean")
    assert mean.item() == pytest.approx(6.0)
    total.backward()
    # d/dp of (p - g)^2 summed over the pairs each point is in. p0 = 0: its own pair with g0
    # (1) and g0's pair with it (g0 is 1 from both points; the first wins) -> -2 - 2. p1 = 2:
    # its pair with g0 and g1's (5) with it -> 2 * (2 - 1) + 2 * (2 - 5).
    assert pred.grad[0, :, 0].tolist() == pytest.approx([-4.0, -4.0])


def test_sigmoid_focal_loss_by_hand():
    """Two classes, logits (0, 0) and label 0: each sigmoid is 1/2, so each class gives
    alpha_t * (1/2)^2 * log 2 with alpha_t 0.25 for the true class and 0.75 for the other."""
    loss = sigmoid_focal_loss(torch.zeros(1, 2), torch.tensor([0]), alpha=0.25, gamma=2.0)
    assert loss.item() == pytest.approx((0.25 + 0.75) * 0.25 * math.log(2))
    # A confident right answer costs almost nothing; gamma = 0 is plain weighted BCE.
    assert sigmoid_focal_loss(torch.tensor([[9.0, -9.0]]), torch.tensor([0])).item() < 1e-6
    bce = sigmoid_focal_loss(torch.zeros(1, 2), torch.tensor([1]), alpha=0.5, gamma=0.0)
    assert bce.item() == pytest.approx(2 * 0.5 * math.log(2))


def test_points_voxelize_exactly():
    centres = voxel_centres(torch.tensor([[0, 0, 0], [10, 20, 3], [10, 20, 3], [10, 20, 3], [199, 199, 15]]))
    outside = torch.tensor([[50.0, 0.0, 0.0]])  # beyond the grid's 40 m
    labels = voxelize(torch.cat([centres, outside]), torch.tensor([4, 1, 2, 2, 16, 3]))
    assert labels.shape == GRID_SHAPE
    assert labels[0, 0, 0] == 4 and labels[199, 199, 15] == 16
    assert labels[10, 20, 3] == 2  # two votes for class 2 beat one for class 1
    assert int((labels != FREE).sum()) == 3
    tie = voxelize(voxel_centres(torch.tensor([[5, 5, 5], [5, 5, 5]])), torch.tensor([7, 3]))
    assert tie[5, 5, 5] == 3  # a tie goes to the lowest class
    box = voxelize(voxel_centres(torch.tensor([[100, 100, 8]])), torch.tensor([11]), extent=(3, 3, 1))
    filled = (box != FREE).nonzero().tolist()
    assert filled == [[x, y, 8] for x in (99, 100, 101) for y in (99, 100, 101)]


def test_occupied_points_are_voxel_centres_of_the_labels():
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[3, 4, 5], sem[100, 50, 2] = 4, 11
    points, classes, n = occupied_points(sem, 5, np.random.default_rng(0))
    assert n == 2 and points.shape == (5, 3)
    got = {
        tuple(np.floor((p.numpy() + [40, 40, 1]) / 0.4).astype(int)): int(c) for p, c in zip(points[:n], classes[:n])
    }
    assert got == {(3, 4, 5): 4, (100, 50, 2): 11}


def test_kept_classes_are_all_drawn_before_the_rest():
    """A uniform draw of 50 of 10,003 voxels would keep a 3-voxel car about once in 70 draws;
    with its class kept every car voxel is in, and the rest of the budget is drawn."""
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[:100, :100, 0] = 11  # 10,000 road voxels
    sem[150, 150, :3] = 4  # a 3-voxel car
    points, classes, n = occupied_points(sem, 50, np.random.default_rng(0), keep=(4,))
    assert n == 50 and int((classes == 4).sum()) == 3 and int((classes == 11).sum()) == 47
    uniform = occupied_points(sem, 50, np.random.default_rng(0))[1]
    assert int((uniform == 4).sum()) < 3
    only_cars = occupied_points(sem, 2, np.random.default_rng(0), keep=(4,))[1]
    assert only_cars.tolist() == [4, 4]  # more kept voxels than the budget: drawn among them
    shared = occupied_points(sem, 20, np.random.default_rng(0), keep=(4,), keep_share=0.1)[1]
    assert int((shared == 4).sum()) == 2  # at most a tenth of the budget goes to them first


# ----------------------------------------------------------------------------- cameras


def _rig(batch: int = 1) -> tuple[torch.Tensor, torch.Tensor, list]:
    cams = nuscenes_rig(72, 128)
    intr = torch.tensor(np.stack([c.intrinsic for c in cams]), dtype=torch.float32)[None].expand(batch, -1, -1, -1)
    to_ego = torch.tensor(np.stack([c.cam_to_ego for c in cams]), dtype=torch.float32)[None].expand(batch, -1, -1, -1)
    return intr, to_ego, cams


def test_projection_matches_the_numpy_cameras():
    intr, to_ego, cams = _rig()
    points = torch.tensor([[[10.0, 1.0, 0.5], [-8.0, 3.0, 1.0], [2.0, -9.0, 0.0], [0.0, 0.0, 30.0]]])
    uv, inside = project(points, intr, to_ego, (72, 128))
    for v, cam in enumerate(cams):
        ref_uv, _, ref_inside = cam.project(points[0].double().numpy())
        assert inside[0, v].tolist() == ref_inside.tolist()
        np.testing.assert_allclose(uv[0, v][inside[0, v]].numpy(), ref_uv[ref_inside], rtol=1e-4, atol=1e-3)


def test_distillation_reads_the_teacher_feature_where_a_point_projects():
    """A point lifted from the centre of CAM_FRONT's patch (row 4, col 9) reads that patch's
    feature exactly; a point no camera sees reads zeros."""
    intr, to_ego, cams = _rig()
    gh, gw = 9, 16
    rows, cols = torch.meshgrid(
        torch.arange(gh, dtype=torch.float32), torch.arange(gw, dtype=torch.float32), indexing="ij"
    )
    features = torch.zeros(1, 6, 3, gh, gw)
    features[:, :, 0], features[:, :, 1] = rows, cols
    features[:, :, 2] = torch.arange(6, dtype=torch.float32)[:, None, None]  # which camera
    centre = ((9 + 0.5) * 128 / gw, (4 + 0.5) * 72 / gh)  # pixel (u, v) of the patch centre
    point = cams[0].lift(np.array([centre]), np.array([12.0]))
    uv, inside = project(torch.tensor(point, dtype=torch.float32)[None], intr, to_ego, (72, 128))
    sampled, seen = sample_views(features, uv, inside, (72, 128))
    assert inside[0, :, 0].tolist() == [True, False, False, False, False, False]  # the front camera alone sees it
    assert sampled[0, 0].tolist() == pytest.approx([4.0, 9.0, 0.0], abs=1e-4)
    assert bool(seen[0, 0])
    nowhere, seen = sample_views(
        features, *project(torch.tensor([[[0.0, 0.0, 500.0]]]), intr, to_ego, (72, 128)), (72, 128)
    )
    assert not bool(seen[0, 0]) and nowhere.abs().sum() == 0


def test_the_surface_cue_says_where_a_point_meets_the_pixels_predicted_depth():
    """A point lifted 12 m along CAM_FRONT's ray through a cell whose predicted depth is
    12 m and whose class is car reads a gap of 0 and car; 6 m along the same ray it reads
    log(6/12), in front of the surface; a point no camera sees reads zeros."""
    from occtrain.families.sparseoccvla.encoder import surface_cue
    from occtrain.formats.occ3d import CLASS_INDEX, NUM_CLASSES

    intr, to_ego, cams = _rig()
    gh, gw = 9, 16
    dense = torch.zeros(1, 6, NUM_CLASSES + 1, gh, gw)
    dense[:, :, CLASS_INDEX["car"]] = 20.0  # every pixel: certainly a car
    dense[:, :, NUM_CLASSES] = math.log(12.0)  # at 12 m
    centre = np.array([((9 + 0.5) * 128 / gw, (4 + 0.5) * 72 / gh)])
    points = torch.tensor(
        np.concatenate([cams[0].lift(centre, np.array([12.0])), cams[0].lift(centre, np.array([6.0])), [[0, 0, 500]]]),
        dtype=torch.float32,
    )[None]
    uv, inside = project(points, intr, to_ego, (72, 128))
    cue = surface_cue(points, dense, to_ego, uv, inside, (72, 128))
    assert cue.shape == (1, 3, NUM_CLASSES + 1)
    assert cue[0, 0, CLASS_INDEX["car"]] == pytest.approx(1.0, abs=1e-6)
    assert cue[0, 0, NUM_CLASSES] == pytest.approx(0.0, abs=1e-4)
    assert cue[0, 1, NUM_CLASSES] == pytest.approx(math.log(0.5), abs=1e-4)
    assert cue[0, 2].abs().sum() == 0


def test_the_dense_loss_reads_each_cells_centre_pixel():
    """A 2 x 2 map over a 4 x 4 image is scored against pixels (1, 1), (1, 3), (3, 1) and
    (3, 3): a map that is right there (whatever the other pixels hold) scores near 0, one
    with every depth doubled scores log 2 more; sky pixels (depth 0) carry no depth loss."""
    from occtrain.families.sparseoccvla.encoder import dense_loss
    from occtrain.formats.occ3d import NUM_CLASSES

    cam_class = torch.full((1, 1, 4, 4), 3, dtype=torch.uint8)  # the pixels read are overwritten below
    cam_depth = torch.full((1, 1, 4, 4), 99.0)
    for (r, c), (k, d) in zip([(1, 1), (1, 3), (3, 1), (3, 3)], [(0, 5.0), (4, 10.0), (11, 20.0), (17, 0.0)]):
        cam_class[0, 0, r, c], cam_depth[0, 0, r, c] = k, d
    right = torch.zeros(1, 1, NUM_CLASSES + 1, 2, 2)
    for (i, j), (k, d) in zip([(0, 0), (0, 1), (1, 0), (1, 1)], [(0, 5.0), (4, 10.0), (11, 20.0), (17, 1.0)]):
        right[0, 0, k, i, j] = 50.0
        right[0, 0, NUM_CLASSES, i, j] = math.log(d)
    assert dense_loss(right, cam_class, cam_depth).item() == pytest.approx(0.0, abs=1e-6)
    doubled = right.clone()
    doubled[:, :, NUM_CLASSES] += math.log(2.0)
    assert dense_loss(doubled, cam_class, cam_depth).item() == pytest.approx(math.log(2.0), abs=1e-5)


# ----------------------------------------------------------------------------- attention and forecaster


def test_spatial_aware_attention_by_hand():
    """A_ij = q_i . k_j / sqrt(d) - tau_i ||p_i - p_j||, with identity projections and tau_i = softplus(0)."""
    from occtrain.families.sparseoccvla.encoder import SpatialSelfAttention

    attn = SpatialSelfAttention(dim=2, heads=1)
    with torch.no_grad():
        attn.qkv.weight.copy_(torch.cat([torch.eye(2)] * 3))
        attn.qkv.bias.zero_()
        attn.tau.weight.zero_()
        attn.tau.bias.zero_()
    q = torch.tensor([[[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]]])
    pos = torch.tensor([[[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]])
    logits, values = attn.logits(q, pos)
    tau = math.log(2.0)  # softplus(0)
    dist = torch.tensor([[0.0, 5.0, 1.0], [5.0, 0.0, math.sqrt(26)], [1.0, math.sqrt(26), 0.0]])
    expected = q[0] @ q[0].T / math.sqrt(2) - tau * dist
    assert torch.allclose(logits[0, 0], expected, atol=1e-5)
    assert torch.equal(values[0, 0], q[0])
    # Nearer queries get more weight at equal similarity: query 0's two neighbours have q . k = 0 and 1.
    weights = logits[0, 0].softmax(-1)
    assert weights[0, 2] > weights[0, 1]


def test_forecaster_recursion_and_ego_embedding():
    from occtrain.families.sparseoccvla.config import SparseOccVLAWorldConfig
    from occtrain.families.sparseoccvla.world_model import EGO_FEATURES, Forecaster

    torch.manual_seed(0)
    cfg = SparseOccVLAWorldConfig(forecast_frames=3)
    fc = Forecaster(hidden=16, dim=8, heads=2, ffn=16, points=4, scale=2.0, cfg=cfg)
    llm_out, q, p = torch.randn(2, 5, 16), torch.randn(2, 5, 8), torch.randn(2, 5, 3) * 10
    ego = torch.randn(2, EGO_FEATURES)
    steps = fc(llm_out, q, p, ego)
    assert len(steps) == 3
    for points, logits in steps:
        assert points.shape == (2, 20, 3) and logits.shape == (2, 20, 17)
    # Each frame's points lie within the head's reach of the previous frame's query positions.
    first = steps[0][0].view(2, 5, 4, 3)
    assert ((first - p[:, :, None]).abs() <= 2.0 + 1e-5).all()
    second = steps[1][0].view(2, 5, 4, 3)
    assert ((second - first.mean(2, keepdim=True)).abs() <= 2.0 + 1e-5).all()
    sum(s[0].sum() + s[1].sum() for s in steps).backward()
    missing = [n for n, param in fc.named_parameters() if param.grad is None or not param.grad.abs().sum() > 0]
    assert not missing, missing
    # The ego state changes the forecast (it is added at every step).
    again = fc(llm_out, q, p, ego + 1.0)
    assert not torch.allclose(again[-1][0], steps[-1][0])
    # Without the residual token the LLM's outputs are not read.
    fc2 = Forecaster(16, 8, 2, 16, 4, 2.0, SparseOccVLAWorldConfig(forecast_frames=1, residual_token=False))
    torch.testing.assert_close(fc2(llm_out, q, p, ego)[0][0], fc2(llm_out * 0, q, p, ego)[0][0])


def test_a_moved_base_steps_back_by_the_egos_constant_velocity_step_before_each_frame():
    """``moved_base``: frame t's points are decoded around the base moved back by the ego's
    constant-velocity step (velocity times 0.5 s): the static world as the next ego sees it."""
    from occtrain.families.sparseoccvla.config import SparseOccVLAWorldConfig
    from occtrain.families.sparseoccvla.world_model import EGO_FEATURES, Forecaster

    torch.manual_seed(0)
    fc = Forecaster(16, 8, 2, 16, 4, 2.0, SparseOccVLAWorldConfig(forecast_frames=2, moved_base=True))
    bases = []
    fc.head.register_forward_hook(lambda module, args, out: bases.append(args[1].detach().clone()))
    p = torch.randn(1, 5, 3) * 10
    ego = torch.zeros(1, EGO_FEATURES)
    ego[0, :2] = torch.tensor([0.8, -0.2])  # 8 m/s forward, 2 m/s to the right (features are / 10)
    steps = fc(torch.randn(1, 5, 16), torch.randn(1, 5, 8), p, ego)
    step = torch.tensor([4.0, -1.0, 0.0])  # a frame's 0.5 s of it
    torch.testing.assert_close(bases[0], p - step)
    torch.testing.assert_close(bases[1], steps[0][0].view(1, 5, 4, 3).mean(2) - step)
    still = Forecaster(16, 8, 2, 16, 4, 2.0, SparseOccVLAWorldConfig(forecast_frames=1))
    assert torch.equal(still.base_shift(ego), torch.zeros(1, 1, 3))


# ----------------------------------------------------------------------------- the planner


def test_ddim_two_steps_equal_the_scheduler_stepped_by_hand():
    from occtrain.families.sparseoccvla.anchor_diffusion import (
        AnchorDiffusionConfig,
        ddim_denoise,
        ddim_scheduler,
        step_spacing,
    )

    cfg = AnchorDiffusionConfig(noise_timestep=30, denoise_steps=2)
    scheduler = ddim_scheduler(cfg)
    torch.manual_seed(0)
    x0 = torch.randn(2, 18, 6, 2)
    x = scheduler.add_noise(x0, torch.randn_like(x0), torch.tensor([30, 30]))
    target = torch.randn_like(x0)  # what the stub decoder always predicts as the clean sample

    spacing = step_spacing(30, 2, 1000)
    got, calls = ddim_denoise(scheduler, x, 30, spacing, 1000, lambda xt, t: (target, t))
    assert spacing == 15 and calls == 15  # the last step ran at t = 15

    a = scheduler.alphas_cumprod.double()
    ref = x.double()
    for t, prev in ((30, 15), (15, 0)):
        eps = (ref - a[t].sqrt() * target.double()) / (1 - a[t]).sqrt()
        ref = a[prev].sqrt() * target.double() + (1 - a[prev]).sqrt() * eps
    torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=1e-5)
    with pytest.raises(ConfigError, match="noise_timestep"):
        step_spacing(30, 4, 1000)


def stub_planner(dataset, tmp_path, **settings):
    """A tiny planner over a stub world model (hidden 8, query rows 6), and three val clips
    whose decisions are random, as the frozen world model's cache would hold them."""
    from occtrain.data.clips import frame_clips
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.sparseoccvla.anchor_diffusion import AnchorDiffusionConfig, AnchorDiffusionPlanner
    from occtrain.formats.occ3d import FUTURE_STEPS

    cfg = AnchorDiffusionConfig(anchors=3, dim=16, heads=2, layers=1, decision_tokens=4, **settings)
    world = SimpleNamespace(hidden_size=8, query_dim=6)
    torch.manual_seed(0)
    planner = AnchorDiffusionPlanner(cfg, SimpleNamespace(world=world), str(dataset), tmp_path)
    clips = list(frame_clips(DatasetIndex.open(dataset), "val", 0, FUTURE_STEPS, partial_history=False))[:3]
    for c in clips:
        planner._decisions[c.anchor["token"]] = {
            "reason": torch.randn(4, 8),
            "mask": torch.tensor([1, 1, 0, 0]).bool(),
            "scene": torch.randn(5, 9),
        }
    return planner, clips


def test_planner_returns_the_top_scored_anchors_trajectory(synth_dataset, tmp_path):
    planner, clips = stub_planner(synth_dataset, tmp_path)
    plan, top, logits = planner.plan(clips)
    best = logits.argmax(-1)
    assert torch.equal(top, planner.anchors[best])
    # The plan is the chosen anchor's denoised trajectory: close to that anchor (a truncated
    # diffusion starts near it), and equal to re-running with that anchor's row picked by hand.
    again = planner.plan(clips)[0]
    torch.testing.assert_close(plan, again)
    # A clip's plan does not depend on the batch it is planned in.
    torch.testing.assert_close(planner.plan(clips[1:2])[0][0], plan[1])
    torch.testing.assert_close(planner.plan(clips[::-1])[0], plan.flip(0))
    loss = planner.training_loss(clips)
    loss.backward()
    missing = [n for n, p in planner.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, missing


def test_plan_prior_writes_anchors_and_plans_as_offsets_from_constant_velocity(synth_dataset, tmp_path):
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.sparseoccvla.anchor_diffusion import AnchorDiffusionConfig, kmeans_anchors
    from occtrain.models.planning_heads import constant_velocity

    index = DatasetIndex.open(synth_dataset)
    whole, offsets = kmeans_anchors(index, 3), kmeans_anchors(index, 3, prior="constant_velocity")
    # The synthetic ego mostly keeps its speed: offsets from constant velocity are far
    # smaller than the trajectories (which run 10-20 m out at 3 s).
    assert np.abs(offsets).max() < np.abs(whole).max() / 2

    planner, clips = stub_planner(synth_dataset, tmp_path, plan_prior="constant_velocity")
    np.testing.assert_array_equal(planner.anchors.numpy(), offsets)
    _, top, logits = planner.plan(clips)
    cv = constant_velocity([c.anchor for c in clips])
    # The top anchor is its offsets added to the clip's constant-velocity plan.
    torch.testing.assert_close(top, planner.anchors[logits.argmax(-1)] + cv)
    planner.training_loss(clips).backward()
    with pytest.raises(ConfigError, match="plan_prior"):
        AnchorDiffusionConfig(plan_prior="ballistic").validate("stages.planner")


def test_kmeans_anchors_cover_the_training_trajectories(synth_dataset):
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.sparseoccvla.anchor_diffusion import kmeans_anchors

    index = DatasetIndex.open(synth_dataset)
    anchors = kmeans_anchors(index, 3)
    assert anchors.shape == (3, 6, 2)
    np.testing.assert_array_equal(anchors, kmeans_anchors(index, 3))  # deterministic
    with pytest.raises(ConfigError, match="fewer than model.anchors"):
        kmeans_anchors(index, 10_000)


# ----------------------------------------------------------------------------- OmniDrive


def test_omnidrive_reader_reads_the_released_layout(tmp_path):
    from occtrain.families.sparseoccvla.omnidrive import OmniDriveText

    write_omnidrive(tmp_path, {"tok_a": "train", "tok_b": "val"})
    text = OmniDriveText(tmp_path)
    assert text.description("tok_b") == "A quiet street number 1 with parked cars."
    assert text.pairs("tok_a") == [
        {"question": "Is the road clear?", "answer": "Yes, clear 0."},
        {"question": "What is ahead?", "answer": "A parked car."},
    ]
    assert text.driving_action("tok_a") == "Keep going straight."
    assert text.description("unknown") is None and text.pairs("unknown") == []
    (tmp_path / "desc" / "val" / "tok_b.json").write_text('{"text": 1}')
    with pytest.raises(DataError, match="tok_b.json"):
        text.description("tok_b")
    with pytest.raises(DataError, match="not an OmniDrive-nuScenes root"):
        OmniDriveText(tmp_path / "desc" / "train")


def test_tasks_read_omnidrive_text_beside_the_worlds(synth_dataset, tmp_path):
    from occtrain.data.clips import Text, frame_clips
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.sparseoccvla.tasks import TASKS, TaskConfig

    index = DatasetIndex.open(synth_dataset)
    clips = list(frame_clips(index, "train", 0, 6, partial_history=False))
    write_omnidrive(tmp_path, {clips[0].anchor["token"]: "train"})
    cfg = TaskConfig(omnidrive=str(tmp_path))
    rng = np.random.default_rng(0)
    # A frame OmniDrive describes takes its description; the others keep the world's caption.
    assert TASKS["caption"].build(clips[0], cfg, rng)[-1] == Text("A quiet street number 0 with parked cars.", True)
    assert TASKS["caption"].build(clips[1], cfg, rng)[-1] == Text(clips[1].anchor["caption"], True)
    pairs = TASKS["conversation"].every_item(clips[0], cfg)
    assert [p[-1].text for p in pairs] == ["Yes, clear 0.", "A parked car."]
    assert TASKS["conversation"].build(clips[1], cfg, rng) is None  # OmniDrive has no text for it
    assert TASKS["conversation"].build(clips[0], TaskConfig(), rng) is None  # no OmniDrive root


# ----------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    ("key", "value", "says"),
    [
        ("points_per_layer", [], "points_per_layer"),
        ("dim", 30, "dim: 30 must be divisible"),
        ("voxel_extent", [1, 1], "voxel_extent"),
        ("queries", 0, "queries: 0 must be at least 1"),
    ],
)
def test_encoder_settings_are_refused_in_one_line(key, value, says):
    from occtrain.families.sparseoccvla.config import SparseOccConfig

    with pytest.raises(ConfigError, match=says):
        SparseOccConfig(**{key: value}).validate("model.sparseocc")


# ----------------------------------------------------------------------------- the world model


@pytest.fixture(scope="module")
def sparse_world():
    """A tiny SparseOccVLA world model over an untrained encoder (4 queries, 2 global tokens)."""
    from occtrain.config.llm import LLMConfig
    from occtrain.core.lm_world_model import WorldInputs
    from occtrain.core.vocab import JointVocab
    from occtrain.families.sparseoccvla.config import SparseOccConfig, SparseOccVLAWorldConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder
    from occtrain.families.sparseoccvla.scene_encoder import SparseSceneEncoder
    from occtrain.families.sparseoccvla.world_model import SparseOccVLAWorldModel
    from occtrain.models.llm import build_llm
    from occtrain.models.text_tokenizer import train_text_tokenizer

    torch.manual_seed(0)
    enc_cfg = SparseOccConfig(
        queries=4, dim=8, heads=2, points_per_layer=[2, 3], token_dim=32, gt_points=16, mixing_groups=2
    )
    scene = SparseSceneEncoder(SparseOccEncoder(enc_cfg))
    llm_cfg = LLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64)
    inputs = WorldInputs(scene)
    world_cfg = SparseOccVLAWorldConfig(global_queries=2, forecast_frames=2)
    vocab = JointVocab(
        train_text_tokenizer(["describe the scene", "forecast now", "yes no"] * 5, 200),
        llm_cfg=llm_cfg,
        **SparseOccVLAWorldModel.vocab_layout(inputs, world_cfg),
    )
    return SparseOccVLAWorldModel.create(build_llm(llm_cfg, len(vocab)), vocab, inputs, "next_scene", world_cfg)


class _Voxels:
    """What the builder reads future frames' labels from (the engine's ``voxels`` input)."""

    def read(self, name: str, token: str) -> torch.Tensor:
        assert name == "voxels"
        sem = torch.full(GRID_SHAPE, FREE, dtype=torch.uint8)
        sem[100 + len(token), 100, 2] = 4
        sem[90, 95:99, 3] = 11
        return sem


def _sequence(world, rows, forecast: bool):
    from occtrain.data.clips import Scene, Text
    from occtrain.families.sparseoccvla.world_model import Ego, Forecast

    parts = [Scene(0), Ego(tuple(float(i) for i in range(10))), Text("forecast now")]
    parts += [Forecast(("t1", "t22"))] if forecast else [Text("yes", True)]
    b = world.builder()
    for part in parts:
        b.lay(part, _Voxels(), {0: rows})
    return b.build()


def test_the_sequence_is_occupancy_then_global_then_ego_tokens(sparse_world):
    from occtrain.families.sparseoccvla.world_model import EGO, global_token

    v = sparse_world.vocab
    seq = _sequence(sparse_world, torch.randn(4, 11), forecast=False)
    ids = seq.input_ids.tolist()
    assert ids[1:5] == list(range(v.occ_start, v.occ_start + 4))
    assert ids[5:8] == [v.extra_id(global_token(0)), v.extra_id(global_token(1)), v.extra_id(EGO)]
    assert seq.payload["scene"].shape == (len(ids), 3 + 8) and seq.payload["ego"][7].tolist() == list(range(10))


def test_global_tokens_read_their_own_sequences_occupancy_tokens(sparse_world):
    """Two sequences in one batch: changing one's scene rows changes its global tokens'
    embeddings, and not the other's."""
    from occtrain.core.builder import batch_payload, collate

    torch.manual_seed(1)
    a, b = torch.randn(4, 11), torch.randn(4, 11)
    batch = collate([_sequence(sparse_world, a, False), _sequence(sparse_world, b, False)], sparse_world.vocab.pad_id)
    emb = sparse_world.embed(batch["input_ids"], batch_payload(batch))
    changed = collate(
        [_sequence(sparse_world, a + 1.0, False), _sequence(sparse_world, b, False)], sparse_world.vocab.pad_id
    )
    emb2 = sparse_world.embed(changed["input_ids"], batch_payload(changed))
    assert not torch.allclose(emb[0, 5:7], emb2[0, 5:7])  # sequence 0's global tokens follow its scene
    torch.testing.assert_close(emb[1], emb2[1])
    with pytest.raises(ValueError, match="need their rows"):
        sparse_world.embed(batch["input_ids"])


def test_forecast_loss_trains_every_part_and_a_batch_without_it_still_reaches_the_forecaster(sparse_world):
    from occtrain.core.builder import collate

    torch.manual_seed(2)
    rows = torch.randn(4, 11) * 5
    batch = collate(
        [_sequence(sparse_world, rows, True), _sequence(sparse_world, rows, False)], sparse_world.vocab.pad_id
    )
    assert batch["forecast_points"].shape == (2, 2, 16, 3) and batch["forecast_valid"][1].sum() == 0
    sparse_world.zero_grad()
    out = sparse_world(batch)
    assert out.scene_loss > 0 and out.text_loss > 0
    out.loss.backward()
    missing = [n for n, p in sparse_world.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, missing
    assert any(p.grad.abs().sum() > 0 for p in sparse_world.forecaster.parameters())
    sparse_world.zero_grad()
    text_only = collate([_sequence(sparse_world, rows, False)], sparse_world.vocab.pad_id)
    out = sparse_world(text_only)
    assert float(out.scene_loss.detach()) == 0.0
    out.loss.backward()  # DDP waits for a gradient of every parameter: the forecaster gets zeros
    assert all(p.grad is not None and p.grad.abs().sum() == 0 for p in sparse_world.forecaster.parameters())


def test_the_encoders_rows_decode_to_its_last_layers_points():
    from occtrain.families.sparseoccvla.config import SparseOccConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder
    from occtrain.families.sparseoccvla.scene_encoder import SparseSceneEncoder

    torch.manual_seed(0)
    enc = SparseOccEncoder(SparseOccConfig(queries=4, dim=8, heads=2, points_per_layer=[2, 3], mixing_groups=2)).eval()
    q = torch.randn(1, 4, 8)
    pos = torch.randn(1, 4, 3) * 5
    head = enc.layers[-1].head
    points, logits = head(q, pos - 0.0)
    mean = points.mean(2)  # P_L: where the queries move
    got, classes = enc.decode_points(q, mean)
    torch.testing.assert_close(got, points.flatten(1, 2))
    assert torch.equal(classes, logits.argmax(-1).flatten(1))
    labels = SparseSceneEncoder(enc).decode(torch.cat([mean, q], -1))
    assert labels.shape == (1, *GRID_SHAPE) and int((labels != FREE).sum()) > 0


def test_frames_move_between_ego_frames_by_the_poses():
    from occtrain.families.sparseoccvla.inputs import ego_to_global

    # The ego drives 5 m along global +y (yaw 90 deg); a point 10 m ahead of the later ego
    # is 15 m ahead of the earlier one.
    earlier, later = ego_to_global(0.0, 0.0, math.pi / 2), ego_to_global(0.0, 5.0, math.pi / 2)
    move = np.linalg.inv(earlier) @ later
    np.testing.assert_allclose(move @ [10.0, 0.0, 0.0, 1.0], [15.0, 0.0, 0.0, 1.0], atol=1e-9)


def test_nearest_by_tree_equals_dense_distances_over_the_valid_points():
    from occtrain.models import point_sets

    gen = torch.Generator().manual_seed(0)
    src, dst = torch.randn(3, 200, 3, generator=gen) * 10, torch.randn(3, 150, 3, generator=gen) * 10
    valid = torch.rand(3, 150, generator=gen) > 0.3
    valid[2] = False  # a sample with no point to match: index 0, as the dense path gives
    tree = point_sets._nearest_by_tree(src, dst, valid)
    dense = torch.cdist(src, dst).masked_fill(~valid[:, None], float("inf")).argmin(-1)
    assert torch.equal(tree, dense)
    assert bool(valid[0, tree[0]].all()) and bool(valid[1, tree[1]].all())


def test_earlier_camera_frames_follow_the_batch_to_its_device(synth_dataset):
    """On a GPU the batch is on the device and earlier frames come from disk: every tensor
    must land beside the batch (the meta device stands in for CUDA here)."""
    from occtrain.data.frames import camera_batch
    from occtrain.data.layout import DatasetIndex
    from occtrain.families.sparseoccvla.inputs import camera_frames

    index = DatasetIndex.open(synth_dataset)
    scene = next(iter(index.scenes))
    token = index.scenes[scene][3]
    batch = {k: v.to("meta") for k, v in camera_batch(index, [(scene, token)]).items()}
    batch["meta"] = [{"scene": scene, "token": token, "index": 3}]
    frames = camera_frames(batch, index, frames=2)
    assert all(
        t.device.type == "meta" for t in (frames.images, frames.intrinsics, frames.cam_to_ego, frames.current_to_frame)
    )
    assert frames.images.shape[1] == 2


def test_initial_positions_learn_in_grid_units_and_old_exports_read_back_in_metres():
    """P_0 is kept in [-1, 1] of the grid's half-ranges: one Adam step at lr 1e-2 moves a
    query by 0.4 m in x (it moved by 1 cm when kept in metres); a state dict that holds P_0
    in metres (an export from before) loads to the same positions."""
    from occtrain.families.sparseoccvla.config import SparseOccConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder

    torch.manual_seed(0)
    cfg = SparseOccConfig(queries=4, dim=8, heads=2, points_per_layer=[2, 3], mixing_groups=2)
    enc = SparseOccEncoder(cfg)
    before = enc.initial_positions.detach().clone()
    assert (before[:, :2].abs() <= 40).all() and (before[:, 2] >= -1).all() and (before[:, 2] <= 5.4).all()
    opt = torch.optim.Adam([enc.initial_unit], lr=1e-2)
    enc.initial_positions[:, 0].sum().backward()
    opt.step()
    moved = (enc.initial_positions.detach() - before)[:, 0]
    torch.testing.assert_close(moved, torch.full((4,), -0.4), atol=1e-4, rtol=0)
    old = {k: v for k, v in enc.state_dict().items() if k != "initial_unit"}
    old["initial_positions"] = enc.initial_positions.detach().clone()
    again = SparseOccEncoder(cfg)
    again.load_state_dict(old)
    torch.testing.assert_close(again.initial_positions, enc.initial_positions)


def test_a_grid_layout_puts_one_query_in_each_cell_of_a_birds_eye_lattice():
    """``query_init: grid``: 16 queries sit at the centres of a 4 x 4 lattice of 20 m cells
    over the 80 x 80 m range, 1 m above the ground; 10 fill rows of 4 and a half-empty last
    row; an unknown layout is refused by name."""
    from occtrain.families.sparseoccvla.config import SparseOccConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder

    enc = SparseOccEncoder(
        SparseOccConfig(queries=16, dim=8, heads=2, points_per_layer=[2], mixing_groups=2, query_init="grid")
    )
    p0 = enc.initial_positions.detach()
    centres = torch.tensor([-30.0, -10.0, 10.0, 30.0])
    torch.testing.assert_close(p0[:, 0], centres.repeat_interleave(4))
    torch.testing.assert_close(p0[:, 1], centres.repeat(4))
    torch.testing.assert_close(p0[:, 2], torch.ones(16))
    ten = SparseOccEncoder(
        SparseOccConfig(queries=10, dim=8, heads=2, points_per_layer=[2], mixing_groups=2, query_init="grid")
    )
    xy = ten.initial_positions.detach()[:, :2]
    assert len({tuple(row) for row in xy.tolist()}) == 10
    torch.testing.assert_close(xy[8:, 1], centres[:2])
    with pytest.raises(ConfigError, match="query_init: 'rings'"):
        SparseOccConfig(query_init="rings").validate("model.sparseocc")


def test_the_budget_oracle_places_the_last_layers_points_on_occupied_voxels():
    """Evaluation reports the oracle of the encoder's point budget: queries x last-layer
    points on occupied voxels with their classes, voxelized as the decoded points are: a
    budget that covers every occupied voxel reconstructs the frame exactly."""
    from occtrain.families.sparseoccvla.config import SparseOccConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder
    from occtrain.metrics.reconstruction import ReconstructionMetrics

    cfg = SparseOccConfig(queries=4, dim=8, heads=2, points_per_layer=[2, 3], mixing_groups=2, voxel_extent=[1, 1, 1])
    enc = SparseOccEncoder(cfg)
    assert enc.point_budget == 12
    sem = torch.full((1, *GRID_SHAPE), FREE, dtype=torch.uint8)
    sem[0, 100, 100, :3] = 4
    sem[0, 10:12, 20:24, 0] = 11  # 3 + 8 = 11 occupied voxels: the budget of 12 covers them
    batch = {"semantics": sem, "meta": [{"token": "t0"}]}
    oracle = enc.oracle(batch, seed=0)
    assert torch.equal(oracle, sem.long())
    metrics = ReconstructionMetrics({}, oracles=("budget_oracle",))
    mask = torch.ones_like(sem, dtype=torch.bool)
    metrics.update(torch.full_like(oracle, FREE), sem.long(), mask, oracles={"budget_oracle": oracle})
    out = metrics.compute()
    assert out["baseline_budget_oracle_occworld_IoU"] == 100.0 and out["occworld_IoU"] == 0.0
    assert out["baseline_budget_oracle_occworld_movable_mIoU"] == 100.0
    with pytest.raises(ValueError, match="oracle"):
        metrics.update(oracle, sem.long(), torch.ones_like(sem, dtype=torch.bool))


def test_points_voxelize_over_a_background_where_none_lands():
    """``background``: a voxel no point covers keeps its label (the prior), one a point
    covers takes the point's class, and the background itself is left as it was."""
    background = torch.full(GRID_SHAPE, FREE, dtype=torch.uint8)
    background[:, :, 0] = 11  # road under everything
    labels = voxelize(voxel_centres(torch.tensor([[3, 4, 0], [7, 7, 5]])), torch.tensor([4, 15]), background=background)
    assert labels[3, 4, 0] == 4 and labels[7, 7, 5] == 15
    assert labels[0, 0, 0] == 11 and labels[0, 0, 1] == FREE
    assert int((labels != background.long()).sum()) == 2 and background[3, 4, 0] == 11


def test_lift_puts_every_pixel_back_where_it_projected_from():
    """``lift`` inverts ``project``: ego points projected into a camera and lifted at their
    camera-z depth come back to themselves; ``beyond`` moves them that far along the ray."""
    from occtrain.models.projection import in_cameras, lift

    intr, to_ego, cams = _rig()
    h, w = 72, 128
    # The depth a plane 12 m in front of each camera gives every pixel, lifted, then projected back.
    depth = torch.full((1, len(cams), h, w), 12.0)
    points = lift(depth, intr, to_ego)
    assert points.shape == (1, len(cams), h, w, 3)
    for v in range(len(cams)):
        flat = points[:, v].reshape(1, -1, 3)
        uv, inside = project(flat, intr, to_ego, (h, w))
        assert bool(inside[0, v].all())
        vv, uu = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        torch.testing.assert_close(uv[0, v], torch.stack([uu, vv], -1).reshape(-1, 2), atol=2e-3, rtol=0)
        torch.testing.assert_close(in_cameras(flat, to_ego)[0, v, :, 2], torch.full((h * w,), 12.0), atol=1e-3, rtol=0)
    further = lift(depth, intr, to_ego, beyond=0.1)
    torch.testing.assert_close(
        (further - points).norm(dim=-1), torch.full((1, len(cams), h, w), 0.1), atol=1e-4, rtol=0
    )


def test_lifted_pixels_of_a_rendered_frame_label_the_voxels_its_cameras_see(synth_dataset):
    """Every pixel's class lifted to its depth lands in a voxel of that class: the ceiling
    row reads what the cameras show and nothing else, and over the prior it keeps the prior
    where no pixel lands."""
    from occtrain.data.frames import frames_batch
    from occtrain.data.layout import DatasetIndex
    from occtrain.models.point_sets import lifted_pixels

    index = DatasetIndex.open(synth_dataset)
    scene = index.splits["val"][0]
    batch = frames_batch(index, [(scene, index.scenes[scene][3])], cameras=True, pixel_truth=True)
    assert batch["cam_class"].shape == batch["cam_depth"].shape == (1, 6, 72, 128)
    truth = batch["semantics"][0].long()
    cams = batch["cam_class"], batch["cam_depth"], batch["intrinsics"], batch["cam_to_ego"]
    lifted = lifted_pixels(*cams)[0]
    seen = lifted != FREE
    assert int(seen.sum()) > 1000
    agree = float((lifted[seen] == truth[seen]).float().mean())
    assert agree > 0.97, agree  # the rest: rays that clip a voxel's corner, the ground beyond the labels
    background = torch.full(GRID_SHAPE, 13, dtype=torch.uint8)
    over = lifted_pixels(*cams, background)[0]
    assert torch.equal(over[seen], lifted[seen]) and bool((over[~seen] == 13).all())
    without = frames_batch(index, [(scene, index.scenes[scene][3])], cameras=True)
    assert "cam_class" not in without  # only where asked: a world model's scene cache reads no maps


def test_the_encoder_decodes_the_prior_where_no_point_lands_and_exports_it():
    """``unseen: prior``: the stage's per-voxel prior is what a decoded scene holds where no
    point lands, kept in the export; ``unseen: free`` keeps the paper's free; an export from
    before the prior was kept loads as free."""
    from occtrain.families.sparseoccvla.config import SparseOccConfig
    from occtrain.families.sparseoccvla.encoder import SparseOccEncoder

    prior = torch.full(GRID_SHAPE, FREE, dtype=torch.uint8)
    prior[:, :, 0] = 11
    small = {"queries": 4, "dim": 8, "heads": 2, "points_per_layer": [2, 3], "mixing_groups": 2}
    nowhere = torch.full((1, 1, 3), 100.0), torch.zeros(1, 1, dtype=torch.long)  # one point beyond the grid
    enc = SparseOccEncoder(SparseOccConfig(**small))
    assert bool((enc.voxelize(*nowhere) == FREE).all())  # until the stage gives the prior
    enc.set_voxel_prior(prior)
    assert torch.equal(enc.voxelize(*nowhere)[0], prior.long())
    again = SparseOccEncoder(SparseOccConfig(**small))
    again.load_state_dict(enc.state_dict())
    assert torch.equal(again.voxelize(*nowhere)[0], prior.long())
    free = SparseOccEncoder(SparseOccConfig(**small, unseen="free"))
    free.set_voxel_prior(prior)
    assert bool((free.voxelize(*nowhere) == FREE).all())
    old = {k: v for k, v in enc.state_dict().items() if k != "unseen_labels"}
    before = SparseOccEncoder(SparseOccConfig(**small))
    before.load_state_dict(old)
    assert bool((before.voxelize(*nowhere) == FREE).all())
    with pytest.raises(ConfigError, match="unseen: 'zero'"):
        SparseOccConfig(unseen="zero").validate("model.sparseocc")

"""The small pieces the planner and distillation stages are made of, checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from occtrain.core.meta_action_planner import MetaActionPlannerConfig, ego_features, feature_size, head_prior
from occtrain.data.schema import COMMANDS, META_DIRECTIONS, META_SPEEDS
from occtrain.engine.export import _base_names
from occtrain.errors import ConfigError
from occtrain.metrics import flatten_metrics
from occtrain.models.distill_losses import distillation_losses
from occtrain.models.planning_heads import PlanningHead, constant_velocity_plan, prior_plan


def test_constant_velocity_drives_straight_at_the_current_speed():
    plan = constant_velocity_plan(torch.tensor([4.0, 0.0]), 6)
    np.testing.assert_allclose(plan[0, :, 0], [2, 4, 6, 8, 10, 12])  # 4 m/s, 0.5 s steps
    assert plan[0, :, 1].abs().max() == 0 and plan[1].abs().max() == 0


def test_planning_head_sums_step_displacements():
    head = PlanningHead(5, 8, 2, 6)
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        head.mlp[-1].bias.copy_(torch.tensor([1.0, 0.5] * 6))
    out = head(torch.randn(3, 5)).detach()
    np.testing.assert_allclose(out[0, :, 0], [1, 2, 3, 4, 5, 6])
    np.testing.assert_allclose(out[2, :, 1], [0.5, 1, 1.5, 2, 2.5, 3])


def test_ego_features_one_hot_layout():
    anchor = {
        "command": "turn left",
        "ego_speed": 5.0,
        "ego_accel": -1.5,
        "ego_yaw_rate": 0.2,
        "ego_past": [[-4, 0], [-3, 0], [-2, 0], [-1, 0]],
        "ego_past_mask": [0, 1, 1, 1],
    }
    meta = {"speed": "decelerate", "direction": "left"}
    f = ego_features(anchor, meta, ["meta_action", "ego_state", "command", "past"])
    assert f.shape == (feature_size(["meta_action", "ego_state", "command", "past"]),)
    s, d = len(META_SPEEDS), len(META_DIRECTIONS)
    assert f[:s].tolist() == [float(x == "decelerate") for x in META_SPEEDS]
    assert f[s : s + d].tolist() == [float(x == "left") for x in META_DIRECTIONS]
    np.testing.assert_allclose(f[s + d : s + d + 3], [0.5, -0.5, 0.2], rtol=1e-6)
    assert f[s + d + 3 : s + d + 3 + len(COMMANDS)].tolist() == [float(c == "turn left") for c in COMMANDS]
    np.testing.assert_allclose(f[-8:], [0, 0, -0.3, 0, -0.2, 0, -0.1, 0], atol=1e-7)  # the masked waypoint is zeroed


def test_distillation_losses_by_hand():
    valid = torch.tensor([[True, False]])
    teacher = torch.tensor([[[math.log(3.0), 0.0], [5.0, 5.0]]])  # p_t = (3/4, 1/4) at T=1
    student = torch.zeros(1, 2, 2)  # p_s = (1/2, 1/2)
    hidden_t = torch.tensor([[[1.0, -1.0], [9.0, 9.0]]])
    feat_s = torch.tensor([[[2.0, -2.0], [0.0, 0.0]]])
    kl, cos = distillation_losses(student, teacher, feat_s, hidden_t, valid, temperature=1.0)
    expected = 0.75 * math.log(0.75 / 0.5) + 0.25 * math.log(0.25 / 0.5)
    assert kl.item() == pytest.approx(expected, rel=1e-5)
    assert cos.item() == pytest.approx(0.0, abs=1e-6)  # same direction as LayerNorm(teacher) = (1, -1)
    kl_same, _ = distillation_losses(teacher, teacher, feat_s, hidden_t, valid, temperature=2.0)
    assert kl_same.item() == pytest.approx(0.0, abs=1e-7)
    # At T = 2 the teacher's logits (log 3, 0) soften to p_t = (sqrt 3, 1) / (sqrt 3 + 1); the
    # KL is scaled by T^2 = 4.
    kl2, _ = distillation_losses(student, teacher, feat_s, hidden_t, valid, temperature=2.0)
    p = [math.sqrt(3) / (math.sqrt(3) + 1), 1 / (math.sqrt(3) + 1)]
    assert kl2.item() == pytest.approx(4 * sum(q * math.log(q / 0.5) for q in p), rel=1e-5)
    # The teacher's state is LayerNorm-ed before the cosine: (3, 1) -> (1, -1), which the
    # student's (1, -1) matches (loss 0; 1 - cos((3, 1), (1, -1)) = 0.553 without the norm)
    # and its (1, 1) is orthogonal to (loss 1).
    hidden_31 = torch.tensor([[[3.0, 1.0], [9.0, 9.0]]])
    _, cos_match = distillation_losses(
        student, teacher, torch.tensor([[[1.0, -1.0], [0.0, 0.0]]]), hidden_31, valid, 1.0
    )
    _, cos_orth = distillation_losses(student, teacher, torch.tensor([[[1.0, 1.0], [0.0, 0.0]]]), hidden_31, valid, 1.0)
    assert cos_match.item() == pytest.approx(0.0, abs=1e-5) and cos_orth.item() == pytest.approx(1.0, abs=1e-5)


def test_peft_names_map_back_to_the_plain_model():
    state = {
        "occ_proj.0.weight": 1,
        "llm.base_model.model.model.layers.0.self_attn.q_proj.base_layer.weight": 2,
        "llm.base_model.model.model.layers.0.self_attn.q_proj.lora_A.default.weight": 3,
        "llm.base_model.model.lm_head.weight": 4,
    }
    assert _base_names(state) == {
        "occ_proj.0.weight": 1,
        "llm.model.layers.0.self_attn.q_proj.weight": 2,
        "llm.lm_head.weight": 4,
    }


def test_flatten_metrics_names_and_drops_labels():
    flat = flatten_metrics("val/plan", {"convention": "x", "L2_stp3": {"1s": 0.5}, "samples": torch.tensor(3)})
    assert flat == {"val/plan_L2_stp3_1s": 0.5, "val/plan_samples": 3.0}


def test_a_heads_prior_is_the_kinematic_plan_along_the_last_move():
    # Moving up-left at 45 degrees: the last move (-past[-1]) is (1, 1) m; 6 m/s now against
    # the last move's sqrt(2) m / 0.5 s = 2.83 m/s -> +12.7 m/s^2 (past_acceleration).
    anchor = {"ego_speed": 6.0, "ego_past": [[-2.0, -2.0], [-1.0, -1.0]], "ego_past_mask": [1, 1]}
    t = np.arange(1, 7) * 0.5
    unit = np.array([1.0, 1.0]) / np.sqrt(2.0)
    cv = prior_plan([anchor], "constant_velocity")[0].numpy()
    np.testing.assert_allclose(cv, (6.0 * t)[:, None] * unit, rtol=1e-5)
    accel = (6.0 - np.sqrt(2.0) / 0.5) / 0.25
    ca = prior_plan([anchor], "constant_acceleration")[0].numpy()
    np.testing.assert_allclose(ca, (6.0 * t + 0.5 * accel * t**2)[:, None] * unit, rtol=1e-5)
    assert prior_plan([anchor], "none") is None
    with pytest.raises(ValueError, match="unknown plan prior"):
        prior_plan([anchor], "kinematic")


def test_a_heads_waypoints_add_to_its_prior_and_its_export_says_which():
    head = PlanningHead(5, 8, 2, 6)
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
    base = torch.arange(12.0).view(1, 6, 2)
    np.testing.assert_allclose(head(torch.randn(1, 5), base=base).detach(), base)  # a zero head keeps the prior
    assert head_prior(None, ["meta_action", "velocity"]) == "constant_velocity"  # what the velocity input meant
    assert head_prior(None, ["meta_action"]) == "none"
    assert head_prior("constant_acceleration", ["meta_action"]) == "constant_acceleration"
    with pytest.raises(ConfigError, match="model.prior 'kinematic' is not one of none, constant_velocity"):
        MetaActionPlannerConfig(prior="kinematic").validate("stages 'planner'")

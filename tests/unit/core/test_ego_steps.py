"""The ego's step between scenes, tracked by one rule for training and generation."""

import torch

from occtrain.core.ego_steps import EgoTrack


def test_a_forecast_reads_each_step_from_the_waypoints_between_scenes():
    """Anchor scene at the origin; waypoint 1 then a predicted scene; waypoint 2 then another:
    the steps are waypoint 1 and waypoint 2 minus waypoint 1."""
    ego = EgoTrack()
    ego.scene(predicted=False)
    assert ego.step() is None  # no waypoint since the scene: nothing to move by
    ego.planned(torch.tensor([[-3.0, 0.0], [-1.5, 0.0]]))  # the ego's past, after the anchor scene
    ego.planned(torch.tensor([[2.0, 0.5]]))  # the last waypoints laid out are the plan
    assert ego.step() == (2.0, 0.5)
    ego.scene(predicted=True)
    ego.planned(torch.tensor([[4.5, 1.5]]))
    assert ego.step() == (2.5, 1.0)
    ego.scene(predicted=True)
    assert ego.step() is None


def test_a_prompt_scene_puts_the_ego_back_at_the_origin():
    """History scenes are each in their own frame: after one, the next step counts from zero."""
    ego = EgoTrack()
    ego.planned(torch.tensor([[5.0, 5.0]]))
    ego.scene(predicted=True)
    ego.scene(predicted=False)
    ego.planned(torch.tensor([[1.0, 0.0]]))
    assert ego.step() == (1.0, 0.0)

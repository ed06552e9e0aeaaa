"""What a predicted scene's query block reads, tracked by one rule for training and generation."""

import torch

from occtrain.core.ego_steps import SceneTrack

PRESENT, FIRST = torch.tensor([1, 2]), torch.tensor([3, 4])


def test_a_forecast_reads_each_step_from_the_waypoints_between_scenes():
    """The present at the origin; waypoint 1 then a predicted scene; waypoint 2 then another:
    the steps are waypoint 1 and waypoint 2 minus waypoint 1, the moves since the present
    waypoint 1 and waypoint 2."""
    track = SceneTrack()
    track.scene(PRESENT, predicted=False)
    assert track.context().step is None and track.context().offset is None  # no waypoint since
    track.planned(torch.tensor([[-3.0, 0.0], [-1.5, 0.0]]))  # the ego's past, after the present
    track.planned(torch.tensor([[2.0, 0.5]]))  # the last waypoints laid out are the plan
    first = track.context()
    assert (first.step, first.offset) == ((2.0, 0.5), (2.0, 0.5))
    assert first.last_scene is PRESENT and first.observed is PRESENT
    track.scene(FIRST, predicted=True)
    track.planned(torch.tensor([[4.5, 1.5]]))
    second = track.context()
    assert (second.step, second.offset) == ((2.5, 1.0), (4.5, 1.5))
    assert second.last_scene is FIRST and second.observed is PRESENT
    track.scene(PRESENT, predicted=True)
    assert track.context().step is None


def test_a_prompt_scene_is_observed_and_puts_the_ego_back_at_the_origin():
    """History scenes are each in their own frame: after one, moves count from zero again."""
    track = SceneTrack()
    track.planned(torch.tensor([[5.0, 5.0]]))
    track.scene(FIRST, predicted=True)
    track.scene(PRESENT, predicted=False)
    track.planned(torch.tensor([[1.0, 0.0]]))
    context = track.context()
    assert context.step == (1.0, 0.0) and context.observed is PRESENT

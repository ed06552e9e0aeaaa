"""The planner contract: an abstract torch module every family's planner subclasses, so a
planner missing part of what the planner stage, eval and drive call is refused when made."""

from __future__ import annotations

import pytest
import torch

from occtrain.core.meta_action_planner import MetaActionPlanner
from occtrain.core.protocols import Planner, Plans
from occtrain.families.sparseoccvla.anchor_diffusion import AnchorDiffusionPlanner


class _NoWaypoints(Planner):
    monitor = "val/x"

    def closed_loop_refusal(self):
        return None

    def sidecar_tasks(self):
        return []

    def training_loss(self, clips):
        return torch.zeros(())

    def validate(self, clips, batch_idx, generate_batches=-1):
        pass

    def compute(self, prefix):
        return {}

    def summary(self):
        return "", {}

    def export(self, path):
        return path


def test_a_planner_without_waypoints_cannot_be_made():
    with pytest.raises(TypeError, match="waypoints"):
        _NoWaypoints()


def test_a_whole_planner_is_a_module_with_the_defaults():
    class Whole(_NoWaypoints):
        def waypoints(self, clips):
            return Plans.own(torch.zeros(len(clips), 6, 2).numpy())

    planner = Whole()
    assert isinstance(planner, torch.nn.Module)
    assert planner.prepare_training(torch.device("cpu")) is None and planner.save_cache() is None
    assert planner.waypoints([None, None]).xy.shape == (2, 6, 2)


@pytest.mark.parametrize("cls", [MetaActionPlanner, AnchorDiffusionPlanner])
def test_the_shipped_planners_keep_the_contract(cls):
    assert issubclass(cls, Planner) and not getattr(cls, "__abstractmethods__", frozenset())

"""Planning heads: OccVLA's MLP from meta action and ego state to waypoints, and the baseline."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from occtrain.errors import OcctrainError
from occtrain.exports import load_state_strict, read_export
from occtrain.occ3d import FRAME_DT


class PlanningHead(nn.Module):
    """An MLP from a feature vector to ``steps`` (x, y) waypoints in the ego frame.

    Waypoints are predicted as per-step displacements and summed, so the trajectory
    is continuous by construction and the output scale stays that of one 0.5 s step.
    """

    def __init__(self, features: int, hidden: int, layers: int, steps: int, dropout: float = 0.0):
        super().__init__()
        dims = [features] + [hidden] * (layers - 1)
        blocks: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.LayerNorm(b), nn.GELU(), nn.Dropout(dropout)]
        blocks.append(nn.Linear(dims[-1], steps * 2))
        self.mlp = nn.Sequential(*blocks)
        self.steps = steps

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, features) -> (B, steps, 2) waypoints in metres."""
        return self.mlp(features).view(-1, self.steps, 2).cumsum(1)


def constant_velocity_plan(speed: torch.Tensor, steps: int) -> torch.Tensor:
    """The trivial baseline: keep driving straight at the current speed. (B,) m/s -> (B, steps, 2)."""
    t = torch.arange(1, steps + 1, device=speed.device, dtype=torch.float32) * FRAME_DT
    x = speed.float()[:, None] * t
    return torch.stack([x, torch.zeros_like(x)], dim=-1)


def load_planning_head(export_dir: Path) -> PlanningHead:
    """The planning head of a planner stage's export, in eval mode."""
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "planner":
        raise OcctrainError(f"{export_dir}: not a planner export (stage kind '{config.get('stage_kind')}')")
    head = PlanningHead(config["features"], config["hidden"], config["layers"], config["steps"], 0.0)
    load_state_strict(head, state, (), str(export_dir))
    return head.eval()

"""Planning heads: OccVLA's MLP from meta action and ego state to waypoints, and the baseline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from occtrain.errors import OcctrainError
from occtrain.formats.exports import load_state_strict, read_export
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.kinematics import constant_acceleration_path, past_acceleration


class PlanningHead(nn.Module):
    """An MLP from a feature vector to ``steps`` (x, y) waypoints in the ego frame.

    Waypoints are predicted as per-step displacements and summed, so the trajectory
    is continuous by construction and the output scale stays that of one 0.5 s step.
    With ``visual_dim`` the head also reads a visual summary through a narrow bottleneck
    (LayerNorm, dropout, a linear map to ``visual_width``): a few hundred training clips
    overfit a full-width one (measured: L2 0.57 m with it, 0.48 m through 8 dims). Given
    a ``base`` plan (a kinematic prior's: constant velocity or acceleration), the MLP's
    waypoints are added to it, so the head learns how the meta action bends and slows the
    ego's motion rather than the motion itself (1.27 m L2 without that, against 0.53 m for
    constant velocity alone).
    """

    def __init__(
        self,
        features: int,
        hidden: int,
        layers: int,
        steps: int,
        dropout: float = 0.0,
        visual_dim: int = 0,
        visual_width: int = 8,
    ):
        super().__init__()
        #: The width of the visual summary it reads (0: none).
        self.visual_dim = visual_dim
        self.visual = (
            nn.Sequential(nn.LayerNorm(visual_dim), nn.Dropout(0.5), nn.Linear(visual_dim, visual_width))
            if visual_dim
            else None
        )
        dims = [features + (visual_width if visual_dim else 0)] + [hidden] * (layers - 1)
        blocks: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.LayerNorm(b), nn.GELU(), nn.Dropout(dropout)]
        blocks.append(nn.Linear(dims[-1], steps * 2))
        self.mlp = nn.Sequential(*blocks)
        self.steps = steps

    def forward(
        self, features: torch.Tensor, visual: torch.Tensor | None = None, base: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(B, features) [+ visual (B, visual_dim)] [+ base (B, steps, 2) m] -> (B, steps, 2) waypoints in metres."""
        if self.visual is not None:
            features = torch.cat([features, self.visual(visual)], dim=1)
        plan = self.mlp(features).view(-1, self.steps, 2).cumsum(1)
        return plan if base is None else plan + base.to(plan.dtype)


def constant_velocity_plan(speed: torch.Tensor, steps: int) -> torch.Tensor:
    """The trivial baseline: keep driving straight at the current speed. (B,) m/s -> (B, steps, 2)."""
    t = torch.arange(1, steps + 1, device=speed.device, dtype=torch.float32) * FRAME_DT
    x = speed.float()[:, None] * t
    return torch.stack([x, torch.zeros_like(x)], dim=-1)


def _last_move(anchor: dict) -> np.ndarray | None:
    """(2,) metres from the last past waypoint to here in the ego frame; None without one."""
    past = np.asarray(anchor.get("ego_past", []), dtype=np.float64).reshape(-1, 2)
    mask = np.asarray(anchor.get("ego_past_mask", []), dtype=bool)
    return -past[-1] if len(past) and mask[-1] else None


def last_move(anchor: dict) -> float | None:
    """Metres the ego moved from the previous frame to this one (its last past waypoint), None without one."""
    move = _last_move(anchor)
    return None if move is None else float(np.linalg.norm(move))


def heading(anchor: dict) -> np.ndarray:
    """(2,) unit vector in the ego frame: the direction of the last move (+x without one)."""
    move, norm = _last_move(anchor), last_move(anchor)
    return move / norm if move is not None and norm is not None and norm > 1e-3 else np.array([1.0, 0.0])


def current_velocity(anchor: dict) -> np.ndarray:
    """(2,) m/s in the ego frame: the speed (the sidecar's, else the last move's) along the
    ``heading``."""
    speed = float(anchor["ego_speed"]) if "ego_speed" in anchor else (last_move(anchor) or 0.0) / FRAME_DT
    return speed * heading(anchor)


def ego_speed(anchor: dict) -> float:
    """The ego's current speed (m/s): the sidecar's, else that of its last move."""
    return float(anchor["ego_speed"]) if "ego_speed" in anchor else float(np.linalg.norm(current_velocity(anchor)))


def constant_velocity(anchors: list[dict], device: torch.device | str = "cpu") -> torch.Tensor:
    """The constant-velocity baseline of each anchor: straight on at its current speed, (B, 6, 2)."""
    return constant_velocity_plan(torch.tensor([ego_speed(a) for a in anchors], device=device), FUTURE_STEPS)


def constant_acceleration(anchors: list[dict], device: torch.device | str = "cpu") -> torch.Tensor:
    """The constant-acceleration baseline of each anchor, (B, 6, 2): straight on from its
    current speed at the acceleration its past shows (``kinematics.past_acceleration``: the
    speed now against the last move's; no future, no sidecar acceleration), stopping at
    standstill. On a world where speed changes are smooth it is the kinematic bar a planner
    must clear, far lower than constant velocity's."""
    rows = []
    for anchor in anchors:
        speed = ego_speed(anchor)
        x = constant_acceleration_path(speed, past_acceleration(speed, last_move(anchor)), FUTURE_STEPS)
        rows.append(np.stack([x, np.zeros_like(x)], axis=1))
    return torch.tensor(np.array(rows), dtype=torch.float32, device=device).reshape(len(anchors), FUTURE_STEPS, 2)


#: What a planning head's waypoints may be written against (``prior_plan``), plain first.
HEAD_PRIORS = ("none", "constant_velocity", "constant_acceleration")


def prior_plan(anchors: list[dict], prior: str, device: torch.device | str = "cpu") -> torch.Tensor | None:
    """(B, 6, 2) the kinematic plan a head's waypoints add to under ``prior`` (None for
    "none"): constant velocity, or constant acceleration at the past's acceleration, each
    turned from straight ahead onto the ``heading`` of the ego's last move."""
    if prior == "none":
        return None
    if prior not in HEAD_PRIORS:
        raise ValueError(f"unknown plan prior '{prior}' (one of {', '.join(HEAD_PRIORS)})")
    plan = constant_velocity if prior == "constant_velocity" else constant_acceleration
    ahead = plan(anchors, device)[..., 0]
    direction = torch.tensor(np.array([heading(a) for a in anchors]), dtype=torch.float32, device=device)
    return ahead[..., None] * direction.reshape(len(anchors), 1, 2)


def load_planning_head(export_dir: Path) -> PlanningHead:
    """The planning head of a planner stage's export, in eval mode (its config's ``inputs``
    say what to feed it, its ``prior`` what to pass as ``base``: ``prior_plan``)."""
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "planner":
        raise OcctrainError(f"{export_dir}: not a planner export (stage kind '{config.get('stage_kind')}')")
    head = PlanningHead(
        config["features"],
        config["hidden"],
        config["layers"],
        config["steps"],
        0.0,
        config.get("visual_dim", 0),
        config.get("visual_width", 8),
    )
    load_state_strict(head, state, (), str(export_dir))
    return head.eval()

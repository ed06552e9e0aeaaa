"""Planning heads: OccVLA's MLP from meta action and ego state to waypoints, and the baseline."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from occtrain.data.schema import LATERAL_DECAY_S, ROUTE_ARC
from occtrain.errors import OcctrainError
from occtrain.formats.exports import load_state_strict, read_export
from occtrain.formats.occ3d import FRAME_DT, FUTURE_STEPS
from occtrain.kinematics import constant_acceleration_path, past_acceleration


class PlanningHead(nn.Module):
    """An MLP from a feature vector to ``steps`` (x, y) waypoints in the ego frame.

    Two ways to write them (``along_route``): as waypoints in the ego frame added to a
    ``base`` plan (below), or along the route ahead: ``steps`` distances travelled along it
    (added to a prior's, kept moving forward) and ``steps`` offsets left of it (added to a
    prior's), laid on the route's centreline (``route_plan``). Along the route a turn is the
    route's, not a large residual for the head to learn (label against a straight prior:
    RMS 3.4 m at the median; along the route its sideways part is 0.13 m).

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
        along_route: bool = False,
    ):
        super().__init__()
        self.along_route = along_route
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
        self,
        features: torch.Tensor,
        visual: torch.Tensor | None = None,
        base: torch.Tensor | None = None,
        route: RoutePrior | None = None,
    ) -> torch.Tensor:
        """(B, features) [+ visual (B, visual_dim)] [+ base (B, steps, 2) m, or the ``route``
        prior when the head writes along the route] -> (B, steps, 2) waypoints in metres."""
        if self.visual is not None:
            features = torch.cat([features, self.visual(visual)], dim=1)
        out = self.mlp(features).view(-1, self.steps, 2)
        if self.along_route:
            if route is None:
                raise ValueError("a head that writes along the route needs the route prior")
            # Progress offsets summed per step (a change of speed, not of position) and kept
            # from running backwards; the sideways offset is the prior's plus the head's.
            progress = torch.cummax((route.progress + out[..., 0].cumsum(1)).clamp(min=0.0), dim=1).values
            return route_plan(route.points, progress, route.lateral + out[..., 1])
        plan = out.cumsum(1)
        return plan if base is None else plan + base.to(plan.dtype)


@dataclass
class RoutePrior:
    """What a head writing along the route adds to: the route's centreline (B, P, 2) at
    ``ROUTE_ARC`` in the ego frame, and per step the distance a kinematic rule travels
    along it (B, steps) and the sideways offset it keeps (B, steps)."""

    points: torch.Tensor
    progress: torch.Tensor
    lateral: torch.Tensor


def route_plan(points: torch.Tensor, progress: torch.Tensor, lateral: torch.Tensor) -> torch.Tensor:
    """Waypoints (B, K, 2) on a route given as points (B, P, 2) at arc lengths ``ROUTE_ARC``
    (its first the ego's projection on it): the centreline ``progress`` metres (B, K) along
    from the projection, moved ``lateral`` metres (B, K) to its left. Linear between the
    points; past the last one, on along its last segment."""
    arc = torch.tensor(ROUTE_ARC, dtype=points.dtype, device=points.device)
    seg = (torch.searchsorted(arc, progress.contiguous(), right=True) - 1).clamp(0, len(ROUTE_ARC) - 2)
    a, b = _take(points, seg), _take(points, seg + 1)
    length = (arc[seg + 1] - arc[seg]).to(points.dtype)
    frac = (progress - arc[seg]) / length
    tangent = (b - a) / (b - a).norm(dim=-1, keepdim=True).clamp(min=1e-6)
    left = torch.stack([-tangent[..., 1], tangent[..., 0]], dim=-1)
    return a + frac[..., None] * (b - a) + lateral[..., None] * left


def _take(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """points (B, P, 2) at index (B, K) -> (B, K, 2)."""
    return torch.gather(points, 1, index[..., None].expand(*index.shape, 2))


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


#: What a planning head's waypoints may be written against (``prior_plan``), plain first;
#: the last is along the route ahead (``route_prior``), where the head writes progress.
HEAD_PRIORS = ("none", "constant_velocity", "constant_acceleration", "constant_acceleration_along_route")
ALONG_ROUTE = "constant_acceleration_along_route"


def route_of(anchor: dict) -> np.ndarray:
    """(P, 2) the route ahead at ``ROUTE_ARC`` in the ego frame: the frame's ``road.route``,
    or where a frame has none (real data without a map), straight on along the ``heading``
    of its last move."""
    road = anchor.get("road")
    if road is not None:
        return np.asarray(road["route"], dtype=np.float64).reshape(len(ROUTE_ARC), 2)
    return np.asarray(ROUTE_ARC)[:, None] * heading(anchor)[None, :]


def lateral_offset(route: np.ndarray) -> float:
    """The ego's offset (m) left of its route: from its projection (the route's first point)."""
    tangent = route[1] - route[0]
    tangent = tangent / max(float(np.linalg.norm(tangent)), 1e-6)
    return float(-route[0] @ np.array([-tangent[1], tangent[0]]))


def route_prior(anchors: list[dict], device: torch.device | str = "cpu") -> RoutePrior:
    """Constant acceleration along the route: each anchor's distances at its speed and past
    acceleration (``kinematics``) laid along its route, its sideways offset fading over
    ``LATERAL_DECAY_S``."""
    t = np.arange(1, FUTURE_STEPS + 1) * FRAME_DT
    routes, progress, lateral = [], [], []
    for anchor in anchors:
        speed = ego_speed(anchor)
        route = route_of(anchor)
        routes.append(route)
        progress.append(constant_acceleration_path(speed, past_acceleration(speed, last_move(anchor)), FUTURE_STEPS))
        lateral.append(lateral_offset(route) * np.exp(-t / LATERAL_DECAY_S))

    def tensor(rows: list[np.ndarray], *shape: int) -> torch.Tensor:
        return torch.tensor(np.array(rows), dtype=torch.float32, device=device).reshape(len(anchors), *shape)

    return RoutePrior(tensor(routes, len(ROUTE_ARC), 2), tensor(progress, FUTURE_STEPS), tensor(lateral, FUTURE_STEPS))


def prior_plan(anchors: list[dict], prior: str, device: torch.device | str = "cpu") -> torch.Tensor | None:
    """(B, 6, 2) the kinematic plan a head's waypoints add to under ``prior`` (None for
    "none"): constant velocity, or constant acceleration at the past's acceleration, each
    turned from straight ahead onto the ``heading`` of the ego's last move."""
    if prior == "none":
        return None
    if prior not in HEAD_PRIORS:
        raise ValueError(f"unknown plan prior '{prior}' (one of {', '.join(HEAD_PRIORS)})")
    if prior == ALONG_ROUTE:
        route = route_prior(anchors, device)
        return route_plan(route.points, route.progress, route.lateral)
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
        config.get("prior") == ALONG_ROUTE,
    )
    load_state_strict(head, state, (), str(export_dir))
    return head.eval()

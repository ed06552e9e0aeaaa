"""OccVLA's planner (Sec. 3.3-3.4): an MLP head from the meta action to the 6 future
waypoints, the ``core.protocols.Planner`` that OccVLA's and OccLLaMA's planner stages train.

The head maps the meta action (speed x direction) and the inputs a recipe names
(``inputs``: OccVLA's current velocity, averaged visual tokens of the consumed model and
past trajectory, with no driving command; the OccLLaMA chain's sidecar ego state and
command) to the waypoints, trained with MSE. It trains on the reference meta actions or,
as in OccVLA's stage 3, on those the consumed world model generates for the training
clips (generated once and cached in the stage directory). Validation reports it with the
reference and with the generated meta action, beside the world model's own action-token
plan (when it generates one), constant velocity and standing still, on the same samples.

What it asks of the consumed world model goes through its family's operations
(``WorldSpec.operations``): ``reference_meta_action(engine, clip)``,
``generated_meta_actions(engine, clips)`` and, for the ``visual`` input,
``visual_summary(engine, clips)``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn
from torchmetrics import MeanMetric

from occtrain.core.plan_subsets import plan_metrics, subset_rows, update_plans
from occtrain.core.protocols import Planner, PlannerContext, PlannerSettings, Plans, WorldEngine
from occtrain.data.clips import Clip, frame_clips, plan_target
from occtrain.data.layout import DatasetIndex
from occtrain.data.schema import COMMANDS, META_DIRECTIONS, META_SPEEDS
from occtrain.errors import ConfigError
from occtrain.formats.exports import write_export
from occtrain.formats.io import atomic_write_json, atomic_write_safetensors
from occtrain.formats.occ3d import FUTURE_STEPS, PAST_STEPS
from occtrain.metrics import compute_metrics
from occtrain.models import count_parameters
from occtrain.models.planning_heads import (
    ALONG_ROUTE,
    HEAD_PRIORS,
    ROUTE_ARC,
    PlanningHead,
    constant_acceleration,
    constant_velocity,
    current_velocity,
    prior_plan,
    route_of,
    route_prior,
)
from occtrain.progress import progress_bar
from occtrain.ranks import is_rank_zero

META_SOURCES = ("ground_truth", "generated")
#: What the head may read, in the order its input vector lays them out. ``route`` to
#: ``curvature`` are what a map and a tracker give (the frame's ``road``, see
#: ``data.schema.RoadContext``): what the expert's plan depends on.
HEAD_INPUTS = (
    "meta_action",
    "ego_state",
    "command",
    "velocity",
    "past",
    "route",
    "lead",
    "pedestrian",
    "stop_line",
    "curvature",
    "visual",
    "scene",
)
#: The inputs read from the world model's own outputs, averaged, through the head's
#: bottleneck, and the family operation that gives each (a head reads at most one).
SUMMARIES = {"visual": "visual_summary", "scene": "scene_summary"}
#: The route points the head reads (m of arc along the route, of ``ROUTE_ARC``).
ROUTE_INPUT_ARC = (2.5, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0)
LOSSES = ("mse", "l1", "huber")
#: Where the cached teacher outputs live in the stage directory.
TEACHER_CACHE = "teacher_outputs"


@dataclass
class MetaActionPlannerConfig(PlannerSettings):
    """The planning head's settings (flat in ``model:`` of a planner stage)."""

    hidden: int = 256
    layers: int = 3
    dropout: float = 0.1
    #: What the head reads (``HEAD_INPUTS``): the meta action (one-hot speed and direction),
    #: the ego state of the frame sidecar (speed, acceleration, yaw rate), the driving
    #: command, the ego's current velocity from its last move, its past waypoints, and
    #: ``visual``, the consumed world model's outputs at its image tokens, averaged
    #: (OccVLA: meta action, velocity, visual tokens and past trajectory; no command).
    inputs: list[str] = field(default_factory=lambda: ["meta_action", "ego_state", "command"])
    #: ``mse`` (OccVLA's), ``l1`` or ``huber`` (quadratic within 1 m, linear beyond: a
    #: junction frame's large error does not outweigh a hundred ordinary ones).
    loss: str = "mse"
    #: The meta action the head trains on: the reference (``ground_truth``) or the one the
    #: consumed model generates for each training clip (``generated``, OccVLA's stage 3;
    #: generated once and cached in the stage directory).
    train_meta: str = "ground_truth"
    #: Width of the bottleneck the visual summary passes through (see ``PlanningHead``).
    visual_width: int = 8
    #: Where validation takes the meta action from: the annotation, or the consumed
    #: model's generated chain of thought (both are always reported when possible).
    meta_source: str = "generated"
    #: What the head's waypoints add to (``HEAD_PRIORS``, not the paper's: OccVLA's head
    #: writes positions): a kinematic plan along the ego's last move, so the head learns
    #: how the meta action departs from it. Unset: constant velocity when the head reads
    #: ``velocity`` (as it always did), else none. ``constant_acceleration`` reads the
    #: past's acceleration, the strongest rule that sees no scene.
    #: ``constant_acceleration_along_route``: that rule laid along the frame's route, and the
    #: head writes how far along it each waypoint lies and how far to its side.
    prior: str | None = None

    def validate(self, where: str) -> None:
        if self.prior is not None and self.prior not in HEAD_PRIORS:
            raise ConfigError(f"{where}: model.prior '{self.prior}' is not one of {', '.join(HEAD_PRIORS)}")
        if self.loss not in LOSSES:
            raise ConfigError(f"{where}: model.loss '{self.loss}' is not one of {', '.join(LOSSES)}")
        for key in ("meta_source", "train_meta"):
            if getattr(self, key) not in META_SOURCES:
                raise ConfigError(
                    f"{where}: model.{key} '{getattr(self, key)}' is not one of {', '.join(META_SOURCES)}"
                )
        unknown = [n for n in self.inputs if n not in HEAD_INPUTS]
        if unknown or not self.inputs:
            raise ConfigError(f"{where}: model.inputs {list(self.inputs)} must name some of {', '.join(HEAD_INPUTS)}")
        if sum(n in self.inputs for n in SUMMARIES) > 1:
            raise ConfigError(f"{where}: model.inputs reads one of {', '.join(SUMMARIES)}, not both")

    def needs_teacher(self) -> bool:
        if "meta_action" not in self.inputs:
            return any(n in self.inputs for n in SUMMARIES)
        generated = self.meta_source == "generated" or self.train_meta == "generated"
        return generated or any(n in self.inputs for n in SUMMARIES)


def head_prior(prior: str | None, inputs: list[str] | tuple[str, ...]) -> str:
    """A head's ``prior``, or where it is unset what its inputs implied (exports before it)."""
    if prior is not None:
        return prior
    return "constant_velocity" if "velocity" in inputs else "none"


def ego_features(anchor: dict, meta: dict | None, inputs: list[str] | tuple[str, ...]) -> np.ndarray:
    """The head's input vector: the ``inputs`` in ``HEAD_INPUTS`` order (the visual summary
    goes in apart, through the head's bottleneck)."""
    parts = []
    for name in HEAD_INPUTS:
        if name not in inputs:
            continue
        if name == "meta_action":
            if meta is None:
                raise ValueError("a head that reads the meta action needs one for every frame it plans")
            parts += [
                np.eye(len(META_SPEEDS))[META_SPEEDS.index(meta["speed"])],
                np.eye(len(META_DIRECTIONS))[META_DIRECTIONS.index(meta["direction"])],
            ]
        elif name == "ego_state":
            parts.append(np.array([anchor["ego_speed"] / 10.0, anchor["ego_accel"] / 3.0, anchor["ego_yaw_rate"]]))
        elif name == "command":
            parts.append(np.eye(len(COMMANDS))[COMMANDS.index(anchor["command"])])
        elif name == "velocity":
            parts.append(current_velocity(anchor) / 10.0)
        elif name == "past":
            past = np.asarray(anchor["ego_past"], dtype=np.float64).reshape(-1) / 10.0
            parts.append(past * np.repeat(np.asarray(anchor["ego_past_mask"], dtype=np.float64), 2))
        elif name in ROAD_INPUTS:
            parts.append(road_features(anchor, name))
    return np.concatenate(parts).astype(np.float32)


#: The head's inputs read from the frame's ``road``, and their widths.
ROAD_INPUTS = {"route": 2 * len(ROUTE_INPUT_ARC), "lead": 4, "pedestrian": 4, "stop_line": 7, "curvature": 1}
#: Beyond these the road's distances read as "nothing ahead" (m), its speeds are scaled by 10 m/s.
_FAR, _SPEED = 60.0, 10.0


def road_features(anchor: dict, name: str) -> np.ndarray:
    """One road input of a frame, scaled to about unit size, each with a flag saying there
    is one (a frame without ``road``, or with no lead, reads as none there): the route's
    points (ego frame); the lead's gap and speed; the nearest pedestrian in the corridor
    (distance, side offset, speed); the next stop line (distance, light one-hot, green left);
    the largest curvature ahead."""
    road = anchor.get("road")
    speed = float(anchor.get("ego_speed", 0.0))
    if name == "route":
        route = route_of(anchor)
        index = [ROUTE_ARC.index(a) for a in ROUTE_INPUT_ARC]
        return (route[index] / 10.0).reshape(-1)
    if name == "curvature":
        return np.array([10.0 * float(road["curvature"]) if road is not None else 0.0])
    item = None if road is None else road.get(name)
    if name == "lead":
        values = (
            [1.0, min(item["gap"], _FAR) / _FAR, item["speed"] / _SPEED, _braking(speed - item["speed"], item["gap"])]
            if item
            else [0.0, 1.0, 0.0, 0.0]
        )
    elif name == "pedestrian":
        values = (
            [1.0, min(item["distance"], _FAR) / _FAR, item["offset"] / 3.0, item["speed"] / _SPEED]
            if item
            else [0.0, 1.0, 0.0, 0.0]
        )
    else:  # stop_line
        if item:
            light = [float(item["light"] == state) for state in ("green", "amber", "red")]
            values = [
                1.0,
                min(item["distance"], _FAR) / _FAR,
                *light,
                max(item["green_left"], -1.0) / 10.0,
                _braking(speed, item["distance"]),
            ]
        else:
            values = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    return np.asarray(values, dtype=np.float64)


def _braking(closing: float, gap: float) -> float:
    """The deceleration (in units of 5 m/s^2, at most 2) that stops a closing speed within a
    gap: how hard the expert must brake for a line or a lead, which the distance and the
    speed alone make the head work out."""
    return min(max(closing, 0.0) ** 2 / (2 * max(gap, 0.5)) / 5.0, 2.0)


def feature_size(inputs: list[str] | tuple[str, ...]) -> int:
    """The length of ``ego_features`` (the visual summary apart)."""
    sizes = {
        "meta_action": len(META_SPEEDS) + len(META_DIRECTIONS),
        "ego_state": 3,
        "command": len(COMMANDS),
        "velocity": 2,
        "past": 2 * PAST_STEPS,
        **ROAD_INPUTS,
        "visual": 0,
        "scene": 0,
    }
    return sum(sizes[n] for n in HEAD_INPUTS if n in inputs)


class MetaActionPlanner(Planner):
    """The head, the frozen world model's outputs it reads (cached per clip), and its
    validation metrics (see the module docstring)."""

    def closed_loop_refusal(self) -> str | None:
        if self.cfg.meta_source == "generated" or "meta_action" not in self.inputs:
            return None
        return (
            "this planning head plans on the logged meta action (model.meta_source: ground_truth), which "
            "closed-loop driving does not have; train it with meta_source: generated"
        )

    def __init__(
        self,
        cfg: MetaActionPlannerConfig,
        teacher: WorldEngine | None,
        data_root: str,
        cache_dir: Path,
        where: str,
        sidecar_reference: bool = True,
    ):
        """``teacher``: the consumed world model (None when the head reads nothing of it);
        ``sidecar_reference``: its reference meta action is the frame sidecar's (OccVLA
        labels its own from the poses)."""
        super().__init__()
        self.cfg, self.data_root, self.inputs = cfg, data_root, list(cfg.inputs)
        #: What the head's waypoints add to (``prior_plan``).
        self.prior = head_prior(cfg.prior, self.inputs)
        self.sidecar_reference = sidecar_reference
        #: The world model's summary the head reads (``SUMMARIES``), if any.
        self.reads_summary = next((n for n in SUMMARIES if n in self.inputs), None)
        if teacher is not None:
            self._check_teacher(teacher, where)
        self.teacher = teacher
        visual_dim = 0
        if self.reads_summary is not None:
            if teacher is None:
                raise ConfigError(
                    f"{where}: model.inputs '{self.reads_summary}' reads a world model's outputs, and it has none"
                )
            visual_dim = teacher.world.hidden_size
        self.head = PlanningHead(
            feature_size(self.inputs),
            cfg.hidden,
            cfg.layers,
            FUTURE_STEPS,
            cfg.dropout,
            visual_dim,
            cfg.visual_width,
            along_route=self.prior == ALONG_ROUTE,
        )
        self._teacher_out: dict[str, dict] = {}  # sample token -> the frozen model's outputs
        self._cache_file = cache_dir / f"{TEACHER_CACHE}.json"
        self._load_teacher_cache()
        self.parsed = MeanMetric()
        #: The head's metric: on the reference meta action (and ``head_generated_meta`` on the
        #: generated one), or plain ``head`` when it reads no meta action.
        self.head_name = "head_gt_meta" if "meta_action" in self.inputs else "head"
        self.monitor = f"val/{self.head_name}_L2_stp3_avg"
        self.metrics = nn.ModuleDict(
            plan_metrics(
                (
                    self.head_name,
                    "head_generated_meta",
                    "llm_action_tokens",
                    "constant_velocity",
                    "constant_acceleration",
                    "constant_acceleration_along_route",
                    "baseline_stationary",
                )
            )
        )

    def _check_teacher(self, teacher: WorldEngine, where: str) -> None:
        family = teacher.family
        for op in ("reference_meta_action", "generated_meta_actions") if "meta_action" in self.inputs else ():
            if teacher.operation(op) is None:
                raise ConfigError(
                    f"{where}: the '{family}' world model generates no meta action; set model.meta_source=ground_truth"
                )
        if self.reads_summary == "scene" and teacher.operation("scene_summary") is None:
            raise ConfigError(f"{where}: model.inputs 'scene': the '{family}' world model offers no scene_summary")
        if self.reads_summary == "visual" and (teacher.vision is None or teacher.operation("visual_summary") is None):
            raise ConfigError(
                f"{where}: model.inputs 'visual' reads image tokens, which the '{family}' world model has none of"
            )

    @property
    def device(self) -> torch.device:
        return next(self.head.parameters()).device

    def sidecar_tasks(self) -> list[str]:
        """The frame-sidecar annotations it reads: the meta action, unless the world model labels its own."""
        return ["meta_action"] if self.teacher is None or self.sidecar_reference else []

    # -- the teacher's outputs, computed once per clip and kept on disk
    def _load_teacher_cache(self) -> None:
        """Per sample token: ``generated`` ([meta action or None, waypoints or None], or None
        where the chain of thought does not apply) and ``visual``."""
        if self.teacher is None or not self._cache_file.is_file():
            return
        from safetensors.torch import load_file

        # Reference meta actions are read from each clip as it comes (caches before kept them).
        kept = json.loads(self._cache_file.read_text())
        self._teacher_out = {t: {k: v for k, v in o.items() if k != "reference"} for t, o in kept.items()}
        visual_file = self._cache_file.with_suffix(".safetensors")
        for token, vis in (load_file(str(visual_file)) if visual_file.is_file() else {}).items():
            self._teacher_out.setdefault(token, {})["visual"] = vis.numpy()

    def save_cache(self) -> None:
        if self.teacher is None or not is_rank_zero():
            return
        visual = {t: torch.as_tensor(o["visual"]) for t, o in self._teacher_out.items() if "visual" in o}
        if visual:
            atomic_write_safetensors(self._cache_file.with_suffix(".safetensors"), visual)
        atomic_write_json(
            self._cache_file, {t: {k: v for k, v in o.items() if k != "visual"} for t, o in self._teacher_out.items()}
        )

    def teacher_outputs(self, clips: list[Clip], generate: bool) -> list[dict]:
        """The frozen model's outputs for each clip (the generated meta action only with
        ``generate``), from the cache or computed now and kept; and the clip's reference meta
        action, read afresh: it comes from the clip's annotated future, and a frame met in
        closed loop (its future unknown) is labelled later under the same token."""
        outs = [self._teacher_out.setdefault(c.anchor["token"], {}) for c in clips]
        teacher = self.teacher
        if teacher is None:
            raise ValueError("this planning head reads no world model: it has no outputs of one")
        reference = self._operation(teacher, "reference_meta_action")
        todo = [i for i, o in enumerate(outs) if "visual" not in o] if self.reads_summary is not None else []
        if todo and self.reads_summary is not None:
            summary = self._operation(teacher, SUMMARIES[self.reads_summary])(teacher, [clips[i] for i in todo])
            for i, vis in zip(todo, summary.cpu().numpy()):
                outs[i]["visual"] = vis
        todo = [i for i, o in enumerate(outs) if "generated" not in o] if generate else []
        if todo:
            generated = self._operation(teacher, "generated_meta_actions")(teacher, [clips[i] for i in todo])
            for i, gen in zip(todo, generated):
                outs[i]["generated"] = (
                    None if gen is None else [gen[0], None if gen[1] is None else np.asarray(gen[1]).tolist()]
                )
        return [{**out, "reference": reference(teacher, clip)} for out, clip in zip(outs, clips)]

    @staticmethod
    def _operation(teacher: WorldEngine, name: str) -> Callable[..., Any]:
        """The world model's operation ``name`` (checked at build: ``_check_teacher``)."""
        op = teacher.operation(name)
        if op is None:
            raise ValueError(f"the '{teacher.family}' world model has no '{name}' operation")
        return op

    def prepare_training(self, device: torch.device) -> None:
        """The teacher's outputs for the training clips, once, when the head trains on
        generated meta actions or reads visual tokens (validation's come as its batches do)."""
        generate = self.cfg.train_meta == "generated"
        if self.teacher is None or not (generate or self.reads_summary is not None):
            return
        index = DatasetIndex.open(self.data_root)
        clips = list(
            frame_clips(index, "train", self.teacher.tasks.context_frames, FUTURE_STEPS, partial_history=False)
        )
        self.teacher.to(device)
        with progress_bar(
            len(clips), f"the world model's {'meta actions' if generate else 'outputs'} on the train split, once"
        ) as advance:
            for i in range(0, len(clips), 16):
                self.teacher_outputs(clips[i : i + 16], generate)
                advance(len(clips[i : i + 16]))
        self.save_cache()

    # -- the head
    def _features(self, clips: list[Clip], source: str) -> tuple[dict[str, torch.Tensor], list[int]]:
        """The head's inputs (``features``, and ``visual`` / ``velocity`` where it reads them)
        for the clips that have a meta action from ``source``, and their rows."""
        device = self.device
        reads_meta = "meta_action" in self.inputs
        teacher = self.teacher is not None and (reads_meta or self.reads_summary is not None)
        outs = self.teacher_outputs(clips, reads_meta and source == "generated") if teacher else [None] * len(clips)
        feats, visual, rows = [], [], []
        for i, (clip, out) in enumerate(zip(clips, outs)):
            if not reads_meta:
                meta = None
            elif out is None:
                meta = clip.anchor.get("meta_action")
            elif source == "generated":
                meta = out["generated"][0] if out["generated"] is not None else None
            else:
                meta = out["reference"]
            if reads_meta and meta is None:
                continue
            feats.append(ego_features(clip.anchor, meta, self.inputs))
            if self.reads_summary is not None:
                assert out is not None  # a head that reads a summary has a teacher (checked at build)
                visual.append(np.asarray(out["visual"], dtype=np.float32))
            rows.append(i)

        def stack(arrays: list[np.ndarray], width: int) -> torch.Tensor:
            return torch.from_numpy(np.stack(arrays)).to(device) if arrays else torch.zeros(0, width, device=device)

        inputs: dict[str, Any] = {"features": stack(feats, feature_size(self.inputs))}
        if self.reads_summary is not None:
            inputs["visual"] = stack(visual, self.head.visual_dim)
        anchors = [clips[i].anchor for i in rows]
        if self.prior == ALONG_ROUTE:
            inputs["route"] = route_prior(anchors, device)
        elif rows and (base := prior_plan(anchors, self.prior, device)) is not None:
            inputs["base"] = base
        return inputs, rows

    def training_loss(self, clips: list[Clip]) -> torch.Tensor:
        """The head's loss on the clips with a meta action (zero through the head when none
        has one: DDP's gradients stay in step)."""
        x, rows = self._features(clips, self.cfg.train_meta)
        if not rows:
            return self.head(**x).sum() * 0.0 if self.prior != ALONG_ROUTE else x["features"].sum() * 0.0
        gt = plan_target([clips[i].anchor for i in rows], x["features"].device)
        err = self.head(**x) - gt.traj
        if self.cfg.loss == "mse":
            per_point = err.pow(2).sum(-1)
        elif self.cfg.loss == "l1":
            per_point = err.abs().sum(-1)
        else:
            per_point = torch.nn.functional.huber_loss(err, torch.zeros_like(err), reduction="none", delta=1.0).sum(-1)
        return (per_point * gt.mask).sum() / gt.mask.sum().clamp(min=1)

    def validate(self, clips: list[Clip], batch_idx: int, generate_batches: int = -1) -> None:
        anchors = [c.anchor for c in clips]
        gt = plan_target(anchors, self.device)
        subsets = subset_rows(anchors, gt)

        def record(name: str, pred: torch.Tensor, rows: list[int]) -> None:
            update_plans(self.metrics, name, pred, gt, subsets, rows)

        x, rows = self._features(clips, "ground_truth")
        record(self.head_name, self.head(**x), rows)
        everyone = list(range(len(anchors)))
        record("constant_velocity", constant_velocity(anchors, gt.traj.device), everyone)
        record("constant_acceleration", constant_acceleration(anchors, gt.traj.device), everyone)
        along = prior_plan(anchors, ALONG_ROUTE, gt.traj.device)
        assert along is not None
        record("constant_acceleration_along_route", along, everyone)
        record("baseline_stationary", torch.zeros_like(gt.traj), everyone)
        if (
            self.teacher is not None
            and "meta_action" in self.inputs
            and self.cfg.meta_source == "generated"
            and (generate_batches < 0 or batch_idx < generate_batches)
        ):
            outs = self.teacher_outputs(clips, generate=True)
            applies = [i for i, o in enumerate(outs) if o["generated"] is not None]
            x, rows = self._features(clips, "generated")
            # Clips the chain of thought does not apply to are skipped, not scored as a zero plan.
            record("head_generated_meta", self.head(**x), rows)
            tokens = [i for i in applies if outs[i]["generated"][1] is not None]
            if tokens:
                plans = torch.stack([torch.as_tensor(outs[i]["generated"][1], dtype=torch.float32) for i in tokens]).to(
                    gt.traj.device
                )
                record("llm_action_tokens", plans, tokens)
            if applies:
                self.parsed.update(
                    sum(outs[i]["generated"][0] is not None for i in applies) / len(applies), len(applies)
                )

    @torch.no_grad()
    def waypoints(self, clips: list[Clip]) -> Plans:
        """The head's plan on the meta action it is scored on (``meta_source``); a clip
        without one (the chain of thought did not end in a meta action) drives on at
        constant velocity, and is marked as fallen back."""
        plans = constant_velocity([c.anchor for c in clips], self.device)
        generated = self.teacher is not None and self.cfg.meta_source == "generated" and "meta_action" in self.inputs
        source = "generated" if generated else "ground_truth"
        x, rows = self._features(clips, source)
        if rows:
            plans[rows] = self.head(**x)
        fell_back = np.ones(len(clips), dtype=bool)
        fell_back[rows] = False
        return Plans(plans.cpu().numpy().astype(np.float64), fell_back)

    def compute(self, prefix: str) -> dict[str, float]:
        """The validation metrics that saw samples, then reset."""
        return compute_metrics(prefix, reset=True, metrics={**self.metrics, "meta_parsed_fraction": self.parsed})

    def summary(self) -> tuple[str, dict[str, float]]:
        n = count_parameters(self.head)
        prior = f", written against {self.prior.replace('_', ' ')}" if self.prior != "none" else ""
        return f"planning head {n / 1e3:.1f}K params, inputs {', '.join(self.inputs)}{prior}", {"params": float(n)}

    def export(self, path: Path) -> Path:
        cfg = self.cfg
        config = {
            "stage_kind": "planner",
            "features": feature_size(self.inputs),
            "visual_dim": self.head.visual_dim,
            "visual_width": cfg.visual_width,
            "hidden": cfg.hidden,
            "layers": cfg.layers,
            "inputs": self.inputs,
            "train_meta": cfg.train_meta,
            "prior": self.prior,
            "loss": cfg.loss,  # what a dagger stage fine-tunes it with
            "steps": FUTURE_STEPS,
        }
        return write_export(path, self.head.state_dict(), config)


def meta_action_planner(
    ctx: PlannerContext, teacher: WorldEngine | None, sidecar_reference: bool = True
) -> MetaActionPlanner:
    """The planner of a planner stage (``WorldSpec.planner``) from its context."""
    where = f"stages '{ctx.spec.name}'"
    # The stage's structured config, read by attribute as the dataclass it was made from.
    cfg = cast(MetaActionPlannerConfig, ctx.model_cfg)
    return MetaActionPlanner(cfg, teacher, ctx.data.root, ctx.cache_dir, where, sidecar_reference)


def load_meta_action_planner(
    export_dir: Path, teacher: WorldEngine, data_root: str, cache_dir: Path, sidecar_reference: bool = True
) -> MetaActionPlanner:
    """A trained head back from its export, over the consumed world model (``occtrain eval``)."""
    from occtrain.formats.exports import load_state_strict, read_export

    state, config = read_export(export_dir)
    cfg = MetaActionPlannerConfig(
        hidden=config["hidden"],
        layers=config["layers"],
        inputs=list(config["inputs"]),
        visual_width=config["visual_width"],
        train_meta=config.get("train_meta", "ground_truth"),
        prior=config.get("prior"),  # unset in exports before it: what the inputs implied
        loss=config.get("loss", "mse"),
    )
    planner = MetaActionPlanner(cfg, teacher, data_root, cache_dir, str(export_dir), sidecar_reference)
    load_state_strict(planner.head, state, (), str(export_dir))
    return planner.eval()

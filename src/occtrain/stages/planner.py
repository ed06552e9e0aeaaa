"""Stage kind ``planner``: OccVLA's MLP planning head on the meta action (Sec. 3.3-3.4).

The head maps the meta action (speed x direction) and the inputs a recipe names
(``model.inputs``: OccVLA's current velocity, averaged visual tokens of the consumed model
and past trajectory, with no driving command; the OccLLaMA chain's sidecar ego state and
command) to the 6 future waypoints, trained with MSE. It trains on the reference meta
actions or, as in OccVLA's stage 3, on those the consumed model generates for the training
clips (generated once at the start and cached in the stage directory). Validation reports
it with the reference and with the generated meta action, beside the consumed model's own
action-token plan (OccLLaMA) and the constant-velocity baseline, on the same samples.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from occtrain.data.clips import Clip, clips_from_batch, plan_target
from occtrain.data.schema import COMMANDS, META_DIRECTIONS, META_SPEEDS
from occtrain.engine import TEXT_ENTRIES, load_world_model
from occtrain.errors import ConfigError
from occtrain.exports import write_export
from occtrain.metrics import PlanningMetric, flatten_metrics
from occtrain.models import count_parameters
from occtrain.models.planner import PlanningHead, constant_velocity_plan
from occtrain.io import atomic_write_json, atomic_write_safetensors, is_rank_zero
from occtrain.occ3d import FRAME_DT, FUTURE_STEPS, PAST_STEPS
from occtrain.stages import StageKind, register
from occtrain.stages.base import Stage, StageContext, StageReport
from occtrain.stages.common import ValidationMeans, configure_adamw

META_SOURCES = ("ground_truth", "generated")
#: What the head may read, in the order its input vector lays them out.
HEAD_INPUTS = ("meta_action", "ego_state", "command", "velocity", "past", "visual")
#: Where the cached teacher outputs live in the stage directory.
TEACHER_CACHE = "teacher_outputs"


@dataclass
class PlannerModelConfig:
    """``model:`` of a planner stage."""

    hidden: int = 256
    layers: int = 3
    dropout: float = 0.1
    #: What the head reads (``HEAD_INPUTS``): the meta action (one-hot speed and direction),
    #: the ego state of the frame sidecar (speed, acceleration, yaw rate), the driving
    #: command, the ego's current velocity from its last move, its past waypoints, and
    #: ``visual``, the consumed world model's outputs at its image tokens, averaged
    #: (OccVLA: meta action, velocity, visual tokens and past trajectory; no command).
    inputs: list[str] = field(default_factory=lambda: ["meta_action", "ego_state", "command"])
    loss: str = "mse"  # mse | l1
    #: The meta action the head trains on: the reference (``ground_truth``) or the one the
    #: consumed model generates for each training clip (``generated``, OccVLA's stage 3;
    #: generated once and cached in the stage directory).
    train_meta: str = "ground_truth"
    #: Width of the bottleneck the visual summary passes through (see ``PlanningHead``).
    visual_width: int = 8
    #: Where validation takes the meta action from: the annotation, or the consumed
    #: model's generated chain of thought (both are always reported when possible).
    meta_source: str = "generated"
    #: Validation batches that run the instruct model's generation (-1: all of them). The
    #: model is frozen, so each clip's chain of thought is generated once and reused.
    generate_batches: int = -1
    #: The generation length of the chain of thought; 0: what the consumed model trained with.
    max_new_text_tokens: int = 0


def ego_features(anchor: dict, meta: dict, inputs: list[str] | tuple[str, ...]) -> np.ndarray:
    """The head's input vector: the ``inputs`` in ``HEAD_INPUTS`` order (the visual summary
    goes in apart, through the head's bottleneck)."""
    parts = []
    for name in HEAD_INPUTS:
        if name not in inputs:
            continue
        if name == "meta_action":
            parts += [np.eye(len(META_SPEEDS))[META_SPEEDS.index(meta["speed"])], np.eye(len(META_DIRECTIONS))[META_DIRECTIONS.index(meta["direction"])]]
        elif name == "ego_state":
            parts.append(np.array([anchor["ego_speed"] / 10.0, anchor["ego_accel"] / 3.0, anchor["ego_yaw_rate"]]))
        elif name == "command":
            parts.append(np.eye(len(COMMANDS))[COMMANDS.index(anchor["command"])])
        elif name == "velocity":
            parts.append(current_velocity(anchor) / 10.0)
        elif name == "past":
            past = np.asarray(anchor["ego_past"], dtype=np.float64).reshape(-1) / 10.0
            parts.append(past * np.repeat(np.asarray(anchor["ego_past_mask"], dtype=np.float64), 2))
    return np.concatenate(parts).astype(np.float32)


def current_velocity(anchor: dict) -> np.ndarray:
    """(2,) m/s in the ego frame: the speed (the sidecar's, else the last move's) along the
    direction of the last move (from the last past waypoint to here; +x without one)."""
    past = np.asarray(anchor.get("ego_past", []), dtype=np.float64).reshape(-1, 2)
    mask = np.asarray(anchor.get("ego_past_mask", []), dtype=bool)
    move = -past[-1] if len(past) and mask[-1] else np.zeros(2)
    norm = float(np.linalg.norm(move))
    speed = float(anchor["ego_speed"]) if "ego_speed" in anchor else norm / FRAME_DT
    return speed * (move / norm if norm > 1e-3 else np.array([1.0, 0.0]))


def feature_size(inputs: list[str] | tuple[str, ...]) -> int:
    """The length of ``ego_features`` (the visual summary apart)."""
    sizes = {
        "meta_action": len(META_SPEEDS) + len(META_DIRECTIONS), "ego_state": 3, "command": len(COMMANDS),
        "velocity": 2, "past": 2 * PAST_STEPS, "visual": 0,
    }
    return sum(sizes[n] for n in HEAD_INPUTS if n in inputs)


class PlannerStage(Stage):
    """Trains the planning head; validates it against the baselines with both L2 conventions."""

    consumes_kinds = ("pretrain", "instruct", "distill")
    consumes_count = (0, 1)
    frozen_prefixes = ("teacher.",)  # the world model is read-only here: checkpoints hold the head

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        where = f"stages '{ctx.spec.name}'"
        if cfg.loss not in ("mse", "l1"):
            raise ConfigError(f"{where}: model.loss '{cfg.loss}' is not one of mse, l1")
        for key in ("meta_source", "train_meta"):
            if cfg[key] not in META_SOURCES:
                raise ConfigError(f"{where}: model.{key} '{cfg[key]}' is not one of {', '.join(META_SOURCES)}")
        self.inputs = list(cfg.inputs)
        unknown = [n for n in self.inputs if n not in HEAD_INPUTS]
        if unknown or not self.inputs:
            raise ConfigError(f"{where}: model.inputs {self.inputs} must name some of {', '.join(HEAD_INPUTS)}")
        if "meta_action" not in self.inputs:
            raise ConfigError(f"{where}: model.inputs must include meta_action: the head plans from it")
        self.teacher = None
        needs_teacher = cfg.meta_source == "generated" or cfg.train_meta == "generated" or "visual" in self.inputs
        if needs_teacher:
            if not ctx.inputs:
                raise ConfigError(
                    f"{where}: model.meta_source/train_meta 'generated' and the 'visual' input read a world model; "
                    "add an instruct stage to consumes, or use ground_truth meta actions without visual input"
                )
            self.teacher = load_world_model(next(iter(ctx.inputs.values())))
            if cfg.max_new_text_tokens > 0:
                self.teacher.with_settings(max_new_text_tokens=cfg.max_new_text_tokens)
            if not {"cot_planning", "meta_action"} & set(self.teacher.task_builders):
                raise ConfigError(
                    f"{where}: the '{self.teacher.family}' world model generates no meta action; set model.meta_source=ground_truth"
                )
            if "visual" in self.inputs and self.teacher.vision is None:
                raise ConfigError(f"{where}: model.inputs 'visual' reads image tokens, which the '{self.teacher.family}' world model has none of")
            self.teacher.requires_grad_(False).eval()
            self.teacher.prepare_inputs(ctx.data.root, ctx.stage_dir / "cache")
        if self.teacher is None or "meta_action" not in self.teacher.task_builders:
            # The sidecar's meta action (and ego state); OccVLA labels its own from the poses.
            self.require_tasks(["meta_action"], instead="leave the planner stage out of the recipe")
        visual_dim = self.teacher.world.hidden_size if "visual" in self.inputs else 0
        self.head = PlanningHead(feature_size(self.inputs), cfg.hidden, cfg.layers, FUTURE_STEPS, cfg.dropout, visual_dim, cfg.visual_width)
        self._teacher_out: dict[str, dict] = {}  # sample token -> the frozen model's outputs
        self._cache_file = ctx.stage_dir / "cache" / f"{TEACHER_CACHE}.json"
        self._load_teacher_cache()
        self.val_means = ValidationMeans("val/meta_parsed_fraction")
        self.metrics = torch.nn.ModuleDict({
            name: PlanningMetric()
            for name in ("head_gt_meta", "head_generated_meta", "llm_action_tokens", "constant_velocity", "baseline_stationary")
        })

    def entries(self, split: str) -> tuple[str, ...] | None:
        # The teacher's prompts read the text entries; its scenes or images come from its caches.
        return TEXT_ENTRIES if self.teacher is not None else ("ann.json",)

    # -- the teacher's outputs, computed once per clip and kept on disk
    def _load_teacher_cache(self) -> None:
        """Per sample token: ``reference`` (meta action), ``generated`` ([meta action or None,
        waypoints or None], or None where the chain of thought does not apply) and ``visual``."""
        if self.teacher is None or not self._cache_file.is_file():
            return
        from safetensors.torch import load_file

        self._teacher_out = json.loads(self._cache_file.read_text())
        visual_file = self._cache_file.with_suffix(".safetensors")
        for token, vis in (load_file(str(visual_file)) if visual_file.is_file() else {}).items():
            self._teacher_out.setdefault(token, {})["visual"] = vis.numpy()

    def _save_teacher_cache(self) -> None:
        if self.teacher is None or not is_rank_zero():
            return
        visual = {t: torch.as_tensor(o["visual"]) for t, o in self._teacher_out.items() if "visual" in o}
        if visual:
            atomic_write_safetensors(self._cache_file.with_suffix(".safetensors"), visual)
        atomic_write_json(self._cache_file, {t: {k: v for k, v in o.items() if k != "visual"} for t, o in self._teacher_out.items()})

    def teacher_outputs(self, clips: list[Clip], generate: bool) -> list[dict]:
        """The frozen model's outputs for each clip (the generated meta action only with
        ``generate``), from the cache or computed now and kept."""
        outs = [self._teacher_out.setdefault(c.anchor["token"], {}) for c in clips]
        todo = [i for i, o in enumerate(outs) if "reference" not in o]
        for i in todo:
            outs[i]["reference"] = self.teacher.reference_meta_action(clips[i])
        todo = [i for i, o in enumerate(outs) if "visual" not in o] if "visual" in self.inputs else []
        if todo:
            for i, vis in zip(todo, self.teacher.visual_summary([clips[i] for i in todo]).cpu().numpy()):
                outs[i]["visual"] = vis
        todo = [i for i, o in enumerate(outs) if "generated" not in o] if generate else []
        if todo:
            for i, gen in zip(todo, self.teacher.generated_meta_actions([clips[i] for i in todo])):
                outs[i]["generated"] = None if gen is None else [gen[0], None if gen[1] is None else np.asarray(gen[1]).tolist()]
        return outs

    def on_fit_start(self) -> None:
        """Compute the teacher's outputs for the training clips once, when the head trains on
        generated meta actions or reads visual tokens (validation's come as its batches do)."""
        if self.teacher is None:
            return
        from occtrain.data.clips import frame_clips
        from occtrain.data.layout import DatasetIndex
        from occtrain.progress import progress_bar

        generate = self.ctx.model_cfg.train_meta == "generated"
        if not generate and "visual" not in self.inputs:
            return
        index = DatasetIndex.open(self.ctx.data.root)
        clips = list(frame_clips(index, "train", self.teacher.tasks.context_frames, FUTURE_STEPS, partial_history=False))
        self.teacher.to(self.device)
        with progress_bar(len(clips), f"the world model's {'meta actions' if generate else 'outputs'} on the train split, once") as advance:
            for i in range(0, len(clips), 16):
                self.teacher_outputs(clips[i : i + 16], generate)
                advance(len(clips[i : i + 16]))
        self._save_teacher_cache()

    # -- data
    def _features(self, clips: list[Clip], source: str) -> tuple[dict[str, torch.Tensor], list[int]]:
        """The head's inputs (``features``, and ``visual`` / ``velocity`` where it reads them)
        for the clips that have a meta action from ``source``, and their rows."""
        outs = self.teacher_outputs(clips, source == "generated") if self.teacher is not None else [None] * len(clips)
        feats, visual, velocity, rows = [], [], [], []
        for i, (clip, out) in enumerate(zip(clips, outs)):
            if out is None:
                meta = clip.anchor.get("meta_action")
            elif source == "generated":
                meta = out["generated"][0] if out["generated"] is not None else None
            else:
                meta = out["reference"]
            if meta is None:
                continue
            feats.append(ego_features(clip.anchor, meta, self.inputs))
            if "visual" in self.inputs:
                visual.append(np.asarray(out["visual"], dtype=np.float32))
            velocity.append(current_velocity(clip.anchor).astype(np.float32))
            rows.append(i)

        def stack(arrays: list[np.ndarray], width: int) -> torch.Tensor:
            return torch.from_numpy(np.stack(arrays)).to(self.device) if arrays else torch.zeros(0, width, device=self.device)

        inputs = {"features": stack(feats, feature_size(self.inputs))}
        if "visual" in self.inputs:
            inputs["visual"] = stack(visual, self.head.visual[0].normalized_shape[0])
        if "velocity" in self.inputs:
            inputs["velocity"] = stack(velocity, 2)
        return inputs, rows

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        clips = clips_from_batch({"qa": [[]] * len(batch["ann"]), "narration": [""] * len(batch["ann"]), **batch})
        x, rows = self._features(clips, self.ctx.model_cfg.train_meta)
        self.log("train/meta_rows", float(len(rows)), reduce_fx="sum", batch_size=len(clips))
        if not rows:
            # No clip has a (parsed) meta action: a zero loss through the head keeps DDP's gradients in step.
            return self.head(**x).sum() * 0.0
        gt = plan_target([clips[i].anchor for i in rows], self.device)
        err = self.head(**x) - gt.traj
        per_point = err.pow(2).sum(-1) if self.ctx.model_cfg.loss == "mse" else err.abs().sum(-1)
        loss = (per_point * gt.mask).sum() / gt.mask.sum().clamp(min=1)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(rows))
        return loss

    # -- validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        clips = clips_from_batch({"qa": [[]] * len(batch["ann"]), "narration": [""] * len(batch["ann"]), **batch})
        anchors = [c.anchor for c in clips]
        gt = plan_target(anchors, self.device)

        def record(name: str, pred: torch.Tensor, rows: list[int]) -> None:
            if rows:
                sub = gt.rows(rows)
                self.metrics[name].update(pred, sub.traj, sub.mask, sub.agents)

        x, rows = self._features(clips, "ground_truth")
        record("head_gt_meta", self.head(**x), rows)
        speeds = torch.tensor([float(np.linalg.norm(current_velocity(a))) if "ego_speed" not in a else a["ego_speed"] for a in anchors], device=self.device)
        everyone = list(range(len(anchors)))
        record("constant_velocity", constant_velocity_plan(speeds, FUTURE_STEPS), everyone)
        record("baseline_stationary", torch.zeros_like(gt.traj), everyone)
        limit = self.ctx.model_cfg.generate_batches
        if self.teacher is not None and self.ctx.model_cfg.meta_source == "generated" and (limit < 0 or batch_idx < limit):
            outs = self.teacher_outputs(clips, generate=True)
            applies = [i for i, o in enumerate(outs) if o["generated"] is not None]
            x, rows = self._features(clips, "generated")
            # Clips the chain of thought does not apply to are skipped, not scored as a zero plan.
            record("head_generated_meta", self.head(**x), rows)
            tokens = [i for i in applies if outs[i]["generated"][1] is not None]
            if tokens:
                plans = torch.stack([torch.as_tensor(outs[i]["generated"][1], dtype=torch.float32) for i in tokens]).to(self.device)
                record("llm_action_tokens", plans, tokens)
            if applies:
                parsed = sum(outs[i]["generated"][0] is not None for i in applies)
                self.val_means.update("val/meta_parsed_fraction", parsed / len(applies), len(applies))

    def on_validation_epoch_end(self) -> None:
        for name, metric in self.metrics.items():
            if metric.update_count == 0:
                continue
            self.log_dict(flatten_metrics(f"val/{name}", metric.compute()))
            metric.reset()
        self.log_dict(self.val_means.pop())

    def on_train_end(self) -> None:
        self._save_teacher_cache()  # clips first met in training (a shorter history) join the cache

    def configure_optimizers(self) -> dict:
        return configure_adamw(self.head.parameters(), self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def report(self) -> StageReport:
        n = count_parameters(self.head)
        return StageReport(f"planning head {n / 1e3:.1f}K params, inputs {', '.join(self.inputs)}", {"params": float(n)})

    def export(self, path: Path) -> Path:
        cfg = self.ctx.model_cfg
        config = {
            "stage_kind": "planner",
            "features": feature_size(self.inputs),
            "visual_dim": self.head.visual[0].normalized_shape[0] if self.head.visual is not None else 0,
            "visual_width": cfg.visual_width,
            "hidden": cfg.hidden,
            "layers": cfg.layers,
            "inputs": self.inputs,
            "train_meta": cfg.train_meta,
            "steps": FUTURE_STEPS,
        }
        return write_export(path, self.head.state_dict(), config)


PLANNER = register(
    StageKind(
        name="planner", model_schema=PlannerModelConfig, data_kind="clips", module=PlannerStage,
        monitor="val/head_gt_meta_L2_stp3_avg", mode="min",
    )
)

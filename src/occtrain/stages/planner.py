"""Stage kind ``planner``: OccVLA's MLP planning head on meta action and ego state.

The head maps the meta action (speed x direction), the ego state (speed, acceleration,
yaw rate, driving command) and optionally the ego's past waypoints to the 6 future
waypoints. It trains on ground-truth meta actions; validation reports it with the
ground-truth meta action and, when the stage consumes an instruct stage, with the meta
action that model generates in its chain of thought, beside that model's own action-token
plan and the constant-velocity baseline, all on the same samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from occtrain.config.llm import MAX_NEW_TEXT_TOKENS
from occtrain.data.clips import clips_from_batch, plan_target
from occtrain.data.schema import COMMANDS, META_DIRECTIONS, META_SPEEDS
from occtrain.data.text_formats import parse_meta_action
from occtrain.engine import CODE_CACHE, TEXT_ENTRIES, CotOutput, load_world_model
from occtrain.errors import ConfigError
from occtrain.exports import write_export
from occtrain.metrics import PlanningMetric, flatten_metrics
from occtrain.models import count_parameters
from occtrain.models.planner import PlanningHead, constant_velocity_plan
from occtrain.occ3d import FUTURE_STEPS, PAST_STEPS
from occtrain.stages import StageKind, register
from occtrain.stages.base import Stage, StageContext, StageReport
from occtrain.stages.common import ValidationMeans, configure_adamw

META_SOURCES = ("ground_truth", "generated")


@dataclass
class PlannerModelConfig:
    """``model:`` of a planner stage."""

    hidden: int = 256
    layers: int = 3
    dropout: float = 0.1
    #: Feed the ego's past waypoints too (not in OccVLA; an option for ablations).
    use_past: bool = False
    loss: str = "mse"  # mse | l1
    #: Where validation takes the meta action from: the annotation, or the consumed
    #: instruct stage's generated chain of thought (both are always reported when possible).
    meta_source: str = "generated"
    #: Validation batches that run the instruct model's generation (-1: all of them). The
    #: model is frozen, so each clip's chain of thought is generated once and reused.
    generate_batches: int = -1
    max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS


def ego_features(anchor: dict, meta: dict, use_past: bool) -> np.ndarray:
    """The head's input vector: one-hot meta speed and direction, ego state, command, past."""
    speed = np.eye(len(META_SPEEDS))[META_SPEEDS.index(meta["speed"])]
    direction = np.eye(len(META_DIRECTIONS))[META_DIRECTIONS.index(meta["direction"])]
    command = np.eye(len(COMMANDS))[COMMANDS.index(anchor["command"])]
    state = np.array([anchor["ego_speed"] / 10.0, anchor["ego_accel"] / 3.0, anchor["ego_yaw_rate"]])
    parts = [speed, direction, state, command]
    if use_past:
        past = np.asarray(anchor["ego_past"], dtype=np.float64).reshape(-1) / 10.0
        parts.append(past * np.repeat(np.asarray(anchor["ego_past_mask"], dtype=np.float64), 2))
    return np.concatenate(parts).astype(np.float32)


def feature_size(use_past: bool) -> int:
    return len(META_SPEEDS) + len(META_DIRECTIONS) + 3 + len(COMMANDS) + (2 * PAST_STEPS if use_past else 0)


class PlannerStage(Stage):
    """Trains the planning head; validates it against the baselines with both L2 conventions."""

    consumes_kinds = ("pretrain", "instruct", "distill")
    consumes_count = (0, 1)
    frozen_prefixes = ("teacher.",)  # the world model is read-only here: checkpoints hold the head

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        if cfg.loss not in ("mse", "l1"):
            raise ConfigError(f"stages '{ctx.spec.name}': model.loss '{cfg.loss}' is not one of mse, l1")
        if cfg.meta_source not in META_SOURCES:
            raise ConfigError(f"stages '{ctx.spec.name}': model.meta_source '{cfg.meta_source}' is not one of {', '.join(META_SOURCES)}")
        # The head reads the meta action (and the teacher's chain of thought ends in one).
        self.require_tasks(["meta_action"], instead="leave the planner stage out of the recipe")
        self.head = PlanningHead(feature_size(cfg.use_past), cfg.hidden, cfg.layers, FUTURE_STEPS, cfg.dropout)
        self.teacher = None
        if cfg.meta_source == "generated":
            if not ctx.inputs:
                raise ConfigError(
                    f"stages '{ctx.spec.name}': model.meta_source 'generated' needs an instruct stage in consumes; "
                    "or set model.meta_source=ground_truth"
                )
            self.teacher = load_world_model(next(iter(ctx.inputs.values()))).with_settings(max_new_text_tokens=cfg.max_new_text_tokens)
            if "cot_planning" not in self.teacher.task_builders:
                raise ConfigError(
                    f"stages '{ctx.spec.name}': model.meta_source 'generated' reads a chain of thought, which the "
                    f"'{self.teacher.family}' world model has no task for; set model.meta_source=ground_truth"
                )
            self.teacher.requires_grad_(False).eval()
            self.teacher.build_code_cache(ctx.data.root, ctx.stage_dir / "cache" / CODE_CACHE)
        self._cot: dict[str, CotOutput | None] = {}  # sample token -> the frozen model's chain of thought
        self.val_means = ValidationMeans("val/meta_parsed_fraction")
        self.metrics = torch.nn.ModuleDict({
            name: PlanningMetric()
            for name in ("head_gt_meta", "head_generated_meta", "llm_action_tokens", "constant_velocity", "baseline_stationary")
        })

    def entries(self, split: str) -> tuple[str, ...] | None:
        # Training reads annotations only; validation also prompts the instruct model, whose
        # scenes come from the code cache.
        return TEXT_ENTRIES if split == "val" and self.teacher is not None else ("ann.json",)

    # -- data
    def _inputs(self, anchors: list[dict], metas: list[dict]) -> torch.Tensor:
        feats = [ego_features(a, m, self.ctx.model_cfg.use_past) for a, m in zip(anchors, metas)]
        return torch.from_numpy(np.stack(feats)).to(self.device)

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        anchors = [ann["anchor"] for ann in batch["ann"]]
        pred = self.head(self._inputs(anchors, [a["meta_action"] for a in anchors]))
        gt = plan_target(anchors, self.device)
        target, mask = gt.traj, gt.mask
        err = pred - target
        per_point = err.pow(2).sum(-1) if self.ctx.model_cfg.loss == "mse" else err.abs().sum(-1)
        loss = (per_point * mask).sum() / mask.sum().clamp(min=1)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(anchors))
        return loss

    # -- validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        anchors = [ann["anchor"] for ann in batch["ann"]]
        gt = plan_target(anchors, self.device)

        def record(name: str, pred: torch.Tensor, rows: list[int] | None = None) -> None:
            rows = list(range(len(anchors))) if rows is None else rows
            sub = gt.rows(rows)
            self.metrics[name].update(pred[rows], sub.traj, sub.mask, sub.agents)

        record("head_gt_meta", self.head(self._inputs(anchors, [a["meta_action"] for a in anchors])))
        speeds = torch.tensor([a["ego_speed"] for a in anchors], device=self.device)
        record("constant_velocity", constant_velocity_plan(speeds, FUTURE_STEPS))
        record("baseline_stationary", torch.zeros_like(gt.traj))
        limit = self.ctx.model_cfg.generate_batches
        if self.teacher is not None and (limit < 0 or batch_idx < limit):
            outputs = self._chain_of_thought(clips_from_batch(batch), batch)
            # Clips the chain of thought does not apply to are skipped, not scored as a zero plan.
            generated = [i for i, o in enumerate(outputs) if o is not None]
            metas = {i: parse_meta_action(outputs[i].text) for i in generated}
            rows = [i for i in generated if metas[i] is not None]
            if rows:
                pred = self.head(self._inputs([anchors[i] for i in rows], [metas[i] for i in rows]))
                full = torch.zeros_like(gt.traj)
                full[rows] = pred
                record("head_generated_meta", full, rows)
            if generated:
                tokens = torch.zeros_like(gt.traj)
                tokens[generated] = torch.stack([torch.as_tensor(outputs[i].waypoints, dtype=torch.float32) for i in generated]).to(self.device)
                record("llm_action_tokens", tokens, generated)
                self.val_means.update("val/meta_parsed_fraction", len(rows) / len(generated), len(generated))

    def _chain_of_thought(self, clips: list, batch: dict) -> list[CotOutput | None]:
        todo = [c for c in clips if c.anchor["token"] not in self._cot]
        if todo:
            rows = [i for i, c in enumerate(clips) if c.anchor["token"] not in self._cot]
            sub = {"ann": [batch["ann"][i] for i in rows]}
            for clip, out in zip(todo, self.teacher.chain_of_thought(todo, sub)):
                self._cot[clip.anchor["token"]] = out
        return [self._cot[c.anchor["token"]] for c in clips]

    def on_validation_epoch_end(self) -> None:
        for name, metric in self.metrics.items():
            if metric.update_count == 0:
                continue
            self.log_dict(flatten_metrics(f"val/{name}", metric.compute()))
            metric.reset()
        self.log_dict(self.val_means.pop())

    def configure_optimizers(self) -> dict:
        return configure_adamw(self.head.parameters(), self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def report(self) -> StageReport:
        n = count_parameters(self.head)
        return StageReport(f"planning head {n / 1e3:.1f}K params", {"params": float(n)})

    def export(self, path: Path) -> Path:
        cfg = self.ctx.model_cfg
        config = {
            "stage_kind": "planner",
            "features": feature_size(cfg.use_past),
            "hidden": cfg.hidden,
            "layers": cfg.layers,
            "use_past": cfg.use_past,
            "steps": FUTURE_STEPS,
        }
        return write_export(path, self.head.state_dict(), config)


PLANNER = register(
    StageKind(
        name="planner", model_schema=PlannerModelConfig, data_kind="clips", module=PlannerStage,
        monitor="val/head_gt_meta_L2_stp3_avg", mode="min",
    )
)

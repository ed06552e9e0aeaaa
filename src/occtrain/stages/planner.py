"""Stage kind ``planner``: the planner of the consumed world model's family.

The family's registration says what a planner stage trains (``WorldSpec.planner``: OccVLA's
MLP head on the meta action, or a family's own) and what settings it takes
(``WorldSpec.planner_config``, flat in ``model:`` beside this stage's own). The planner
reads the consumed world model, frozen, when its settings ask for it; this module only
wires it into Lightning.
"""

from __future__ import annotations

from dataclasses import dataclass, make_dataclass
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.config import to_object
from occtrain.core.protocols import PlannerSettings
from occtrain.core.registry import get_world
from occtrain.data.clips import clips_from_batch, frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.engine import TEXT_ENTRIES, WorldModelEngine, load_world_model
from occtrain.engine.closed_loop import StageDriver
from occtrain.engine.evaluator import fixed_subset
from occtrain.errors import ConfigError
from occtrain.formats.exports import read_config
from occtrain.formats.occ3d import FUTURE_STEPS
from occtrain.progress import progress_bar
from occtrain.stages import StageKind, register
from occtrain.stages.optim import configure_adamw
from occtrain.stages.stage import EvalRequest, EvalResult, Stage, StageContext, StageReport


@dataclass
class PlannerStageConfig(PlannerSettings):
    """What every planner stage takes, whatever its family's planner (whose settings,
    ``PlannerSettings`` too, a stage's schema joins to these)."""

    #: Validation batches that run the world model's generation (-1: all of them). The
    #: model is frozen, so each clip's outputs are generated once and reused.
    generate_batches: int = -1
    #: The world model's generation length; 0: what it trained with.
    max_new_text_tokens: int = 0


class PlannerStage(Stage):
    """Trains the family's planner; validates it against the baselines with both L2 conventions."""

    count_flops = True
    consumes_kinds = ("pretrain", "instruct", "distill")
    consumes_count = (1, 1)
    frozen_prefixes = ("planner.teacher.",)  # the world model is read-only here: checkpoints hold the planner

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        """This stage's settings with the family planner's beside them."""
        if family is None:
            return kind.model_schema
        own = get_world(family).planner_config
        return (
            make_dataclass(f"PlannerModelConfig_{family}", [], bases=(own, kind.model_schema))
            if own
            else kind.model_schema
        )

    @classmethod
    def check_family(cls, family: str | None, consumed: dict[str, Any], where: str) -> None:
        if family is not None and get_world(family).planner is None:
            raise ConfigError(
                f"{where}: the '{family}' family has no planner; leave the planner stage out of the recipe"
            )

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = to_object(ctx.model_cfg)
        where = f"stages '{ctx.spec.name}'"
        if not isinstance(cfg, PlannerStageConfig):  # the family's settings joined to the stage's
            raise ConfigError(f"{where}: the planner's settings {type(cfg).__name__} are not a planner stage's")
        cfg.validate(where)
        export = next(iter(ctx.inputs.values()))
        teacher = None
        if cfg.needs_teacher():
            teacher = load_world_model(export)
            if cfg.max_new_text_tokens > 0:
                teacher.with_settings(max_new_text_tokens=cfg.max_new_text_tokens)
            teacher.requires_grad_(False).eval()
            teacher.prepare_inputs(ctx.data.root, ctx.cache_dir, ctx.shared_cache_dir)
        family = teacher.family if teacher is not None else str(read_config(export).get("family", ""))
        build = get_world(family).planner
        if build is None:
            raise ConfigError(f"{where}: the '{family}' family has no planner; leave the planner stage out")
        self.planner = build(ctx, teacher)
        self.require_tasks(self.planner.sidecar_tasks(), instead="leave the planner stage out of the recipe")
        self.reads_text = teacher is not None

    def monitored(self, kind: StageKind) -> tuple[str | None, str]:
        """The planner's own metric (``monitor``, lower is better), else the kind's."""
        return self.planner.monitor, "min"

    def entries(self, split: str) -> tuple[str, ...] | None:
        # The world model's prompts read the text entries; its scenes or images come from its caches.
        return TEXT_ENTRIES if self.reads_text else ("ann.json",)

    def _clips(self, batch: dict[str, Any]) -> list:
        return clips_from_batch({"qa": [[]] * len(batch["ann"]), "narration": [""] * len(batch["ann"]), **batch})

    def on_fit_start(self) -> None:
        self.planner.prepare_training(self.device)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        clips = self._clips(batch)
        loss = self.planner.training_loss(clips)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(clips))
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self.planner.validate(self._clips(batch), batch_idx, self.ctx.model_cfg.generate_batches)

    def on_validation_epoch_end(self) -> None:
        self.log_dict(self.planner.compute("val"))

    def on_train_end(self) -> None:
        self.planner.save_cache()  # clips first met in training (a shorter history) join the cache

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        params = [p for p in self.planner.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    def report(self) -> StageReport:
        summary, metrics = self.planner.summary()
        return StageReport(summary, metrics)

    def export(self, path: Path) -> Path:
        return self.planner.export(path)

    evaluable = True

    @staticmethod
    def load_planner(request: EvalRequest, what: str) -> tuple[Any, WorldModelEngine]:
        """A trained planner back from its export over its frozen world model (``what``: the
        command asking, for the error a planner that cannot be rebuilt gets)."""
        family = read_config(request.consumed[0]).get("family", "")
        world = get_world(family)
        if world.load_planner is None:  # refused before the world model is loaded
            raise ConfigError(
                f"{request.export}: {what} cannot rebuild a '{family}' planner; its validation metrics are in "
                "metrics.json"
            )
        teacher = load_world_model(request.consumed[0]).eval()
        return world.load_planner(request.export, teacher, request), teacher

    drivable = True

    @classmethod
    def driver(cls, request: EvalRequest) -> StageDriver:
        """The planner on the world model's outputs for each driven frame (its meta action
        generated, never the logged one: closed loop has no log to read it from)."""
        planner, teacher = cls.load_planner(request, "occtrain drive")
        refusal = planner.closed_loop_refusal()
        if refusal is not None:
            raise ConfigError(f"{request.export}: {refusal}")
        return StageDriver(teacher, planner.waypoints)

    @staticmethod
    def rebuild(request: EvalRequest) -> tuple[Any, list]:
        """A trained planner back from its export over its frozen world model, and the
        split's clips it plans (every frame with a whole 3 s future)."""
        planner, teacher = PlannerStage.load_planner(request, "occtrain eval")
        teacher.prepare_inputs(request.data_root, request.cache_dir, request.shared_cache_dir)
        clips = list(
            frame_clips(
                DatasetIndex.open(request.data_root),
                request.split,
                teacher.tasks.context_frames,
                FUTURE_STEPS,
                partial_history=False,
            )
        )
        return planner, clips

    @classmethod
    @torch.no_grad()
    def evaluate_export(cls, request: EvalRequest) -> EvalResult:
        """The trained planner on every frame of the split with a whole 3 s future (or a
        fixed subset of ``samples``), over the consumed world model, beside its baselines."""
        planner, every = cls.rebuild(request)
        chosen = fixed_subset([c.anchor["token"] for c in every], request.samples)
        clips = [c for c in every if c.anchor["token"] in chosen]
        with progress_bar(len(clips), f"planning {len(clips)} {request.split} frames") as advance:
            for i in range(0, len(clips), request.batch_size):
                planner.validate(clips[i : i + request.batch_size], i // request.batch_size)
                advance(len(clips[i : i + request.batch_size]))
        metrics = planner.compute(request.split)
        return EvalResult(
            {k.removeprefix(f"{request.split}/"): v for k, v in metrics.items()},
            coverage={"planning": [len(clips), len(every)]},
        )


PLANNER = register(
    StageKind(
        name="planner",
        model_schema=PlannerStageConfig,
        data_kind="clips",
        module=PlannerStage,
        monitor="val/head_gt_meta_L2_stp3_avg",
        mode="min",
    )
)

"""Stage kinds ``planner`` and ``dagger``: the planner of the consumed world model's
family, and its fine-tuning in closed loop.

The family's registration says what a planner stage trains (``WorldSpec.planner``: OccVLA's
MLP head on the meta action, or a family's own) and what settings it takes
(``WorldSpec.planner_config``, flat in ``model:`` beside this stage's own). The planner
reads the consumed world model, frozen, when its settings ask for it; this module only
wires it into Lightning. A ``dagger`` stage takes a trained planner on and drives it
between its training steps (``engine.closed_loop.dagger``): one kind of the other, so they share this
module as pretrain and instruct share theirs.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, fields, make_dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.config import to_object
from occtrain.core.protocols import Planner, PlannerSettings
from occtrain.core.registry import get_world
from occtrain.data.cameras import nuscenes_rig
from occtrain.data.clips import Clip, clips_from_batch, frame_clips
from occtrain.data.closed_loop_recording import RecordedDataset
from occtrain.data.layout import DatasetIndex
from occtrain.engine import TEXT_ENTRIES, load_world_model
from occtrain.engine.closed_loop import StageDriver, refuse_short_episodes
from occtrain.engine.closed_loop.dagger import (
    Aggregate,
    DaggerSettings,
    drive_route,
    load_policy,
    policy_key,
    replay_weights,
    route_seed,
    scene_name,
)
from occtrain.engine.closed_loop.rollouts import POLICIES_DIR, PolicySpec, RolloutJob, drive_in_workers, write_policy
from occtrain.engine.evaluator import fixed_subset
from occtrain.engine.trained_planner import load_planner
from occtrain.errors import ConfigError
from occtrain.formats.exports import read_config
from occtrain.formats.metrics_file import SampleSet, digest_items
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


def split_plans(index: DatasetIndex, split: str, context: int) -> list[Clip]:
    """A split's plans: a clip at every frame with ``context`` frames of history and a whole 3 s future."""
    return list(frame_clips(index, split, context, FUTURE_STEPS, partial_history=False))


class PlannerStage(Stage):
    """Trains the family's planner; validates it against the baselines with both L2 conventions."""

    count_flops = True
    consumes_kinds: ClassVar[tuple[str, ...]] = ("pretrain", "instruct", "distill")
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
        planner = build(ctx, teacher)
        if not isinstance(planner, Planner):  # a plugin's builder may return anything
            raise ConfigError(
                f"{where}: the '{family}' family's planner is a {type(planner).__name__}, not a subclass of "
                "occtrain.core.protocols.Planner"
            )
        self.planner: Planner = planner
        self.require_tasks(self.planner.sidecar_tasks(), instead="leave the planner stage out of the recipe")
        self.reads_text = teacher is not None
        #: The world model's history, which ``occtrain eval`` gives every plan it scores.
        self.context_frames = teacher.tasks.context_frames if teacher is not None else 0

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

    def split_items(self) -> int | None:
        """The plans ``occtrain eval`` scores on the val split (every frame with a whole 3 s
        future and the world model's context): the shards' clips need the planner's longer
        history, so a validation over them sees fewer."""
        return len(split_plans(DatasetIndex.open(self.ctx.data.root), "val", self.context_frames))

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

    drivable = True

    @classmethod
    def driver(cls, request: EvalRequest) -> StageDriver:
        """The planner on the world model's outputs for each driven frame (its meta action
        generated, never the logged one: closed loop has no log to read it from)."""
        planner, teacher = load_planner(request, "occtrain drive")
        refusal = planner.closed_loop_refusal()
        if refusal is not None:
            raise ConfigError(f"{request.export}: {refusal}")
        return StageDriver(teacher, planner.waypoints)

    @staticmethod
    def rebuild(request: EvalRequest) -> tuple[Planner, list[Clip]]:
        """A trained planner back from its export over its frozen world model, and the
        split's clips it plans (every frame with a whole 3 s future)."""
        planner, teacher = load_planner(request, "occtrain eval")
        teacher.prepare_inputs(request.data_root, request.cache_dir, request.shared_cache_dir)
        return planner, split_plans(DatasetIndex.open(request.data_root), request.split, teacher.tasks.context_frames)

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
        return EvalResult.on_items(
            {k.removeprefix(f"{request.split}/"): v for k, v in metrics.items()},
            "planning",
            [c.anchor["token"] for c in clips],
            [c.anchor["token"] for c in every],
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


@dataclass
class DaggerStageConfig(DaggerSettings):
    """A ``dagger`` stage's settings: how it drives and aggregates (``engine.closed_loop.dagger``), and
    the planner stage's own (the planner's architecture is the consumed export's)."""

    generate_batches: int = -1
    max_new_text_tokens: int = 0


class DaggerStage(PlannerStage):
    """A trained planner fine-tuned on the frames it drives into, each labelled by the world's
    expert (``engine.closed_loop.dagger``): before each round's ``steps_per_round`` optimizer steps its
    routes are driven with the weights of that moment, and every batch then mixes the
    dataset's clips with clips of every frame aggregated so far."""

    consumes_kinds = ("pretrain", "instruct", "distill", "planner")
    consumes_count = (2, 2)

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        return kind.model_schema  # the planner's own settings come with its export

    @classmethod
    def check_consumes(cls, kind: str, consumed: dict[str, str], where: str) -> None:
        super().check_consumes(kind, consumed, where)
        kinds = list(consumed.values())
        if kinds[0] == "planner" or kinds[1] != "planner":
            raise ConfigError(
                f"{where}: a dagger stage consumes the world model its planner reads, then the planner "
                "(consumes: [<its world model stage>, <planner stage>])"
            )

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        to_object(model).validate(key)

    @classmethod
    def check_against_consumed(cls, model: Any, consumed: Mapping[str, Any], key: str) -> None:
        """An episode no longer than the world model's history is the expert's alone: the
        policy would drive none of its frames and the stage train on the expert's driving."""
        tasks = getattr(next(iter(consumed.values())).model_cfg, "tasks", None)
        if tasks is not None and "context_frames" in tasks:
            refuse_short_episodes(model.seconds, int(tasks.context_frames), f"{key}.seconds")

    @classmethod
    def check_trainer(cls, model: Any, trainer: Any, where: str) -> None:
        rounds, steps = model.rounds, model.steps_per_round
        if trainer.max_steps != rounds * steps:
            raise ConfigError(
                f"{where}.trainer.max_steps is {trainer.max_steps}, but model.rounds x model.steps_per_round is "
                f"{rounds} x {steps} = {rounds * steps}; set them so they agree"
            )

    def __init__(self, ctx: StageContext):
        Stage.__init__(self, ctx)
        cfg: DaggerStageConfig = to_object(ctx.model_cfg)
        self.settings = cfg
        world_export, planner_export = ctx.inputs.values()
        request = EvalRequest(
            planner_export, [world_export], str(ctx.data.root), cache_dir=ctx.cache_dir, shared_cache_dir=None
        )
        planner, teacher = load_policy(request, f"stages '{ctx.spec.name}'", cfg.max_new_text_tokens)
        refuse_short_episodes(cfg.seconds, teacher.tasks.context_frames, f"stages.{ctx.spec.name}.model.seconds")
        teacher.prepare_inputs(ctx.data.root, ctx.cache_dir, ctx.shared_cache_dir)
        # The head fine-tunes as the planner stage trained it (dropout on); its world model stays frozen.
        planner.train()
        teacher.eval()
        self.planner, self.teacher, self.reads_text = planner, teacher, True
        self.context_frames = teacher.tasks.context_frames
        synth = ctx.data.synth
        reads_cameras = teacher.vision is not None or teacher.scenes_from_cameras()
        self.camera = (synth.camera_height, synth.camera_width) if reads_cameras else None
        root = ctx.stage_dir / "dagger"
        self.aggregate = Aggregate(
            root, cfg, RecordedDataset(root / "frames", nuscenes_rig(*self.camera) if self.camera else None)
        )
        #: Rounds whose frames the batches draw from, and their clips (futures: the expert's labels).
        self._rounds = 0
        self._aggregated: list = []
        #: How likely each aggregated clip is drawn (critical frames favoured: ``replay_weights``).
        self._replay = np.zeros(0)
        #: Each round's rollouts in the mean (``Aggregate.round_scores``), for the report.
        self.round_scores: dict[int, dict[str, float]] = {}

    @property
    def history(self) -> int:
        return int(self.teacher.tasks.context_frames)

    @contextlib.contextmanager
    def _in_eval(self) -> Iterator[None]:
        """The planner in eval mode (no dropout) for driving and the world model's outputs;
        back to training after, its world model staying frozen in eval mode."""
        was_training = self.planner.training
        self.planner.eval()
        try:
            yield
        finally:
            self.planner.train(was_training)
            self.teacher.eval()

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        round_ = self.global_step // self.settings.steps_per_round
        if round_ < self._rounds:
            return
        for r in range(self._rounds, round_ + 1):
            if not self.aggregate.complete(r):
                if r != round_ or self.global_step != r * self.settings.steps_per_round:
                    raise RuntimeError(
                        f"round {r}'s routes are missing at step {self.global_step}: they are driven at step "
                        f"{r * self.settings.steps_per_round}; retrain the stage with --restart {self.ctx.spec.name}"
                    )
                self._drive(r)
        index = self.aggregate.index(round_ + 1)
        self._aggregated = self.aggregate.clips(index, self.history)
        self._replay = replay_weights(self._aggregated, self.settings.critical_weight)
        new = self.aggregate.scenes(round_ + 1)[self._rounds * self.settings.routes_per_round :]
        # One route at a time, whether met as it was driven or after a resume: an encoder's
        # float sums depend on the batch, and a cut must not change what it encodes. Then
        # what the frozen world model says of each new clip is computed once, in eval mode
        # and outside the training steps' random stream (as the planner stage's train split
        # is, before it trains): a training step never runs the world model, so a resumed
        # run's steps draw what an uncut run's drew.
        with self._in_eval(), torch.no_grad(), torch.random.fork_rng():
            for scene in new:
                self.teacher.add_samples(index, [(scene, t) for t in index.scenes[scene]])
                route = [c for c in self._aggregated if index.scene_of(c.anchor["token"]) == scene]
                if route:
                    self.planner.training_loss(route)
        for r in range(self._rounds, round_ + 1):
            scores = self.aggregate.round_scores(r)
            self.round_scores[r] = scores
            self.log_dict({f"dagger/{k}": v for k, v in scores.items()}, batch_size=1)
        self._rounds = round_ + 1
        # Driving a round and the world model's outputs for its frames are not this step's
        # time, nor its FLOPs (they would make the stage's MFU and step time the rollouts').
        if self.step_meter is not None:
            self.step_meter.restart_step()

    @torch.no_grad()
    def _drive(self, round_: int) -> None:
        """Drive round ``round_``'s routes with the weights of now (those already driven by
        the same weights, before a cut, are kept), in process or in ``workers`` processes."""
        cfg, aggregate = self.settings, self.aggregate
        key, beta = policy_key(self.planner), cfg.beta_at(round_)
        todo = [k for k in range(cfg.routes_per_round) if not aggregate.driven(round_, k, key)]
        what = f"round {round_}: driving {cfg.routes_per_round} routes (beta {beta:.2f})"
        with self._in_eval(), progress_bar(cfg.routes_per_round, what) as advance:
            advance(cfg.routes_per_round - len(todo))
            if cfg.workers > 1 and len(todo) > 1:
                self._drive_in_workers(round_, key, todo, advance)
                return
            driver = StageDriver(self.teacher, self.planner.waypoints)
            for k in todo:
                seed = route_seed(cfg, round_, k)
                labelled, result = drive_route(
                    driver, aggregate.dataset, scene_name(round_, k), seed, cfg.seconds, beta, self.camera, key
                )
                aggregate.record(labelled, result)
                advance(1)

    def _drive_in_workers(self, round_: int, key: str, todo: list[int], advance: Callable[[int], None]) -> None:
        world_export, planner_export = self.ctx.inputs.values()
        root = self.aggregate.root
        weights = write_policy(self.planner, root, key)
        # The engine's own settings, not this module's subclass: unpickling that in a worker
        # would import the stages, and Lightning with them.
        settings = DaggerSettings(**{f.name: getattr(self.settings, f.name) for f in fields(DaggerSettings)})
        trainable = tuple(n for n, p in self.planner.named_parameters() if p.requires_grad)
        with tempfile.TemporaryDirectory(prefix="occtrain-dagger-") as scratch:
            spec = PolicySpec(
                str(world_export),
                str(planner_export),
                str(self.ctx.data.root),
                str(weights),
                key,
                trainable,
                self.settings.max_new_text_tokens,
                scratch,
            )
            jobs = [RolloutJob(spec, str(root), settings, self.camera, round_, k) for k in todo]
            drive_in_workers(jobs, self.settings.workers, advance)
        # The round is recorded: no route is left to drive by these weights (nor by those of a
        # round cut short before, whose file a resumed run in process would leave).
        shutil.rmtree(root / POLICIES_DIR, ignore_errors=True)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        clips = self._clips(batch)
        share = self.settings.aggregate_share
        if self._aggregated and share > 0:
            extra = len(clips) if share >= 1 else max(1, round(len(clips) * share / (1 - share)))
            rng = np.random.default_rng([self.ctx.trainer.seed, self.global_step])
            drawn = [self._aggregated[i] for i in rng.choice(len(self._aggregated), extra, p=self._replay)]
            clips = drawn if share >= 1 else clips + drawn
        loss = self.planner.training_loss(clips)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(clips))
        return loss

    def report(self) -> StageReport:
        summary, metrics = self.planner.summary()
        rollouts = []  # driven on training routes: not the val split the validation scored
        for r, scores in sorted(self.round_scores.items()):
            keys = [f"round{r}_{k}" for k in scores]
            metrics.update(dict(zip(keys, scores.values())))
            routes = [route_seed(self.settings, r, k) for k in range(self.settings.routes_per_round)]
            on = (
                f"round {r}'s {len(routes)} training routes driven closed loop ({int(scores['rollout_frames'])} frames)"
            )
            rollouts.append(SampleSet(digest_items(map(str, routes)), len(routes), len(routes), ["rollouts"], keys, on))
        frames = sum(int(s["rollout_frames"]) for s in self.round_scores.values())
        return StageReport(
            f"{summary}; closed loop: {len(self.round_scores)} rounds, {frames} frames aggregated",
            metrics,
            sample_sets=rollouts,
        )


DAGGER = register(
    StageKind(
        name="dagger",
        model_schema=DaggerStageConfig,
        data_kind="clips",
        module=DaggerStage,
        monitor="val/head_gt_meta_L2_stp3_avg",
        mode="min",
    )
)

"""Stage kind ``distill``: a smaller student world model learns from the frozen instruct model.

The student shares the teacher's joint vocabulary, text tokenizer and scene tokenizer, so
their logits live in one space. Losses: KL between the temperature-softened teacher and
student distributions (scaled by T^2), the student's own next-token loss, and feature
distillation of the last hidden states as SparseOccVLA distils features: the student's
states go through a linear projection and LayerNorm, and a cosine loss pulls them towards
the teacher's LayerNorm-ed states. The student exports as a world model, so ``occtrain
eval`` and later stages read it like the teacher.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.config import to_object
from occtrain.config.llm import MAX_NEW_TEXT_TOKENS, LLMConfig
from occtrain.core.lm_world_model import WorldInputs
from occtrain.core.shared_tasks import validate_tasks
from occtrain.data.clips import clips_from_batch
from occtrain.engine import (
    TEXT_ENTRIES,
    Evaluator,
    Priors,
    WorldModelEngine,
    compare_generation_speed,
    export_engine,
    load_world_model,
    move_batch,
    scorable,
    speed_prompt,
)
from occtrain.errors import ConfigError
from occtrain.formats.metrics_file import SampleSet
from occtrain.models import count_parameters
from occtrain.models.compiling import decoder_layers
from occtrain.models.distill_losses import FeatureProjector, distillation_losses
from occtrain.models.flops import TransformerFlops
from occtrain.models.llm import build_llm, check_llm
from occtrain.stages import StageKind, register
from occtrain.stages.common import ValidationMeans, evaluate_engine, family_schema, lm_step_work
from occtrain.stages.optim import configure_adamw
from occtrain.stages.stage import EvalRequest, EvalResult, Stage, StageContext, StageReport, StepWork


def _student_llm() -> LLMConfig:
    return LLMConfig(hidden_size=96, num_layers=1, num_heads=4, intermediate_size=256)


@dataclass
class DistillModelConfig:
    """``model:`` of a distill stage."""

    #: The student's LLM (fewer layers / narrower than the teacher's).
    student: LLMConfig = field(default_factory=_student_llm)
    temperature: float = 2.0
    #: Loss weights: KL on logits, student cross-entropy on the labels, hidden-state cosine.
    kl_weight: float = 1.0
    ce_weight: float = 0.5
    feature_weight: float = 1.0
    #: Validation generation: items per task (fixed seeded subset, -1: all) and prompts per batch.
    val_samples: int = 64
    val_batch_size: int = 16
    max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS
    cache_codes: bool = True


class DistillStage(Stage):
    """Trains the student against the frozen teacher; validates both with the same evaluator."""

    consumes_kinds = ("pretrain", "instruct", "distill")
    consumes_count = (1, 1)
    # Teacher and frozen encoders come from their exports; checkpoints carry what trains.
    frozen_prefixes = ("teacher.", "student.scene_encoder.", "student.vision.")
    evaluable = True
    saves_predictions = True

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        return family_schema(kind.model_schema, family, with_world=False)

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        """The student's LLM, through the checks its build makes (the backend's own included)."""
        check_llm(to_object(model.student), f"{key}.student")
        if model.max_new_text_tokens < 1:
            raise ConfigError(
                f"{key}.max_new_text_tokens: {model.max_new_text_tokens}; a validation generates at least 1 token of "
                "text per answer"
            )

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        tasks = to_object(cfg.tasks)
        teacher = load_world_model(next(iter(ctx.inputs.values()))).with_settings(tasks, cfg.max_new_text_tokens)
        teacher.default_tasks("instruct")
        validate_tasks(tasks, f"stages '{ctx.spec.name}'.model.tasks", teacher.task_specs)
        self.require_tasks(t for t, w in tasks.weights.items() if w > 0)
        self.teacher = teacher.requires_grad_(False).eval()
        vocab = teacher.vocab
        student_llm = build_llm(cfg.student, len(vocab))
        # The teacher's architecture around the student's LLM, over the same frozen encoders.
        world = teacher.spec.model.from_export(
            teacher.world.export_config(), student_llm, vocab, WorldInputs(teacher.scene_encoder, teacher.vision)
        )
        self.student = WorldModelEngine(
            teacher.scene_encoder,
            world,
            teacher.text_tokenizer,
            tasks,
            cfg.max_new_text_tokens,
            teacher.family,
            teacher.vision,
        )
        self.projector = FeatureProjector(world.hidden_size, teacher.world.hidden_size)
        priors, hooks = Priors.of(ctx.data.root, ctx.shared_cache_dir), teacher.spec.eval_hooks
        names = scorable(teacher.task_specs, tasks.weights)
        self.evaluator = Evaluator(names, teacher.task_specs, priors=priors, hooks=hooks)
        self.teacher_evaluator = Evaluator(names, teacher.task_specs, priors=priors, hooks=hooks)
        self.val_means = ValidationMeans("val/loss", "val/token_acc")
        self._teacher_scores: dict[str, float] | None = None
        self._entries: dict[str, tuple[str, ...] | None] = {}
        if teacher.encoded_inputs() or (cfg.cache_codes and teacher.reads_scenes()):
            # One cache, shared: teacher and student read the same scenes and views.
            self.teacher.prepare_inputs(ctx.data.root, ctx.cache_dir, ctx.shared_cache_dir)
            self.student.scene_cache, self.student.input_caches = self.teacher.scene_cache, self.teacher.input_caches
            self.student.data_index = self.teacher.data_index
            self._entries = (
                {"train": TEXT_ENTRIES} if teacher.reads_scenes() else {"train": TEXT_ENTRIES, "val": TEXT_ENTRIES}
            )
        self._speed: dict[str, float] = {}

    def entries(self, split: str) -> tuple[str, ...] | None:
        return self._entries.get(split)

    def train(self, mode: bool = True) -> DistillStage:
        super().train(mode)
        self.teacher.eval()
        return self

    def compiled_blocks(self) -> list[torch.nn.Module]:
        """The student's decoder layers; the teacher's forwards run without gradients, eager."""
        return decoder_layers(self.student.world.llm)

    def on_train_start(self) -> None:
        self._student_flops = TransformerFlops.of(self.student.world.llm)
        self._teacher_flops = TransformerFlops.of(self.teacher.world.llm)

    def _flops_per_token(self, seq_len: int) -> float:
        """The student's training and the frozen teacher's forward, on the same tokens."""
        return self._student_flops.train_per_token(seq_len) + self._teacher_flops.forward_per_token(seq_len)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor | None:
        cfg = self.ctx.model_cfg
        clips = clips_from_batch(batch)
        model_batch, names = self.student.task_batch(clips, batch, self.step_seed(self.global_step))
        self.log("train/skipped_clips", float(names.count(None)), reduce_fx="sum", batch_size=len(clips))
        self.step_work = StepWork(samples=0, tokens=0, flops=0.0)
        if model_batch is None:
            return None  # no clip of the batch has a configured task: no step
        samples = len(names) - names.count(None)
        self.step_work = lm_step_work(model_batch, samples, self._flops_per_token)
        model_batch = move_batch(model_batch, self.device)
        with torch.no_grad():
            t_out = self.teacher.world(model_batch, output_hidden_states=True)
        s_out = self.student.world(model_batch, output_hidden_states=True)
        valid = model_batch["input_ids"] != self.student.vocab.pad_id
        kl, cos = distillation_losses(
            s_out.logits, t_out.logits, self.projector(s_out.hidden), t_out.hidden, valid, cfg.temperature
        )
        loss = cfg.kl_weight * kl + cfg.ce_weight * s_out.loss + cfg.feature_weight * cos
        bs = len(names) - names.count(None)
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        self.log("train/kl", kl, batch_size=bs)
        self.log("train/feature_cos", cos, batch_size=bs)
        self.log("train/student_ce", s_out.loss, batch_size=bs)
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        clips = clips_from_batch(batch)
        model_batch, names = self.student.task_batch(clips, batch, seed=self.ctx.data.seed)  # by clip, as in pretrain
        if model_batch is not None:
            model_batch = move_batch(model_batch, self.device)
            out = self.student.world(model_batch)
            acc = self.student.world.token_accuracy(out.logits, model_batch["labels"])
            bs = len(names) - names.count(None)
            self.val_means.update("val/loss", out.loss, bs)
            self.val_means.update("val/token_acc", acc, bs)

    def on_validation_epoch_end(self) -> None:
        cfg = self.ctx.model_cfg
        root = self.ctx.data.root
        self.evaluator.run(self.student, root, "val", cfg.val_batch_size, samples=cfg.val_samples)
        scores = self.evaluator.compute("val")  # texts and pictures stay for report()
        if self._teacher_scores is None:  # the teacher is frozen: score it once
            self.teacher_evaluator.run(self.teacher, root, "val", cfg.val_batch_size, samples=cfg.val_samples)
            self._teacher_scores = {
                k.replace("val/", "val/teacher_", 1): v for k, v in self.teacher_evaluator.compute("val").items()
            }
        # The protocol occtrain eval uses too (engine.speed), so both report one speedup.
        self._speed = compare_generation_speed(
            {"teacher": self.teacher, "student": self.student}, speed_prompt(self.student, root)
        )
        scores.update(self._teacher_scores)
        if self._speed:
            scores["val/student_tokens_per_s"] = self._speed["student"]
            scores["val/teacher_tokens_per_s"] = self._speed["teacher"]
            scores["val/speedup"] = self._speed["student"] / self._speed["teacher"]
        scores.update(self.val_means.pop())
        self.log_dict(scores)

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        params = [p for p in self.student.world.parameters() if p.requires_grad] + list(self.projector.parameters())
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    def report(self) -> StageReport:
        s, t = count_parameters(self.student.world), count_parameters(self.teacher.world)
        return StageReport(
            f"student {s / 1e6:.2f}M params vs teacher {t / 1e6:.2f}M ({s / t:.2f}x)",
            {"student_params": float(s), "teacher_params": float(t), "param_ratio": s / t},
            texts=list(self.evaluator.texts),
            scenes=list(self.evaluator.scenes),
            coverage=dict(self.evaluator.coverage),
            sample_sets=self._sample_sets(),
        )

    def _sample_sets(self) -> list[SampleSet]:
        """Which items the student's and the teacher's scores were scored on (the teacher's
        were computed once, its keys renamed ``val/teacher_*``)."""
        teacher = [
            replace(s, keys=[k.replace("val/", "val/teacher_", 1) for k in s.keys])
            for s in self.teacher_evaluator.sample_sets
        ]
        return list(self.evaluator.sample_sets) + teacher

    def export(self, path: Path) -> Path:
        return export_engine(self.student, path, stage=self.ctx.spec.name)

    @classmethod
    def evaluate_export(cls, request: EvalRequest) -> EvalResult:
        """The student's answers scored as a world model's, and its generation speed against
        its teacher's by the protocol validation uses (``engine.speed``)."""
        student = load_world_model(request.export).eval()
        result = evaluate_engine(student, request)
        teacher_export = request.consumed[0]
        if not (teacher_export / "config.json").is_file():
            raise ConfigError(f"{teacher_export}: the distill stage's teacher export is missing; its speedup needs it")
        teacher = load_world_model(teacher_export).eval()
        # The same frozen encoders: the student's encodings serve the teacher.
        teacher.scene_cache, teacher.input_caches = student.scene_cache, student.input_caches
        speed = compare_generation_speed(
            {"teacher": teacher, "student": student}, speed_prompt(student, request.data_root, request.split)
        )
        result.metrics.update(
            student_tokens_per_s=speed["student"],
            teacher_tokens_per_s=speed["teacher"],
            speedup=speed["student"] / speed["teacher"],
        )
        return result


DISTILL = register(
    StageKind(
        name="distill", model_schema=DistillModelConfig, data_kind="clips", module=DistillStage, monitor="val/token_acc"
    )
)

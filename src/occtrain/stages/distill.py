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

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F

from occtrain.config.llm import LLMConfig
from occtrain.data.tasks import INSTRUCT_TASKS, TaskConfig, clips_from_batch, validate_tasks
from occtrain.errors import ConfigError
from occtrain.models.llm import build_llm
from occtrain.models.world_model import OccWorldModel
from occtrain.stages import StageContext, StageKind, register
from occtrain.stages.common import configure_adamw
from occtrain.stages.world_model import CODE_CACHE, TEXT_ENTRIES, Evaluator, WorldModelEngine, _to, export_engine, load_world_model, qa_prior


def _student_llm() -> LLMConfig:
    return LLMConfig(hidden_size=96, num_layers=1, num_heads=4, intermediate_size=256)


@dataclass
class DistillModelConfig:
    """``model:`` of a distill stage."""

    #: The student's LLM (fewer layers / narrower than the teacher's).
    student: LLMConfig = field(default_factory=_student_llm)
    tasks: TaskConfig = field(default_factory=lambda: TaskConfig(weights={t: 1.0 for t in INSTRUCT_TASKS}))
    temperature: float = 2.0
    #: Loss weights: KL on logits, student cross-entropy on the labels, hidden-state cosine.
    kl_weight: float = 1.0
    ce_weight: float = 0.5
    feature_weight: float = 1.0
    generate_batches: int = 2
    max_new_text_tokens: int = 96
    #: New tokens timed for the generation-speed comparison.
    speed_tokens: int = 32
    cache_codes: bool = True


class FeatureProjector(torch.nn.Module):
    """Student hidden states -> the teacher's width, then LayerNorm (SparseOccVLA's distillation head)."""

    def __init__(self, student_dim: int, teacher_dim: int):
        super().__init__()
        self.proj = torch.nn.Linear(student_dim, teacher_dim)
        self.norm = torch.nn.LayerNorm(teacher_dim)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.norm(self.proj(hidden))


def distillation_losses(
    student_logits: torch.Tensor, teacher_logits: torch.Tensor, student_feat: torch.Tensor, teacher_hidden: torch.Tensor,
    valid: torch.Tensor, temperature: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """KL(teacher || student) at temperature T (times T^2) and 1 - cosine of the features,
    both averaged over the ``valid`` (non-padding) positions."""
    t = temperature
    log_p_s = F.log_softmax(student_logits[valid].float() / t, dim=-1)
    log_p_t = F.log_softmax(teacher_logits[valid].float() / t, dim=-1)
    kl = F.kl_div(log_p_s, log_p_t, log_target=True, reduction="batchmean") * t * t
    target = F.layer_norm(teacher_hidden[valid].float(), teacher_hidden.shape[-1:])
    cos = 1.0 - F.cosine_similarity(student_feat[valid].float(), target, dim=-1).mean()
    return kl, cos


class DistillStage(L.LightningModule):
    """Trains the student against the frozen teacher; validates both with the same evaluator."""

    def __init__(self, ctx: StageContext):
        super().__init__()
        cfg = ctx.model_cfg
        validate_tasks(cfg.tasks, f"stages '{ctx.spec.name}'.model.tasks")
        if len(ctx.inputs) != 1:
            raise ConfigError(f"stages '{ctx.spec.name}': a distill stage consumes exactly one instruct (or pretrain) stage")
        self.ctx = ctx
        teacher = load_world_model(next(iter(ctx.inputs.values())))
        self.teacher = teacher.requires_grad_(False).eval()
        vocab = teacher.vocab
        student_llm = build_llm(cfg.student, len(vocab))
        world = OccWorldModel(student_llm, vocab, codebook=teacher.scene_tokenizer.codebook,
                              scene_prediction=teacher.world.scene_prediction)
        self.student = WorldModelEngine(teacher.scene_tokenizer, world, teacher.text_tokenizer)
        self.projector = FeatureProjector(world.hidden_size, teacher.world.hidden_size)
        prior = qa_prior(ctx.data.root)
        self.evaluator = Evaluator(cfg.tasks, cfg.max_new_text_tokens, qa_prior=prior)
        self.teacher_evaluator = Evaluator(cfg.tasks, cfg.max_new_text_tokens, qa_prior=prior)
        self._teacher_scores: dict[str, float] | None = None
        if cfg.cache_codes:  # one cache, shared: teacher and student read the same scenes
            self.teacher.build_code_cache(ctx.data.root, ctx.stage_dir / "cache" / CODE_CACHE)
            self.student.code_cache = self.teacher.code_cache
            self.entries = {"train": TEXT_ENTRIES, "val": None}
        self._speed: dict[str, float] = {}

    def train(self, mode: bool = True) -> DistillStage:
        super().train(mode)
        self.teacher.eval()
        return self

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        cfg = self.ctx.model_cfg
        clips = clips_from_batch(batch)
        seed = self.ctx.data.seed * 1_000_003 + self.global_step
        model_batch, _ = self.student.task_batch(clips, batch, cfg.tasks, seed)
        model_batch = _to(model_batch, self.device)
        with torch.no_grad():
            t_out = self.teacher.world(model_batch, output_hidden_states=True)
        s_out = self.student.world(model_batch, output_hidden_states=True)
        valid = model_batch["input_ids"] != self.student.vocab.pad_id
        kl, cos = distillation_losses(s_out.logits, t_out.logits, self.projector(s_out.hidden), t_out.hidden, valid, cfg.temperature)
        loss = cfg.kl_weight * kl + cfg.ce_weight * s_out.loss + cfg.feature_weight * cos
        bs = len(clips)
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        self.log("train/kl", kl, batch_size=bs)
        self.log("train/feature_cos", cos, batch_size=bs)
        self.log("train/student_ce", s_out.loss, batch_size=bs)
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        cfg = self.ctx.model_cfg
        clips = clips_from_batch(batch)
        model_batch, _ = self.student.task_batch(clips, batch, cfg.tasks, seed=batch_idx)
        model_batch = _to(model_batch, self.device)
        out = self.student.world(model_batch)
        acc = self.student.world.token_accuracy(out.logits, model_batch["labels"])
        self.log("val/loss", out.loss, batch_size=len(clips), sync_dist=True)
        self.log("val/token_acc", acc, batch_size=len(clips), sync_dist=True)
        if batch_idx < cfg.generate_batches:
            self.evaluator.update(self.student, clips, batch)
            if self._teacher_scores is None:  # the teacher is frozen: score it once
                self.teacher_evaluator.update(self.teacher, clips, batch)
            if batch_idx == 0:
                self._time_generation(model_batch)

    @torch.no_grad()
    def _time_generation(self, model_batch: dict) -> None:
        """Tokens per second of greedy text generation, teacher and student on the same prompt."""
        prompt = model_batch["input_ids"][0][model_batch["input_ids"][0] != self.student.vocab.pad_id][:64].cpu()
        n = self.ctx.model_cfg.speed_tokens
        for name, engine in (("teacher", self.teacher), ("student", self.student)):
            engine.world.generate_text(prompt, 2)  # warm-up
            start = time.perf_counter()
            engine.world.generate_text(prompt, n, eos=-1)  # never stops early: n tokens exactly
            self._speed[name] = n / (time.perf_counter() - start)

    def on_validation_epoch_end(self) -> None:
        scores = self.evaluator.compute("val")
        self.evaluator.reset()
        if self._teacher_scores is None:
            self._teacher_scores = {k.replace("val/", "val/teacher_", 1): v for k, v in self.teacher_evaluator.compute("val").items()}
            self.teacher_evaluator.reset()
        scores.update(self._teacher_scores)
        if self._speed:
            scores["val/student_tokens_per_s"] = self._speed["student"]
            scores["val/teacher_tokens_per_s"] = self._speed["teacher"]
            scores["val/speedup"] = self._speed["student"] / self._speed["teacher"]
        self.log_dict(scores)

    def configure_optimizers(self) -> dict:
        params = [p for p in self.student.world.parameters() if p.requires_grad] + list(self.projector.parameters())
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        # Teacher and scene tokenizer come from their exports; checkpoints carry what trains.
        return {
            k: v for k, v in super().state_dict(*args, **kwargs).items()
            if not k.startswith(("teacher.", "student.scene_tokenizer."))
        }

    def load_state_dict(self, state_dict: dict[str, Any], strict: bool = True, **kwargs: Any) -> Any:
        return super().load_state_dict(state_dict, strict=False)

    def _params(self, engine: WorldModelEngine) -> int:
        return sum(p.numel() for p in engine.world.parameters())

    def summary(self) -> str:
        s, t = self._params(self.student), self._params(self.teacher)
        return f"student {s / 1e6:.2f}M params vs teacher {t / 1e6:.2f}M ({s / t:.2f}x)"

    def summary_metrics(self) -> dict[str, float]:
        s, t = self._params(self.student), self._params(self.teacher)
        return {"student_params": float(s), "teacher_params": float(t), "param_ratio": s / t}

    def samples(self) -> list[dict]:
        return list(self.evaluator.texts)

    def export(self, path: Path) -> Path:
        return export_engine(self.student, path, merge=False, stage=self.ctx.spec.name)


DISTILL = register(
    StageKind(name="distill", model_schema=DistillModelConfig, data_kind="clips", build=DistillStage, monitor="val/token_acc")
)

"""Stage kinds ``pretrain`` and ``instruct``: a family's world model over the joint vocabulary.

``pretrain`` consumes a tokenizer export, trains a local BPE text tokenizer on the
dataset's text (or takes ``llm.path``'s), lays out the joint vocabulary and trains the LLM
on OccLLaMA's five tasks. ``instruct`` consumes a world-model export and tunes it on
NuScenes-QA and chain-of-thought planning through a peft LoRA adapter, the base frozen.

Both validate by teacher-forced loss and token accuracy on the val batches, and by
generation on a fixed seeded subset of ``val_samples`` val items per task, scored by the
engine's evaluator. The model, its prompts, generation and export are the engine's
(``occtrain.engine``); this module only wires them into Lightning.
"""

from __future__ import annotations

from dataclasses import field, make_dataclass
from pathlib import Path
from typing import Any

import torch

from occtrain.config import to_object
from occtrain.data.clips import clips_from_batch
from occtrain.engine import TEXT_ENTRIES, Evaluator, export_engine, load_world_model, Priors, move_batch, new_world_model
from occtrain.families import families
from occtrain.families.occllama import InstructModelConfig, PretrainModelConfig
from occtrain.families.occllama.tasks import validate_tasks
from occtrain.models import count_parameters
from occtrain.errors import ConfigError
from occtrain.exports import export_kind
from occtrain.models.adapters import adapters_of, add_adapters
from occtrain.models.llm import apply_lora
from occtrain.stages import StageKind, register
from occtrain.stages.base import Stage, StageContext, StageReport
from occtrain.stages.common import ValidationMeans, configure_adamw, freeze_prefixes

WORLD_MODEL_KINDS = ("pretrain", "instruct", "distill")


class WorldModelStage(Stage):
    """Trains the world model on the configured tasks; validates by loss, accuracy and generation."""

    consumes_count = (1, 1)
    # They come from the tokenizer's and the vision stage's exports.
    frozen_prefixes = ("engine.scene_tokenizer.", "engine.vision.")

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        where = f"stages '{ctx.spec.name}'.model"
        tasks = to_object(cfg.tasks)
        if ctx.spec.kind == "pretrain":
            exports = self._exports_by_kind(where)
            # Every family's section: the one of the family the tokenizer picks is used.
            sections = {name: to_object(cfg[name]) for name, spec in families().items() if spec.world_config is not None}
            self.engine = new_world_model(
                exports["tokenizer"], cfg.llm, tasks, ctx.data.root, cfg.max_new_text_tokens, cfg.family, sections, where,
                vision_export=exports.get("vision"),
            )
        else:
            self.engine = load_world_model(next(iter(ctx.inputs.values()))).with_settings(tasks, cfg.max_new_text_tokens)
        # The family's own tasks: known once the engine says which family it is.
        self.engine.default_tasks("pretrain" if ctx.spec.kind == "pretrain" else "instruct")
        validate_tasks(tasks, f"{where}.tasks", self.engine.task_builders)
        self.require_tasks(t for t, w in tasks.weights.items() if w > 0)
        world = self.engine.world
        if cfg.use_lora and cfg.use_adapters:
            raise ConfigError(f"{where}: use_lora and use_adapters are both on; train through one of them")
        if cfg.use_lora:
            world.llm.requires_grad_(False)
            world.requires_grad_(False)
            world.llm = apply_lora(world.llm, cfg.lora)
        if cfg.use_adapters:
            # The LM's own weights freeze; its adapters and the model's own parts (image
            # projector, occupancy queries and projector) train.
            adapter_cfg = to_object(cfg.adapter)
            adapter_cfg.validate(f"{where}.adapter")
            world.llm.requires_grad_(False)
            for adapter in adapters_of(world.llm) or add_adapters(world.llm, adapter_cfg):
                adapter.requires_grad_(True)
        if tasks.occupancy_weight == 0:
            for p in getattr(world, "occupancy_parameters", list)():
                p.requires_grad_(False)  # no loss reaches them: DDP must not wait for their gradients
        freeze_prefixes(world, list(ctx.spec.freeze))
        self.evaluator = Evaluator(Evaluator.scorable(tasks.weights), priors=Priors.of(ctx.data.root))
        self.val_means = ValidationMeans("val/loss", "val/token_acc")
        self._entries: dict[str, tuple[str, ...] | None] = {}
        if self.engine.vision is not None or cfg.cache_codes:
            self.engine.prepare_inputs(ctx.data.root, ctx.stage_dir / "cache")
            # Training then reads no occupancy; validation still scores forecasts against it.
            # A model that reads cameras takes its occupancy targets from the dataset: its
            # shards give the annotations and the text alone.
            self._entries = {"train": TEXT_ENTRIES, "val": TEXT_ENTRIES} if self.engine.vision is not None else {"train": TEXT_ENTRIES}

    def _exports_by_kind(self, where: str) -> dict[str, Path]:
        """A pretrain stage's inputs by stage kind: one tokenizer, at most one vision stage."""
        found: dict[str, Path] = {}
        for name, path in self.ctx.inputs.items():
            kind = export_kind(Path(path))
            if kind in found:
                raise ConfigError(f"{where}: consumes two {kind} stages; a world model reads one")
            found[kind] = Path(path)
        if "tokenizer" not in found:
            raise ConfigError(f"{where}: a pretrain stage consumes a tokenizer stage; add one to consumes")
        return found

    def entries(self, split: str) -> tuple[str, ...] | None:
        return self._entries.get(split)

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        clips = clips_from_batch(batch)
        model_batch, names = self.engine.task_batch(clips, batch, self.step_seed(self.global_step))
        self.log("train/skipped_clips", float(names.count(None)), reduce_fx="sum", batch_size=len(clips))
        if model_batch is None:
            return None  # no clip of the batch has a configured task: no step
        out = self.engine.world(move_batch(model_batch, self.device))
        loss = out.loss
        bs = len(names) - names.count(None)
        self.log("train/loss", loss, prog_bar=True, batch_size=bs)
        self.log("train/text_loss", out.text_loss, batch_size=bs)
        self.log("train/scene_loss", out.scene_loss, batch_size=bs)
        kept = [n for n in names if n is not None]
        for task in sorted(set(kept)):  # which task is learning, which is not
            rows = [i for i, n in enumerate(kept) if n == task]
            self.log(f"train/loss_{task}", out.sample_loss[rows].mean(), batch_size=len(rows))
        return loss

    # -- validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        clips = clips_from_batch(batch)
        # Tasks drawn by clip alone (not by batch position): every validation, and any
        # split of the clips over DDP ranks, scores each clip on the same task.
        model_batch, names = self.engine.task_batch(clips, batch, seed=self.ctx.data.seed)
        if model_batch is not None:
            out = self.engine.world(move_batch(model_batch, self.device))
            bs = len(names) - names.count(None)
            self.val_means.update("val/loss", out.loss, bs)
            acc = self.engine.world.token_accuracy(out.logits, model_batch["labels"].to(self.device))
            self.val_means.update("val/token_acc", acc, bs)

    def on_validation_epoch_end(self) -> None:
        cfg = self.ctx.model_cfg
        self.evaluator.run(self.engine, self.ctx.data.root, "val", cfg.val_batch_size, samples=cfg.val_samples)
        self.log_dict(self.val_means.pop())
        self.log_dict(self.evaluator.compute("val"))  # texts and pictures stay for report()

    def configure_optimizers(self) -> dict:
        params = [p for p in self.engine.world.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def report(self) -> StageReport:
        world = self.engine.world
        total, trained = count_parameters(world), count_parameters(world, trainable=True)
        summary = f"world model {total / 1e6:.2f}M params ({trained / 1e6:.2f}M trained), vocab {len(self.engine.vocab)}"
        # Scene tokens per frame: Occ-LLM's patch-size table reads it beside the step time.
        metrics = {"params": float(total), "scene_tokens": float(self.engine.vocab.scene_len)}
        return StageReport(summary, metrics, texts=list(self.evaluator.texts), scenes=list(self.evaluator.scenes))

    def export(self, path: Path) -> Path:
        return export_engine(self.engine, path, stage=self.ctx.spec.name, merge=self.ctx.model_cfg.merge_export)


class PretrainStage(WorldModelStage):
    consumes_kinds = ("tokenizer", "vision")
    consumes_count = (1, 2)  # a tokenizer, and a vision stage for a world model that reads cameras


class InstructStage(WorldModelStage):
    consumes_kinds = WORLD_MODEL_KINDS


def pretrain_model_schema() -> type:
    """``model:`` of a pretrain stage: OccLLaMA's settings, ``family`` (whose world model;
    empty: the tokenizer's family, else OccLLaMA's) and a section per family with world settings."""
    sections = [(name, spec.world_config) for name, spec in families().items() if spec.world_config is not None]
    extra = [("family", str, field(default=""))] + [(name, cfg, field(default_factory=cfg)) for name, cfg in sections]
    return make_dataclass("PretrainModelConfig", extra, bases=(PretrainModelConfig,))


PRETRAIN = register(
    StageKind(name="pretrain", model_schema=pretrain_model_schema(), data_kind="clips", module=PretrainStage, monitor="val/token_acc")
)
INSTRUCT = register(
    StageKind(name="instruct", model_schema=InstructModelConfig, data_kind="clips", module=InstructStage, monitor="val/token_acc")
)

"""Stage kinds ``pretrain`` and ``instruct``: a family's world model over the joint vocabulary.

``pretrain`` builds the family's world model over the exports it consumes (a tokenizer's
scene encoder, a vision stage's camera encoder: what the family's registration names),
trains a local BPE text tokenizer on the dataset's text (or takes ``llm.path``'s), lays out
the joint vocabulary and trains on the family's pretraining tasks. ``instruct`` consumes a
world-model export and tunes it on the family's instruction tasks, through a peft LoRA
adapter (the base frozen), bottleneck adapters, or fully.

Both validate by teacher-forced loss and token accuracy on the val batches, and by
generation on a fixed seeded subset of ``val_samples`` val items per task, scored by the
engine's evaluator with the family's scorers. The model, its prompts, generation and
export are the engine's (``occtrain.engine``); this module only wires them into Lightning.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

from occtrain.config import to_object
from occtrain.config.llm import MAX_NEW_TEXT_TOKENS, LLMConfig, LoRAConfig
from occtrain.core.registry import get_world, tokenizer_family
from occtrain.core.shared_tasks import validate_tasks
from occtrain.data.clips import clips_from_batch
from occtrain.engine import (
    TEXT_ENTRIES,
    Evaluator,
    Priors,
    export_engine,
    load_world_model,
    move_batch,
    new_world_model,
    scorable,
)
from occtrain.engine.closed_loop import StageDriver, world_model_driver
from occtrain.errors import ConfigError
from occtrain.formats.exports import export_kind, read_config
from occtrain.models import count_parameters
from occtrain.models.adapters import AdapterConfig, adapters_of, add_adapters
from occtrain.models.compiling import decoder_layers
from occtrain.models.flops import TransformerFlops
from occtrain.models.llm import apply_lora, check_llm, checkpoint_layers
from occtrain.stages import StageKind, register
from occtrain.stages.common import ValidationMeans, evaluate_engine, family_schema, lm_step_work, schema_family
from occtrain.stages.optim import configure_adamw, freeze_prefixes
from occtrain.stages.sharding import FullCopy, ShardedStrategy, is_sharded, local_numel, shard_world_model
from occtrain.stages.stage import EvalRequest, EvalResult, Stage, StageContext, StageReport, StepWork

WORLD_MODEL_KINDS = ("pretrain", "instruct", "distill")


@dataclass
class WorldModelConfig:
    """``model:`` of a pretrain or instruct stage; ``tasks`` are the family's task settings
    and ``model.<family>`` its world settings (see ``WorldModelStage.model_schema``)."""

    #: Whose world model a pretrain stage builds (empty: the tokenizer's family); an
    #: instruct stage's is the consumed export's.
    family: str = ""
    llm: LLMConfig = field(default_factory=LLMConfig)
    lora: LoRAConfig = field(default_factory=LoRAConfig)
    #: Train through a LoRA adapter, the base frozen (instruct's default).
    use_lora: bool = False
    #: Fold the adapter into the exported weights instead of exporting it as a peft dir.
    merge_export: bool = False
    #: Train through bottleneck adapters at the residual connections instead, the base
    #: frozen (OccVLA's stage 2 and VQA branch); an export that has them trains them on.
    use_adapters: bool = False
    adapter: AdapterConfig = field(default_factory=AdapterConfig)
    #: Validation generates answers for this many items per task (a fixed seeded subset
    #: of the val split, the same at every validation; -1: all of them) and scores them.
    val_samples: int = 64
    #: Prompts generated together in validation.
    val_batch_size: int = 16
    #: Encode the whole dataset with the frozen encoders once, before training, instead of
    #: every clip at every step (measured in tools/bench/world_model.py).
    cache_codes: bool = True
    max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS
    #: Pack the training batch's sequences several to a row, each attending only to itself
    #: (``core.packing``): the same loss over fewer padded positions. Not for a family
    #: whose sequences carry per-sequence targets (OccVLA, SparseOccVLA).
    pack_sequences: bool = False
    #: A packed row's tokens; 0: the batch's longest sequence's (never fewer than that).
    pack_length: int = 0
    #: Recompute the LLM's (and a trainable vision tower's) layer activations in backward
    #: instead of keeping them: the same gradients, far less activation memory (see
    #: ``occtrain plan-memory --checkpointing``), about a third more compute.
    gradient_checkpointing: bool = False


@dataclass
class InstructConfig(WorldModelConfig):
    """``model:`` of an instruct stage: through a LoRA adapter by default."""

    use_lora: bool = True


class WorldModelStage(Stage):
    """Trains the world model on the configured tasks; validates by loss, accuracy and generation.

    Under ``trainer.strategy: fsdp`` the world model (its LLM's decoder layers, then the
    rest of it) is sharded over the ranks in :meth:`configure_model`; the frozen scene
    encoder and vision tower stay whole on every rank (no gradients, no optimizer state).
    Validation and the export run on an unsharded copy gathered for them (see
    :class:`~occtrain.stages.sharding.FullCopy`): every rank holds the full world model's
    weights while it validates, rank zero alone while it exports.
    """

    consumes_count = (1, 1)
    # They come from the exports of the stages it consumes.
    frozen_prefixes = ("engine.scene_encoder.", "engine.vision.")
    shards = True

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        return family_schema(kind.model_schema, family, with_world=False)

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        cfg = ctx.model_cfg
        where = f"stages '{ctx.spec.name}'.model"
        tasks = to_object(cfg.tasks)
        self.engine = self.build_engine(ctx, tasks, where)
        # The family's own tasks: known once the engine says which family it is.
        self.engine.default_tasks("pretrain" if ctx.spec.kind == "pretrain" else "instruct")
        validate_tasks(tasks, f"{where}.tasks", self.engine.task_specs)
        self.require_tasks(t for t, w in tasks.weights.items() if w > 0)
        #: Training rows: packed to this many tokens (0: the longest sequence's), or None: one sequence each.
        self._pack: int | None = cfg.pack_length if cfg.pack_sequences else None
        self.train_through(cfg, where)
        for p in self.engine.world.unused_parameters(tasks):
            p.requires_grad_(False)
        freeze_prefixes(self.engine.world, list(ctx.spec.freeze))
        hooks = self.engine.spec.eval_hooks
        self.evaluator = Evaluator(
            scorable(self.engine.task_specs, tasks.weights),
            self.engine.task_specs,
            priors=Priors.of(ctx.data.root, ctx.shared_cache_dir),
            hooks=hooks,
        )
        self.val_means = ValidationMeans("val/loss", "val/token_acc")
        self._entries: dict[str, tuple[str, ...] | None] = {}
        #: Under sharding: the world model's unsharded copy, and (while it holds the
        #: weights) the engine over it, which validation and the export run.
        self._full: FullCopy | None = None
        self._gathered: dict[str, Any] = {}
        engine = self.engine
        if engine.encoded_inputs() or (cfg.cache_codes and engine.reads_scenes()):
            engine.prepare_inputs(ctx.data.root, ctx.cache_dir, ctx.shared_cache_dir)
            # Training then reads no occupancy; validation still scores forecasts against it.
            # A model whose prompts hold no scenes takes its occupancy targets from the
            # dataset: its shards give the annotations and the text alone.
            self._entries = (
                {"train": TEXT_ENTRIES} if engine.reads_scenes() else {"train": TEXT_ENTRIES, "val": TEXT_ENTRIES}
            )

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        """How the stage trains (an instruct stage's LLM is the consumed export's)."""
        if model.use_lora and model.use_adapters:
            raise ConfigError(f"{key}: use_lora and use_adapters are both on; train through one of them")
        if model.use_adapters:
            to_object(model.adapter).validate(f"{key}.adapter")
        if model.max_new_text_tokens < 1:
            raise ConfigError(
                f"{key}.max_new_text_tokens: {model.max_new_text_tokens}; a validation generates at least 1 token of "
                "text per answer"
            )
        if model.pack_length < 0:
            raise ConfigError(f"{key}.pack_length: {model.pack_length} is negative; give a row's tokens, or 0")
        family = schema_family(model)
        if model.pack_sequences and family is not None and not get_world(family).model.packs_sequences:
            raise ConfigError(
                f"{key}.pack_sequences: the {family} world model's sequences carry per-sequence targets and cannot "
                "share a row; set it to false"
            )

    def build_engine(self, ctx: StageContext, tasks: Any, where: str):
        """The consumed world model with this stage's task settings (instruct)."""
        return load_world_model(next(iter(ctx.inputs.values()))).with_settings(tasks, ctx.model_cfg.max_new_text_tokens)

    def train_through(self, cfg: Any, where: str) -> None:
        """What trains: the whole model, a LoRA adapter or bottleneck adapters."""
        world = self.engine.world
        if cfg.use_lora and cfg.use_adapters:
            raise ConfigError(f"{where}: use_lora and use_adapters are both on; train through one of them")
        if cfg.use_lora:
            world.llm.requires_grad_(False)
            world.requires_grad_(False)
            world.llm = apply_lora(world.llm, cfg.lora)
            if world.trains_own_parts_with_lora:  # the family's own parts train beside the adapter
                for name, p in world.named_parameters():
                    if not name.startswith("llm."):
                        p.requires_grad_(True)
        if cfg.use_adapters:
            # The LM's own weights freeze; its adapters and the model's own parts (image
            # projector, occupancy queries and projector) train.
            adapter_cfg = to_object(cfg.adapter)
            adapter_cfg.validate(f"{where}.adapter")
            world.llm.requires_grad_(False)
            for adapter in adapters_of(world.llm) or add_adapters(world.llm, adapter_cfg):
                adapter.requires_grad_(True)
        if cfg.gradient_checkpointing:
            checkpoint_layers(world.llm)
            vision = self.engine.vision
            if vision is not None and any(p.requires_grad for p in vision.parameters()):
                checkpoint_layers(vision.tower)

    def entries(self, split: str) -> tuple[str, ...] | None:
        return self._entries.get(split)

    # -- sharding (trainer.strategy: fsdp)
    def configure_model(self) -> None:
        """Shard the world model under :class:`ShardedStrategy`; nothing under any other
        strategy. Lightning calls it again for ``validate``: sharded once."""
        world = self.engine.world
        if not isinstance(self.trainer.strategy, ShardedStrategy) or is_sharded(world):
            return
        self._full = FullCopy(world)  # before sharding: a copy of the plain module
        mesh = self.device_mesh
        assert mesh is not None  # the sharded strategy made one
        shard_world_model(world, mesh["data_parallel"])

    def _gather(self, everywhere: bool) -> None:
        """Fill the unsharded copy (a collective: every rank calls it); see ``FullCopy.gather``."""
        if self._full is not None and self._full.gather(self.engine.world, self.device, everywhere):
            self._gathered["engine"] = _with_world(self.engine, self._full.module)

    def _release(self) -> None:
        if self._full is not None:
            self._full.release()
            self._gathered.clear()

    @property
    def _unsharded(self):
        """The engine validation and the export run: over the gathered copy when sharded."""
        return self._gathered.get("engine", self.engine)

    # -- training
    def compiled_blocks(self) -> list[torch.nn.Module]:
        """The LLM's decoder layers (LoRA's or the adapters' layers inside them included)."""
        return decoder_layers(self.engine.world.llm)

    def on_train_start(self) -> None:
        # Counted from the world model as it trains: sharded, with LoRA or adapters.
        self._flops = TransformerFlops.of(self.engine.world.llm)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor | None:
        clips = clips_from_batch(batch)
        model_batch, names = self.engine.task_batch(clips, batch, self.step_seed(self.global_step), self._pack)
        self.log("train/skipped_clips", float(names.count(None)), reduce_fx="sum", batch_size=len(clips))
        self.step_work = StepWork(samples=0, tokens=0, flops=0.0)
        if model_batch is None:
            return None  # no clip of the batch has a configured task: no step
        bs = len(names) - names.count(None)
        self.step_work = lm_step_work(model_batch, bs, self._flops.train_per_token)
        out = self.engine.world(move_batch(model_batch, self.device))
        loss = out.loss
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
        engine = self._unsharded
        model_batch, names = engine.task_batch(clips, batch, seed=self.ctx.data.seed)
        if model_batch is not None:
            out = engine.world(move_batch(model_batch, self.device))
            bs = len(names) - names.count(None)
            self.val_means.update("val/loss", out.loss, bs)
            acc = engine.world.token_accuracy(out.logits, model_batch["labels"].to(self.device))
            self.val_means.update("val/token_acc", acc, bs)

    def on_validation_epoch_start(self) -> None:
        # Sharded, every forward would be a collective: ranks with other numbers of val
        # batches or generated tokens would wait on each other. The full copy has none.
        self._gather(everywhere=True)

    def on_validation_epoch_end(self) -> None:
        cfg = self.ctx.model_cfg
        self.evaluator.run(self._unsharded, self.ctx.data.root, "val", cfg.val_batch_size, samples=cfg.val_samples)
        self._release()
        self.log_dict(self.val_means.pop())
        self.log_dict(self.evaluator.compute("val"))  # texts and pictures stay for report()

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        params = [p for p in self.engine.world.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    # -- reporting and export
    def report(self) -> StageReport:
        world = self.engine.world
        total, trained = count_parameters(world), count_parameters(world, trainable=True)
        summary = (
            f"world model {total / 1e6:.2f}M params ({trained / 1e6:.2f}M trained), vocab {len(self.engine.vocab)}"
        )
        # Scene tokens per frame: Occ-LLM's patch-size table reads it beside the step time.
        metrics = {"params": float(total), "scene_tokens": float(self.engine.vocab.scene_len)}
        if self._full is not None:  # what this rank holds of the sharded world model
            metrics["params_per_rank"] = float(local_numel(world))
        return StageReport(
            summary,
            metrics,
            texts=list(self.evaluator.texts),
            scenes=list(self.evaluator.scenes),
            coverage=dict(self.evaluator.coverage),
            sample_sets=list(self.evaluator.sample_sets),
        )

    def prepare_export(self) -> None:
        self._gather(everywhere=False)  # rank zero's copy on the CPU: what export() writes

    def export(self, path: Path) -> Path:
        if self._full is not None and not self._full.loaded:
            raise RuntimeError("a sharded stage exports after prepare_export() ran on every rank")
        return export_engine(self._unsharded, path, stage=self.ctx.spec.name, merge=self.ctx.model_cfg.merge_export)

    evaluable = True
    saves_predictions = True

    @classmethod
    def evaluate_export(cls, request: EvalRequest) -> EvalResult:
        """The export's answers generated on every item of the split (or a fixed subset),
        scored with its family's scorers: by default the tasks it trained on."""
        return evaluate_engine(load_world_model(request.export).eval(), request)

    drivable = True

    @classmethod
    def driver(cls, request: EvalRequest) -> StageDriver:
        """The world model drives by its family's ``plan`` operation."""
        return world_model_driver(load_world_model(request.export), str(request.export))


def _with_world(engine: Any, world: torch.nn.Module) -> Any:
    """A shallow copy of ``engine`` (its caches and frozen encoders shared) over ``world``."""
    twin = copy.copy(engine)
    object.__setattr__(twin, "_modules", {**engine._modules, "world": world})
    return twin


class PretrainStage(WorldModelStage):
    """Builds a fresh world model of its family over the exports it consumes."""

    consumes_kinds = ("tokenizer", "vision")
    consumes_count = (0, 2)

    @classmethod
    def family_of(cls, model: dict, consumed: dict[str, Any]) -> str | None:
        """``model.family``, else the consumed tokenizer's family."""
        if model.get("family"):
            return str(model["family"])
        for planned in consumed.values():
            if planned.spec.kind == "tokenizer":
                return planned.family
        return None

    @classmethod
    def model_schema(cls, kind: StageKind, family: str | None, model: dict | None = None) -> type:
        return family_schema(kind.model_schema, family, with_world=True)

    @classmethod
    def check_family(cls, family: str | None, consumed: dict[str, Any], where: str) -> None:
        """A pretrain stage builds a world model: its family must have one, and it consumes
        what that family's model is built over."""
        if family is None:
            raise ConfigError(
                f"{where}: model.family is empty and no tokenizer stage is consumed; name the family whose world model "
                "to build"
            )
        get_world(family, f"{where}: model.family")
        kinds = sorted(p.spec.kind for p in consumed.values())
        wanted = sorted(get_world(family).inputs)
        if kinds != wanted:
            raise ConfigError(
                f"{where}: a '{family}' world model is built over {' and '.join(wanted) or 'nothing'} "
                f"(consumes those stages), got {' and '.join(kinds) or 'none'}"
            )

    @classmethod
    def check_model(cls, model: Any, key: str) -> None:
        """Also the LLM it builds, through the backend's own config validators."""
        super().check_model(model, key)
        check_llm(to_object(model.llm), f"{key}.llm")

    def build_engine(self, ctx: StageContext, tasks: Any, where: str):
        cfg = ctx.model_cfg
        family = cfg.family or self.inferred_family(ctx)
        world_cfg = to_object(cfg[family]) if family in cfg else None
        return new_world_model(
            self._exports_by_kind(where),
            cfg.llm,
            tasks,
            ctx.data.root,
            cfg.max_new_text_tokens,
            family,
            world_cfg,
            where,
        )

    def inferred_family(self, ctx: StageContext) -> str:
        """The consumed tokenizer's family (what ``family_of`` read from the recipe)."""
        for path in ctx.inputs.values():
            if export_kind(Path(path)) == "tokenizer":
                return tokenizer_family(read_config(Path(path))["arch"])
        raise ConfigError(f"stages '{ctx.spec.name}'.model.family is empty and no tokenizer stage is consumed")

    def _exports_by_kind(self, where: str) -> dict[str, Path]:
        """A pretrain stage's inputs by stage kind: at most one of each."""
        found: dict[str, Path] = {}
        for path in self.ctx.inputs.values():
            kind = export_kind(Path(path))
            if kind in found:
                raise ConfigError(f"{where}: consumes two {kind} stages; a world model reads one")
            found[kind] = Path(path)
        return found


class InstructStage(WorldModelStage):
    consumes_kinds = WORLD_MODEL_KINDS


PRETRAIN = register(
    StageKind(
        name="pretrain", model_schema=WorldModelConfig, data_kind="clips", module=PretrainStage, monitor="val/token_acc"
    )
)
INSTRUCT = register(
    StageKind(
        name="instruct", model_schema=InstructConfig, data_kind="clips", module=InstructStage, monitor="val/token_acc"
    )
)

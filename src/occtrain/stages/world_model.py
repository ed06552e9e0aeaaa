"""Stage kinds ``pretrain`` and ``instruct``: the OccLLaMA world model over the joint vocabulary.

``pretrain`` consumes a tokenizer export, trains a local BPE text tokenizer on the
dataset's text, lays out the joint vocabulary and trains the LLM on OccLLaMA's five tasks.
``instruct`` consumes a world-model export and tunes it on NuScenes-QA and chain-of-thought
planning through a peft LoRA adapter, the base frozen.

Both validate by teacher-forced loss and token accuracy on every val batch, and by
generation (the answer parts of each task rolled out autoregressively, scenes by
next-scene prediction) on the first ``generate_batches`` val batches, scored with the
papers' metrics: forecasting mIoU/IoU (OccWorld convention) through the tokenizer's
decoder, planning L2/collision (ST-P3 and UniAD), QA accuracy, caption metrics.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch

from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.data.layout import DatasetIndex
from occtrain.data.synth.text import parse_meta_action
from occtrain.data.tasks import (
    INSTRUCT_TASKS, PRETRAIN_TASKS, TASKS, Actions, Clip, Part, Scene, TaskConfig, Text,
    clips_from_batch, corpus_texts, ego_future, future_agent_boxes, sample_task, validate_tasks,
)
from occtrain.errors import ConfigError
from occtrain.io import is_rank_zero
from occtrain.progress import progress_bar
from occtrain.occ3d import FREE, FUTURE_STEPS
from occtrain.metrics import CaptionMetric, ForecastMetric, PlanningMetric, QAMetric
from occtrain.models.llm import apply_lora, build_llm
from occtrain.models.planner import constant_velocity_plan
from occtrain.models.text_tokenizer import train_text_tokenizer
from occtrain.models.vocab import JointVocab
from occtrain.models.world_model import OccWorldModel, collate
from occtrain.stages import StageContext, StageKind, register
from occtrain.stages.common import EXPORT_CONFIG, configure_adamw, flatten_metrics, read_export, write_export
from occtrain.stages.tokenizer import load_tokenizer

TEXT_TOKENIZER_DIR = "text_tokenizer"
SCENE_TOKENIZER_DIR = "scene_tokenizer"
ADAPTER_DIR = "adapter"
CODE_CACHE = "scene_codes.safetensors"
#: The shard entries a world-model stage trains on when scenes come from the code cache.
TEXT_ENTRIES = ("ann.json", "qa.json", "narration.txt")


@dataclass
class PretrainModelConfig:
    """``model:`` of a pretrain stage (OccLLaMA Sec. III-C, multi-task pretraining)."""

    llm: LLMConfig = field(default_factory=LLMConfig)
    tasks: TaskConfig = field(default_factory=TaskConfig)
    lora: LoRAConfig = field(default_factory=LoRAConfig)
    #: Train through a LoRA adapter, the base frozen (instruct's default).
    use_lora: bool = False
    #: Fold the adapter into the exported weights instead of exporting it as a peft dir.
    merge_export: bool = False
    #: Val batches that also run generation (it dominates validation time).
    generate_batches: int = 2
    #: Encode the whole dataset with the frozen tokenizer once, before training, instead of
    #: every clip at every step (measured in tools/bench/world_model.py).
    cache_codes: bool = True
    max_new_text_tokens: int = 96


@dataclass
class InstructModelConfig(PretrainModelConfig):
    """``model:`` of an instruct stage: QA and chain-of-thought planning through LoRA."""

    tasks: TaskConfig = field(default_factory=lambda: TaskConfig(weights={t: 1.0 for t in INSTRUCT_TASKS}))
    use_lora: bool = True


@dataclass
class CotOutput:
    """A generated chain of thought: its text and the trajectory that follows it."""

    text: str
    waypoints: np.ndarray  # (6, 2)


class WorldModelEngine(torch.nn.Module):
    """The scene tokenizer (frozen), the world model and the text tokenizer, used as one.

    Turns clips and task parts into token sequences, and rolls answers out by generation.
    Stages, ``occtrain eval``, the planner and distillation all go through this class.
    """

    def __init__(self, scene_tokenizer: torch.nn.Module, world: OccWorldModel, text_tokenizer: Any):
        super().__init__()
        self.scene_tokenizer = scene_tokenizer.eval().requires_grad_(False)
        self.world = world
        self.text_tokenizer = text_tokenizer
        #: Sample token -> codes, when the dataset was encoded ahead (see build_code_cache).
        self.code_cache: dict[str, torch.Tensor] | None = None

    @property
    def vocab(self) -> JointVocab:
        return self.world.vocab

    def train(self, mode: bool = True) -> WorldModelEngine:
        super().train(mode)
        self.scene_tokenizer.eval()  # frozen: no dropout, no codebook updates
        return self

    # -- scenes
    @torch.no_grad()
    def scene_codes(self, batch: dict, needed: list[set[int]]) -> dict[tuple[int, int], torch.Tensor]:
        """Codes (h*w,) of the clip frames each sample needs: from the code cache when one is
        set (then the batch needs no occupancy at all), else encoded in one tokenizer batch."""
        keys = [(b, f) for b, frames in enumerate(needed) for f in sorted(frames)]
        if not keys:
            return {}
        if self.code_cache is not None:
            return {(b, f): self.code_cache[batch["ann"][b]["tokens"][f]] for b, f in keys}
        frames = torch.stack([batch["semantics"][b, f] for b, f in keys]).long()
        codes = self.scene_tokenizer.encode(frames).flatten(1)
        return dict(zip(keys, codes))

    @torch.no_grad()
    def build_code_cache(self, data_root: str | Path, cache_file: Path, batch_size: int = 8) -> None:
        """Encode every frame of the dataset once (the tokenizer is frozen), kept in
        ``cache_file`` (safetensors, written atomically) so a resumed stage reuses it."""
        from safetensors.torch import load_file, save_file

        if cache_file.is_file():
            self.code_cache = load_file(str(cache_file))
            return
        index = DatasetIndex.open(data_root)
        samples = [(scene, token) for scene, tokens in index.scenes.items() for token in tokens]
        cache: dict[str, torch.Tensor] = {}
        device = self.scene_tokenizer.codebook.device
        with progress_bar(len(samples), "encoding scenes with the frozen tokenizer") as advance:
            for i in range(0, len(samples), batch_size):
                chunk = samples[i : i + batch_size]
                sem = torch.from_numpy(np.stack([index.labels(s, t)["semantics"] for s, t in chunk])).long().to(device)
                for (_, token), codes in zip(chunk, self.scene_tokenizer.encode(sem).flatten(1).cpu()):
                    cache[token] = codes.to(torch.int32).contiguous()
                advance(len(chunk))
        if is_rank_zero():
            cache_file.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache_file.with_suffix(".tmp")
            save_file(cache, str(tmp))
            tmp.replace(cache_file)
        self.code_cache = cache

    @torch.no_grad()
    def decode_scenes(self, codes: torch.Tensor) -> torch.Tensor:
        """(N, h*w) codes -> (N, X, Y, Z) class labels through the tokenizer's decoder."""
        h, w = self.scene_tokenizer.latent_hw
        return self.scene_tokenizer.decode(codes.view(-1, h, w)).argmax(1)

    # -- sequences
    def encode_parts(self, parts: list[Part], codes: dict[int, torch.Tensor]):
        """One task's parts -> a TokenSequence, scenes looked up by clip frame in ``codes``."""
        builder = self.world.builder()
        for part in parts:
            if isinstance(part, Text):
                builder.text(part.text, part.supervise)
            elif isinstance(part, Scene):
                builder.scene(codes[part.frame], part.supervise)
            else:
                builder.actions(torch.tensor(part.xy, dtype=torch.float32), part.supervise)
        return builder.build()

    def task_batch(self, clips: list[Clip], batch: dict, tasks: TaskConfig, seed: int) -> tuple[dict, list[str]]:
        """Draw a task per clip and collate the sequences into a model batch."""
        drawn = [sample_task(c, tasks, seed, c.anchor["token"]) for c in clips]
        needed = [{p.frame for p in parts if isinstance(p, Scene)} for _, parts in drawn]
        codes = self.scene_codes(batch, needed)
        seqs = [
            self.encode_parts(parts, {f: codes[(b, f)] for f in needed[b]}) for b, (_, parts) in enumerate(drawn)
        ]
        return collate(seqs, pad_id=self.vocab.pad_id), [name for name, _ in drawn]

    # -- generation
    @torch.no_grad()
    def rollout(
        self, parts: list[Part], codes: dict[int, torch.Tensor], max_new_text_tokens: int = 96
    ) -> tuple[list[Part], dict[int, torch.Tensor]]:
        """Generate the answer parts of a task one after the other, each conditioned on the
        ones generated before it (not on the ground truth): the prompt is the parts before
        the first supervised one; a text answer is generated up to the end-of-text token, an
        action answer as many waypoints as the reference has, a scene by one next-scene pass.
        Returns the generated parts and the codes of every scene, generated ones included.
        """
        first = next(i for i, p in enumerate(parts) if p.supervise)
        codes = dict(codes)
        decoder = self.world.decoder(self.encode_parts(parts[:first], codes).input_ids)
        generated: list[Part] = []
        next_frame = max(codes) + 1 if codes else 0
        for target in parts[first:]:  # the answer parts are contiguous: one decoder, one KV cache
            if isinstance(target, Text):
                generated.append(Text(self.vocab.decode_text(decoder.text(max_new_text_tokens)), True))
            elif isinstance(target, Actions):
                xy = decoder.actions(steps=len(target.xy))
                generated.append(Actions(tuple(map(tuple, xy.tolist())), True))
            else:
                codes[next_frame] = decoder.scene()
                generated.append(Scene(next_frame, True))
                next_frame += 1
        return generated, codes

    def chain_of_thought(self, clips: list[Clip], batch: dict, max_new_text_tokens: int = 96) -> list[CotOutput]:
        """Narration, meta action and trajectory generated for each clip (OccLLaMA's CoT planning)."""
        outputs = []
        cfg = TaskConfig(weights={"cot_planning": 1.0})
        parts_per_clip = [TASKS["cot_planning"](c, cfg, np.random.default_rng(0)) for c in clips]
        needed = [{p.frame for p in ps if isinstance(p, Scene)} if ps else set() for ps in parts_per_clip]
        codes = self.scene_codes(batch, needed)
        for b, parts in enumerate(parts_per_clip):
            if parts is None:
                outputs.append(CotOutput("", np.zeros((6, 2))))
                continue
            (text, traj), _ = self.rollout(parts, {f: codes[(b, f)] for f in needed[b]}, max_new_text_tokens)
            outputs.append(CotOutput(text.text, np.asarray(traj.xy)))
        return outputs


class Evaluator(torch.nn.Module):
    """Rolls out the answers of the evaluation tasks and scores them with the papers' metrics.

    Planning is scored three ways, OccLLaMA's M0-M3 comparison: ``plan_direct`` (the
    planning task's trajectory), ``plan_alternate`` (the waypoints of the forecasting
    rollout, alternating with generated scenes) and ``plan_cot`` (after the chain of thought).
    """

    TASKS = ("forecasting", "planning", "qa", "cot_planning")

    def __init__(
        self, tasks: TaskConfig, max_new_text_tokens: int, record: bool = False, qa_prior: dict[str, str] | None = None
    ):
        super().__init__()
        self.tasks = tasks
        self.max_new_text_tokens = max_new_text_tokens
        #: Baselines scored on the same samples: copy the current scene forward, stand still,
        #: drive on at constant velocity, answer the commonest training answer of the type.
        self.qa_prior = qa_prior or {}
        self.metrics = torch.nn.ModuleDict({
            "forecast_occworld": ForecastMetric(),
            "baseline_copy_forecast_occworld": ForecastMetric(),
            "baseline_constant_velocity": PlanningMetric(),
            "baseline_stationary": PlanningMetric(),
            "baseline_prior_qa": QAMetric(),
            "plan_direct": PlanningMetric(),
            "plan_alternate": PlanningMetric(),
            "plan_cot": PlanningMetric(),
            "qa": QAMetric(),
            "cot_caption": CaptionMetric(),
        })
        self.meta_hits = 0
        self.meta_total = 0
        self.texts: list[dict] = []
        #: With ``record``, every prediction in the formats ``occtrain score`` reads.
        self.record = record
        self.predictions: dict[str, dict] = {"planning": {}, "planning_gt": {}, "forecast": {}, "qa": {}, "captions": {}, "captions_gt": {}}

    @torch.no_grad()
    def update(self, engine: WorldModelEngine, clips: list[Clip], batch: dict) -> None:
        rng = np.random.default_rng(0)
        for task in self.TASKS:
            if self.tasks.weights.get(task, 0) <= 0:
                continue
            built = [TASKS[task](c, self.tasks, rng) for c in clips]
            needed = [{p.frame for p in ps if isinstance(p, Scene) and not p.supervise} if ps else set() for ps in built]
            codes = engine.scene_codes(batch, needed)
            for b, parts in enumerate(built):
                if parts is not None:
                    generated, all_codes = engine.rollout(parts, {f: codes[(b, f)] for f in needed[b]}, self.max_new_text_tokens)
                    self._score(engine, task, clips[b], parts, generated, all_codes, batch["semantics"][b])
        if any(self.tasks.weights.get(t, 0) > 0 for t in ("planning", "forecasting", "cot_planning")):
            for clip in clips:
                self._score_plan_baselines(clip.anchor)

    def _score_plan_baselines(self, anchor: dict) -> None:
        """Standing still and constant velocity, on every clip a plan is scored on."""
        dev = self.metrics["plan_direct"].device
        future, mask = ego_future(anchor)
        gt_xy, gt_mask = torch.tensor(future, dtype=torch.float32, device=dev)[None], torch.tensor(mask, device=dev)[None]
        agents = [future_agent_boxes(anchor)]
        speed = torch.tensor([float(anchor.get("ego_speed", 0.0))], device=dev)
        self.metrics["baseline_constant_velocity"].update(constant_velocity_plan(speed, FUTURE_STEPS), gt_xy, gt_mask, agents)
        self.metrics["baseline_stationary"].update(torch.zeros_like(gt_xy), gt_xy, gt_mask, agents)

    def _score(self, engine, task, clip, parts, generated, codes, semantics) -> None:
        anchor, token = clip.anchor, clip.anchor["token"]
        dev = self.metrics["plan_direct"].device  # metrics follow the module onto the accelerator
        future, mask = ego_future(anchor)
        gt_xy, gt_mask = torch.tensor(future, dtype=torch.float32, device=dev)[None], torch.tensor(mask, device=dev)[None]
        agents = [future_agent_boxes(anchor)]
        actions = [p for p in generated if isinstance(p, Actions)]
        if task in ("planning", "forecasting", "cot_planning") and actions:
            # The forecasting rollout yields one waypoint per scene; together they are its plan.
            xy = [pt for p in actions for pt in p.xy] if task == "forecasting" else list(actions[-1].xy)
            pred = torch.zeros_like(gt_xy)
            pred[0, : len(xy)] = torch.tensor(xy[: pred.shape[1]], dtype=torch.float32, device=dev)
            plan_mask = gt_mask.clone()
            plan_mask[0, len(xy):] = False
            name = {"planning": "plan_direct", "forecasting": "plan_alternate", "cot_planning": "plan_cot"}[task]
            self.metrics[name].update(pred, gt_xy, plan_mask, agents)
            if self.record and task == "planning":
                self.predictions["planning"][token] = pred[0].tolist()
                self.predictions["planning_gt"][token] = {
                    "traj": future.tolist(), "mask": mask.astype(int).tolist(), "agents": [a.tolist() for a in agents[0]],
                }
        if task == "forecasting":
            scenes = [p for p in generated if isinstance(p, Scene)]
            decoded = engine.decode_scenes(torch.stack([codes[p.frame] for p in scenes])).cpu()
            a = clip.anchor_index
            steps = FUTURE_STEPS
            pred = torch.full((1, steps, *decoded.shape[1:]), FREE, dtype=torch.long)
            target = torch.full_like(pred, FREE)
            valid = torch.zeros(1, steps, dtype=torch.bool)
            n = min(len(scenes), steps, semantics.shape[0] - a - 1)
            pred[0, :n] = decoded[:n]
            target[0, :n] = semantics[a + 1 : a + 1 + n].long()
            valid[0, :n] = True
            self.metrics["forecast_occworld"].update(pred.to(dev), target.to(dev), valid.to(dev))
            copy = semantics[a].long()[None, None].expand_as(pred)
            self.metrics["baseline_copy_forecast_occworld"].update(copy.to(dev), target.to(dev), valid.to(dev))
            if self.record:
                self.predictions["forecast"][token] = (anchor["scene"], decoded[:n].numpy().astype(np.uint8))
        if task == "qa":
            question = parts[-2].text.removeprefix("Question: ").removesuffix(" Answer:")
            q = next(q for q in clip.qa if q["question"] == question)
            answer = generated[0].text.strip()
            self.metrics["qa"].update([answer], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            prior = self.qa_prior.get(q["template_type"], "")
            self.metrics["baseline_prior_qa"].update([prior], [q["answer"]], [q["template_type"]], [q["num_hop"]])
            self._keep_text("qa", parts[-2].text, answer, q["answer"])
            if self.record:
                self.predictions["qa"][f"{token}|{question}"] = (q, answer)
        if task == "cot_planning":
            text, reference = generated[0].text, parts[-2].text
            self.metrics["cot_caption"].update([text], [[reference]], ids=[token])
            self._keep_text("cot", "Task: describe the scene, then plan.", text, reference)
            self.meta_total += 1
            self.meta_hits += int(parse_meta_action(text) == anchor["meta_action"])
            if self.record:
                self.predictions["captions"][token] = text
                self.predictions["captions_gt"][token] = [reference]

    def _keep_text(self, task: str, prompt: str, prediction: str, reference: str) -> None:
        if len(self.texts) < 12:
            self.texts.append({"task": task, "prompt": prompt, "prediction": prediction, "reference": reference})

    def compute(self, prefix: str) -> dict[str, float]:
        out: dict[str, float] = {}
        for name, metric in self.metrics.items():
            if metric.update_count:
                out.update(flatten_metrics(f"{prefix}/{name}", metric.compute()))
        if self.meta_total:
            out[f"{prefix}/meta_action_acc"] = 100.0 * self.meta_hits / self.meta_total
        return out

    def reset(self) -> None:
        for metric in self.metrics.values():
            metric.reset()
        self.meta_hits = self.meta_total = 0
        self.texts = []  # the dashboard shows the last validation's outputs, as the metrics do


# ----------------------------------------------------------------------------- building


def qa_prior(data_root: str | Path) -> dict[str, str]:
    """The commonest training answer of each NuScenes-QA template type (the QA baseline)."""
    from collections import Counter

    questions = DatasetIndex.open(data_root).questions("train") or []
    by_type: dict[str, Counter] = {}
    for q in questions:
        by_type.setdefault(q["template_type"], Counter())[q["answer"]] += 1
    return {t: c.most_common(1)[0][0] for t, c in by_type.items()}


def _consumed(ctx: StageContext) -> tuple[Path, dict]:
    if len(ctx.inputs) != 1:
        raise ConfigError(f"stages '{ctx.spec.name}': a {ctx.spec.kind} stage consumes exactly one earlier stage (consumes: [...])")
    export = next(iter(ctx.inputs.values()))
    _, config = read_export(export)
    return export, config


def _text_tokenizer_for(ctx: StageContext, cfg: PretrainModelConfig):
    """The LLM's own tokenizer when ``llm.path`` is set, else a BPE trained on the dataset's text.

    Training is deterministic, so every DDP rank (and a resumed run) builds the same one.
    """
    if cfg.llm.path:
        from occtrain.models.llm import load_text_tokenizer

        return load_text_tokenizer(cfg.llm.path)
    index = DatasetIndex.open(ctx.data.root)
    return train_text_tokenizer(corpus_texts(index), cfg.llm.text_vocab_size)


def build_engine(ctx: StageContext) -> WorldModelEngine:
    """A fresh world model over a tokenizer export (pretrain), or a world-model export (instruct)."""
    cfg = ctx.model_cfg
    export, config = _consumed(ctx)
    if config.get("stage_kind") == "tokenizer":
        if ctx.spec.kind != "pretrain":
            raise ConfigError(f"stages '{ctx.spec.name}': an {ctx.spec.kind} stage consumes a pretrain stage, not a tokenizer")
        scene_tok = load_tokenizer(export)
        text_tok = _text_tokenizer_for(ctx, cfg)
        vocab = JointVocab(text_tok, num_codes=scene_tok.num_codes, scene_hw=tuple(scene_tok.latent_hw), llm_cfg=cfg.llm)
        llm = build_llm(cfg.llm, len(vocab))
        world = OccWorldModel(llm, vocab, codebook=scene_tok.codebook, scene_prediction=cfg.llm.scene_prediction)
        return WorldModelEngine(scene_tok, world, text_tok)
    if config.get("stage_kind") == "world_model":
        return load_world_model(export)
    raise ConfigError(f"stages '{ctx.spec.name}' consumes {export}, which is neither a tokenizer nor a world-model export")


def load_world_model(export_dir: Path) -> WorldModelEngine:
    """Rebuild the engine from a world-model export: weights, vocab, tokenizers, adapter."""
    from transformers import PreTrainedTokenizerFast

    export_dir = Path(export_dir)
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "world_model":
        raise ConfigError(f"{export_dir}: not a world-model export (stage kind '{config.get('stage_kind')}')")
    scene_tok = load_tokenizer(export_dir / SCENE_TOKENIZER_DIR)
    text_tok = PreTrainedTokenizerFast.from_pretrained(str(export_dir / TEXT_TOKENIZER_DIR), local_files_only=True)
    vocab = JointVocab.from_json(config["vocab"], text_tok)
    world = OccWorldModel.from_export(config["world"], vocab, codebook=scene_tok.codebook)
    world.load_state_dict(state)
    if (export_dir / ADAPTER_DIR).is_dir():
        from peft import PeftModel

        world.llm = PeftModel.from_pretrained(world.llm, str(export_dir / ADAPTER_DIR), is_trainable=False)
    return WorldModelEngine(scene_tok, world, text_tok)


# ----------------------------------------------------------------------------- the stage


class WorldModelStage(L.LightningModule):
    """Trains the world model on the configured tasks; validates by loss, accuracy and generation."""

    def __init__(self, ctx: StageContext):
        super().__init__()
        cfg = ctx.model_cfg
        validate_tasks(cfg.tasks, f"stages '{ctx.spec.name}'.model.tasks")
        self.ctx = ctx
        self.engine = build_engine(ctx)
        world = self.engine.world
        if cfg.use_lora:
            world.llm.requires_grad_(False)
            world.requires_grad_(False)
            world.llm = apply_lora(world.llm, cfg.lora)
        from occtrain.stages.common import freeze_prefixes

        freeze_prefixes(world, list(ctx.spec.freeze))
        self.evaluator = Evaluator(cfg.tasks, cfg.max_new_text_tokens, qa_prior=qa_prior(ctx.data.root))
        if cfg.cache_codes:
            self.engine.build_code_cache(ctx.data.root, ctx.stage_dir / "cache" / CODE_CACHE)
            # Training then reads no occupancy; validation still scores forecasts against it.
            self.entries = {"train": TEXT_ENTRIES, "val": None}

    # -- training
    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        clips = clips_from_batch(batch)
        seed = self.ctx.data.seed * 1_000_003 + self.global_step
        model_batch, names = self.engine.task_batch(clips, batch, self.ctx.model_cfg.tasks, seed)
        out = self.engine.world(_to(model_batch, self.device))
        bs = len(clips)
        self.log("train/loss", out.loss, prog_bar=True, batch_size=bs)
        self.log("train/text_loss", out.text_loss, batch_size=bs)
        self.log("train/scene_loss", out.scene_loss, batch_size=bs)
        return out.loss

    # -- validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        clips = clips_from_batch(batch)
        cfg = self.ctx.model_cfg
        model_batch, _ = self.engine.task_batch(clips, batch, cfg.tasks, seed=batch_idx)
        out = self.engine.world(_to(model_batch, self.device))
        bs = len(clips)
        self.log("val/loss", out.loss, batch_size=bs, sync_dist=True)
        acc = self.engine.world.token_accuracy(out.logits, model_batch["labels"].to(self.device))
        self.log("val/token_acc", acc, batch_size=bs, sync_dist=True)
        if batch_idx < cfg.generate_batches:
            self.evaluator.update(self.engine, clips, batch)

    def on_validation_epoch_end(self) -> None:
        self.log_dict(self.evaluator.compute("val"))
        self.evaluator.reset()

    def configure_optimizers(self) -> dict:
        params = [p for p in self.engine.world.parameters() if p.requires_grad]
        return configure_adamw(params, self.ctx.spec.optim, self.ctx.trainer.max_steps)

    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        # The frozen scene tokenizer comes from its own export; checkpoints need not carry it.
        return {k: v for k, v in super().state_dict(*args, **kwargs).items() if not k.startswith("engine.scene_tokenizer.")}

    def load_state_dict(self, state_dict: dict[str, Any], strict: bool = True, **kwargs: Any) -> Any:
        missing, unexpected = super().load_state_dict(state_dict, strict=False)
        if unexpected or [k for k in missing if not k.startswith("engine.scene_tokenizer.")]:
            raise ConfigError("checkpoint does not match this stage's model; run with --restart for this stage")

    # -- reporting and export
    def summary(self) -> str:
        world = self.engine.world
        total = sum(p.numel() for p in world.parameters())
        trainable = sum(p.numel() for p in world.parameters() if p.requires_grad)
        return f"world model {total / 1e6:.2f}M params ({trainable / 1e6:.2f}M trained), vocab {len(self.engine.vocab)}"

    def summary_metrics(self) -> dict[str, float]:
        return {"params": float(sum(p.numel() for p in self.engine.world.parameters()))}

    def samples(self) -> list[dict]:
        return list(self.evaluator.texts)

    def export(self, path: Path) -> Path:
        return export_engine(self.engine, path, merge=self.ctx.model_cfg.merge_export, stage=self.ctx.spec.name)


def export_engine(engine: WorldModelEngine, path: Path, merge: bool, stage: str) -> Path:
    """Write a self-contained world-model export: weights, config, both tokenizers, adapter.

    With a LoRA adapter, ``model.safetensors`` holds the base weights under their plain
    names and ``adapter/`` the peft adapter; ``merge`` folds the adapter into the weights
    instead. The engine itself is left as it was.
    """
    from peft import PeftModel

    world = engine.world
    llm = world.llm
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        engine.text_tokenizer.save_pretrained(str(tmp / TEXT_TOKENIZER_DIR))
        extra = {TEXT_TOKENIZER_DIR: tmp / TEXT_TOKENIZER_DIR, SCENE_TOKENIZER_DIR: Path(engine.scene_tokenizer.export_dir)}
        state = world.state_dict()
        if isinstance(llm, PeftModel):
            if merge:
                state = _merged_state(world, llm)
            else:
                llm.save_pretrained(str(tmp / ADAPTER_DIR))
                extra[ADAPTER_DIR] = tmp / ADAPTER_DIR
            state = _base_names(state)
        config = {"stage_kind": "world_model", "stage": stage, "vocab": engine.vocab.to_json(), "world": world.export_config()}
        return write_export(path, state, config, extra)


def _base_names(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """peft's wrapped names (``base_model.model.``, ``.base_layer.``) back to the plain model's; LoRA weights dropped."""
    out = {}
    for name, value in state.items():
        if ".lora_" in name:
            continue
        out[name.replace("base_model.model.", "").replace(".base_layer.", ".")] = value
    return out


def _merged_state(world: OccWorldModel, llm: Any) -> dict[str, torch.Tensor]:
    """The world model's weights with the adapter folded in, computed on a copy."""
    import copy

    merged = copy.deepcopy(llm).merge_and_unload()
    state = {k: v for k, v in world.state_dict().items() if not k.startswith("llm.")}
    state.update({f"llm.{k}": v for k, v in merged.state_dict().items()})
    return state


def _to(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


PRETRAIN = register(
    StageKind(name="pretrain", model_schema=PretrainModelConfig, data_kind="clips", build=WorldModelStage, monitor="val/token_acc")
)
INSTRUCT = register(
    StageKind(name="instruct", model_schema=InstructModelConfig, data_kind="clips", build=WorldModelStage, monitor="val/token_acc")
)

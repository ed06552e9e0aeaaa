"""What every stage kind shares: the Trainer, the resumable data position, optimizers, metric names."""

from __future__ import annotations

import io
import logging
import math
import os
import re
import time
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import field, make_dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, ProgressBar
from lightning.pytorch.plugins.io import TorchCheckpointIO
from rich.progress import BarColumn, Progress, TextColumn
from torchmetrics import MeanMetric

from occtrain.config.recipe import OptimConfig
from occtrain.config.schema import TrainerConfig
from occtrain.core.registry import get_world
from occtrain.data.datamodule import ResumableLoader
from occtrain.data.shards import PAD_KEY
from occtrain.engine import Evaluator, Priors, scorable
from occtrain.errors import ConfigError, OcctrainError
from occtrain.io import atomic_open, remove_inside
from occtrain.metrics import compute_metrics
from occtrain.progress import Ticker, console, plain, progress_bar
from occtrain.stages.base import EvalRequest, EvalResult, lacking_tasks
from occtrain.stages.loggers import build_loggers
from occtrain.stages.sharding import trainer_strategy

LAST_CKPT = "last.ckpt"
#: The checkpoint ``last.ckpt`` replaced, kept so a damaged ``last.ckpt`` still resumes.
PREVIOUS_CKPT = "previous.ckpt"


# ----------------------------------------------------------------------------- checkpoints


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints written to a temp name, fsynced and renamed: a kill, a full disk or a
    read-only directory never leaves a partial ``last.ckpt`` or ``best.ckpt``. The
    ``last.ckpt`` being replaced stays as ``previous.ckpt`` (a hard link: no copy)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any = None) -> None:
        path = Path(path)
        # Serialized in memory first, so a failing write is an OSError of ours to explain,
        # not one torch's zip writer wraps in a RuntimeError.
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        with atomic_open(path) as fh:
            fh.write(buf.getbuffer())
            if path.name == LAST_CKPT and path.is_file():
                previous = path.with_name(PREVIOUS_CKPT)
                remove_inside(previous, path.parent)
                os.link(path, previous)


def readable_checkpoint(path: Path) -> str:
    """Why ``path`` cannot be a checkpoint to resume from ("" when it can).

    torch writes a zip archive; its central directory and per-entry CRCs catch truncation
    and damaged bytes without unpickling anything."""
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
        return f"damaged entry {bad}" if bad else ""
    except (zipfile.BadZipFile, OSError, EOFError) as err:
        return str(err) or type(err).__name__


def last_checkpoint(stage_dir: Path, say: Callable[[str], None] = lambda line: None) -> Path | None:
    """The checkpoint a cut-off stage resumes from: ``last.ckpt``, else the one before it
    when ``last.ckpt`` is unreadable (``say`` gets one line about it), else None."""
    ckpt_dir = stage_dir / "checkpoints"
    last, previous = ckpt_dir / LAST_CKPT, ckpt_dir / PREVIOUS_CKPT
    if not last.is_file():
        return None
    problem = readable_checkpoint(last)
    if not problem:
        _refuse_pickled(last)
        return last
    if previous.is_file() and not readable_checkpoint(previous):
        say(f"{last} is unreadable ({problem}); resuming from the checkpoint before it, {previous}")
        return previous
    say(f"{last} is unreadable ({problem}) and no earlier checkpoint is; the stage starts afresh")
    return None


def _refuse_pickled(path: Path) -> None:
    """A sound archive whose pickle names more than tensors and plain values (not one
    occtrain wrote) stops the run: never unpickled, and never overwritten by a fresh start."""
    import pickle

    try:
        torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError as err:
        found = re.search(r"Unsupported global: (?:GLOBAL )?(\S+)", str(err))
        what = f"object {found.group(1)}" if found else "objects"
        raise OcctrainError(
            f"{path}: holds pickled {what}, which a weights-only load refuses (occtrain never unpickles); "
            "move it away to start the stage afresh"
        ) from None


def checkpoint_step(path: Path) -> int:
    """The optimizer step a checkpoint was saved at (weights-only load: nothing unpickled)."""
    return int(torch.load(path, map_location="cpu", weights_only=True, mmap=True).get("global_step", 0))


# ----------------------------------------------------------------------------- callbacks


class _TrackConsumed(Callback):
    """Points the resumable loader at the trainer's step count."""

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        loader = trainer.train_dataloader
        if isinstance(loader, ResumableLoader):
            acc = trainer.accumulate_grad_batches
            loader.consumed = lambda: trainer.global_step * acc


class _StepSeed(Callback):
    """Seeds torch before every training batch from the optimizer step, the micro-batch
    within it and the rank: dropout, sampled loss terms and codebook restarts then draw the
    same numbers in a resumed run as in an uninterrupted one, wherever the checkpoint fell
    and whatever validation or a loader drew in between."""

    def __init__(self, base_seed: int):
        self.base_seed = base_seed

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        acc = trainer.accumulate_grad_batches
        micro = trainer.global_step * acc + batch_idx % acc
        torch.manual_seed((self.base_seed * 1_000_003 + micro) * 1024 + trainer.global_rank)


class _Heartbeat(Callback):
    """Calls ``record(seconds since the attempt began)`` at most every ``every_s`` seconds
    and at each checkpoint, so a run killed with -9 keeps the wall time it spent."""

    def __init__(self, record: Callable[[float], None], every_s: float = 30.0):
        self.record, self.every_s = record, every_s
        self.started = self.last = time.time()

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        now = time.time()
        if now - self.last >= self.every_s and trainer.is_global_zero:
            self.last = now
            self.record(now - self.started)

    def on_save_checkpoint(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.is_global_zero:
            self.last = time.time()
            self.record(self.last - self.started)


class AttemptRecord(Callback):
    """Reports what this attempt does, as the trainer sees it, to ``record`` (rank zero):
    ``start_step`` and ``world_size`` when training begins (after a checkpoint is restored,
    so a resume reports the step it continues from; at the end of fit when the restored
    checkpoint had already finished training, which Lightning then skips),
    ``train_samples_per_rank`` when training ends and ``val_samples_per_rank`` after each
    validation (padding left out)."""

    def __init__(self, record: Callable[[dict[str, Any]], None]):
        self.record = record
        self.train_samples = 0
        self.val_samples = 0
        self.started = False

    def _report(self, trainer: L.Trainer, facts: dict[str, Any]) -> None:
        if trainer.is_global_zero:
            self.record(facts)

    def _per_rank(self, trainer: L.Trainer, count: int) -> list[int]:
        # Every rank calls it, with the tensor on its own device: NCCL gathers no CPU tensors.
        counts = trainer.strategy.all_gather(torch.tensor([count], device=trainer.strategy.root_device))
        return [int(c) for c in counts.flatten()]

    def _report_start(self, trainer: L.Trainer) -> None:
        self.started = True
        self._report(trainer, {"start_step": trainer.global_step, "world_size": trainer.world_size})

    def on_train_start(self, trainer: L.Trainer, *args: Any) -> None:
        self.train_samples = 0
        self._report_start(trainer)

    def on_fit_end(self, trainer: L.Trainer, *args: Any) -> None:
        # A kill -9 just after the last checkpoint leaves nothing to train on resume.
        if not self.started:
            self._report_start(trainer)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, *args: Any) -> None:
        self.train_samples += _batch_samples(batch)

    def on_train_end(self, trainer: L.Trainer, *args: Any) -> None:
        self._report(trainer, {"train_samples_per_rank": self._per_rank(trainer, self.train_samples)})

    def on_validation_epoch_start(self, *args: Any) -> None:
        self.val_samples = 0

    def on_validation_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, *args: Any
    ) -> None:
        self.val_samples += _batch_samples(batch)

    def on_validation_epoch_end(self, trainer: L.Trainer, *args: Any) -> None:
        self._report(trainer, {"val_samples_per_rank": self._per_rank(trainer, self.val_samples)})


def _batch_samples(batch: Any) -> int:
    """Real samples in a collated batch: its tokens, none for a batch of padding alone."""
    if not isinstance(batch, dict) or batch.get(PAD_KEY):
        return 0
    return len(batch.get("token", ()))


class StepTimer(Callback):
    """Mean wall time of a training step, loading its batch included: the time from one
    batch's start to the next one's, the first ``warmup`` steps of an attempt and the
    intervals that hold a validation or a checkpoint left out."""

    def __init__(self, warmup: int = 2):
        self.warmup = warmup
        self.times: list[float] = []
        self._last: float | None = None

    def on_train_batch_start(self, *args: Any) -> None:
        now = time.perf_counter()
        if self._last is not None:
            self.times.append(now - self._last)
        self._last = now

    def _skip(self, *args: Any) -> None:
        self._last = None

    on_validation_start = on_save_checkpoint = on_train_end = _skip

    @property
    def mean_s(self) -> float | None:
        kept = self.times[self.warmup :] or self.times
        return sum(kept) / len(kept) if kept else None


class StepProgress(ProgressBar):
    """The stage's optimizer steps (``step 8/20``), loss, rate and time left: a bar on a
    terminal, a plain line every few seconds in a log (see :mod:`occtrain.progress`).

    Lightning's own bars count the batches of an epoch, which a stage budgeted in steps
    does not have: they showed ``Epoch 0/-2``, the logger's version and ``8/5`` after a
    resume. Validation gets a line of its own, as batches of the validation loop.
    """

    def __init__(self, name: str):
        super().__init__()
        self.name = name
        self.enabled = True
        self._bar: Progress | None = None
        self._tasks: dict[str, Any] = {}
        self._train: Ticker | None = None
        self._val: Ticker | None = None

    def disable(self) -> None:
        self.enabled = False

    def enable(self) -> None:
        self.enabled = True

    def print(self, *args: Any, **kwargs: Any) -> None:
        console.print(*args, **kwargs)  # the bar's own console: printed above the bar, not through it

    @staticmethod
    def _metrics(trainer: L.Trainer) -> str:
        # What the stage logs with prog_bar=True (its training loss), without the "train/" prefix.
        items = trainer.progress_bar_metrics.items()
        return ", ".join(f"{k.removeprefix('train/')} {v:.4g}" for k, v in items if isinstance(v, (int, float)))

    def _show(self, key: str, ticker: Ticker) -> None:
        """Start ``ticker``'s row of the bar (terminal) or keep it quiet until its interval (log)."""
        if plain():
            return
        ticker.every_s = math.inf  # the bar shows it; no plain lines through the bar
        if self._bar is None:
            self._bar = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                TextColumn("{task.fields[text]}"),
                console=console,
                transient=False,
            )
            self._bar.start()
        self._tasks[key] = self._bar.add_task(
            ticker.description, total=ticker.total, completed=ticker.done, text=ticker.text()
        )

    def _set(self, key: str, ticker: Ticker, done: int, extra: str = "", final: bool = False) -> None:
        ticker.update(done, extra)
        if self._bar is not None and key in self._tasks:
            self._bar.update(self._tasks[key], completed=done, text=ticker.text(extra, final))

    def _stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
        self._bar, self._tasks = None, {}

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.enabled:
            return
        total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
        # A resume starts at its checkpoint's step; the rate counts this process's steps only.
        self._train = Ticker(self.name, total, start=trainer.global_step, unit="step")
        self._show("train", self._train)

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.enabled and self._train is not None:
            self._set("train", self._train, trainer.global_step, self._metrics(trainer))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.enabled and self._train is not None:
            self._set("train", self._train, trainer.global_step, self._metrics(trainer), final=True)
            if plain():
                self._train.say(self._metrics(trainer), final=True)
        self._stop()

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.enabled or trainer.sanity_checking:
            return
        batches = trainer.num_val_batches
        total = sum(batches) if isinstance(batches, list) else batches
        self._val = Ticker(
            f"{self.name} validation", int(total) if math.isfinite(total) and total > 0 else None, unit="batch"
        )
        self._show("val", self._val)

    def on_validation_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.enabled and self._val is not None:
            self._set("val", self._val, self._val.done + 1)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._val is None:
            return
        if plain():
            self._val.say(final=True)
        if self._bar is not None and "val" in self._tasks:
            self._bar.remove_task(self._tasks.pop("val"))
        if "train" not in self._tasks:  # trainer.validate(): no training row to keep the bar for
            self._stop()
        self._val = None

    def on_exception(self, *args: Any, **kwargs: Any) -> None:
        self._stop()  # leave the terminal usable for the traceback

    def teardown(self, *args: Any, **kwargs: Any) -> None:
        self._stop()


def current_rss_mb() -> float | None:
    """This process's resident memory now (MB), from /proc; None where there is no /proc."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class PeakMemory(Callback):
    """The largest resident memory of this process seen after a training step (MB), and on
    a CUDA device the most it allocated during the stage's training: what a stage needs of
    a machine, read per stage (the process-wide high-water marks would carry an earlier
    stage's peak into a later one)."""

    def __init__(self) -> None:
        self.peak_mb: float | None = None
        self.peak_gpu_mb: float | None = None

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        if pl_module.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(pl_module.device)

    def on_train_batch_end(self, trainer: Any, pl_module: Any, *args: Any) -> None:
        rss = current_rss_mb()
        if rss is not None:
            self.peak_mb = max(self.peak_mb or 0.0, rss)
        if pl_module.device.type == "cuda":
            self.peak_gpu_mb = torch.cuda.max_memory_allocated(pl_module.device) / 2**20


# ----------------------------------------------------------------------------- validation


class ValidationMeans(torch.nn.Module):
    """Validation means weighted by sample count, each a torchmetrics ``MeanMetric``.

    Under DDP the sums and counts of every rank are gathered before dividing, so a split
    spread unevenly over ranks averages exactly as in one process (Lightning's own
    ``sync_dist`` reduction of a logged value does not promise that).
    """

    def __init__(self, *names: str):
        super().__init__()
        self.names = names
        self.means = torch.nn.ModuleList(MeanMetric() for _ in names)

    def update(self, name: str, value: torch.Tensor | float, weight: int) -> None:
        self.means[self.names.index(name)].update(torch.as_tensor(value, dtype=torch.float32).detach(), weight)

    def pop(self) -> dict[str, float]:
        """The means of this validation (all ranks must call it), then reset."""
        return compute_metrics("", dict(zip(self.names, self.means)), reset=True)


# ----------------------------------------------------------------------------- trainer


def quiet_lightning() -> None:
    """Keep a run's log readable: Lightning's device banners, tips and a deprecation notice
    of its own internals say nothing a user can act on."""
    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
    logging.getLogger("lightning.pytorch.accelerators.cuda").setLevel(logging.WARNING)
    # "Received SIGTERM": the runner says what a stop means and how to resume, in one line.
    logging.getLogger("lightning.pytorch.trainer.connectors.signal_connector").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=r".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=r".*is_gradient_checkpointing.*")
    # Every epoch-level value a stage logs is already gathered over ranks (torchmetrics
    # metrics, ValidationMeans), so Lightning's advice to sync it again does not apply.
    warnings.filterwarnings("ignore", message=r".*sync_dist=True.*when logging on epoch level.*")
    # Frozen sub-models (the scene tokenizer, a teacher) are in eval mode on purpose.
    warnings.filterwarnings("ignore", message=r".*module\(s\) in eval mode.*")


def _callbacks(
    cfg: TrainerConfig,
    name: str,
    ckpt_dir: Path,
    monitor: str | None,
    mode: str,
    record_time: Callable[[float], None] | None,
    record_attempt: Callable[[dict[str, Any]], None] | None,
) -> list[Callback]:
    """Checkpoints (last every N steps, best by ``monitor``), the resumable data position,
    per-step seeds, the learning rate, the progress bar, step times and the manifest's records."""
    callbacks: list[Callback] = [
        ModelCheckpoint(
            dirpath=ckpt_dir,
            filename="step{step}",
            every_n_train_steps=cfg.ckpt_every_n_steps,
            save_last=True,
            save_top_k=0,
            auto_insert_metric_name=False,
            enable_version_counter=False,
        ),
        _TrackConsumed(),
        _StepSeed(cfg.seed),
        LearningRateMonitor(logging_interval="step"),
        StepProgress(name),
        StepTimer(),
        PeakMemory(),
    ]
    if record_time is not None:
        callbacks.append(_Heartbeat(record_time))
    if record_attempt is not None:
        callbacks.append(AttemptRecord(record_attempt))
    if monitor:
        callbacks.append(
            ModelCheckpoint(
                dirpath=ckpt_dir,
                filename="best",
                monitor=monitor,
                mode=mode,
                save_top_k=1,
                auto_insert_metric_name=False,
                enable_version_counter=False,
            )
        )
    return callbacks


def _usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def check_trainer_setup(cfg: TrainerConfig, key: str) -> None:
    """Refuse, in one line naming ``key`` and before anything is written, a trainer this
    machine cannot run: GPUs where torch sees none, more devices than there are, a strategy
    or precision the accelerator does not take (Lightning's own checks, run by building
    the Trainer without fitting)."""
    accelerator, devices = str(cfg.accelerator), int(cfg.devices)
    if accelerator in ("gpu", "cuda"):
        found = torch.cuda.device_count()
        if found == 0:
            raise ConfigError(
                f"{key}.accelerator is {accelerator}, but torch {torch.__version__} sees no GPU here; "
                "train on the CPU with configs/trainer/cpu.yaml (trainer.accelerator=cpu trainer.strategy=auto "
                "trainer.devices=1)"
            )
        if devices > found:
            raise ConfigError(
                f"{key}.devices is {devices}, but this machine has {found} GPU{'s' * (found != 1)}; use at most "
                f"{found}, or -1 for all"
            )
    elif accelerator == "cpu" and devices > _usable_cores():
        raise ConfigError(
            f"{key}.devices is {devices} CPU processes, but this machine has {_usable_cores()} cores; "
            f"use at most {_usable_cores()} (or several nodes with torchrun)"
        )
    on_cpu = accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())
    if on_cpu and str(cfg.precision) in ("16-mixed", "16"):
        # Lightning would train in bf16 instead, with a warning, while the recipe, the
        # manifest and the config hash all keep saying 16-mixed.
        raise ConfigError(
            f"{key}.precision is {cfg.precision}, but float16 mixed precision needs a GPU; "
            "on the CPU use bf16-mixed (what Lightning would switch to) or 32-true"
        )
    quiet_lightning()
    try:
        L.Trainer(
            accelerator=accelerator,
            devices=devices,
            num_nodes=cfg.num_nodes,
            strategy=trainer_strategy(cfg),
            precision=cfg.precision,
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
        )
    except (MisconfigurationException, ValueError, RuntimeError, ImportError, TypeError) as e:
        raise ConfigError(
            f"{key}: accelerator={accelerator} devices={devices} strategy={cfg.strategy} precision={cfg.precision} "
            "cannot run here "
            f"({str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__})"
        ) from None


def build_trainer(
    cfg: TrainerConfig,
    stage_dir: Path,
    monitor: str | None,
    mode: str = "max",
    resume_step: int | None = None,
    record_time: Callable[[float], None] | None = None,
    record_attempt: Callable[[dict[str, Any]], None] | None = None,
) -> L.Trainer:
    """A Trainer writing ``checkpoints/`` (last.ckpt every N steps, best by ``monitor``) and ``logs/``.

    ``resume_step``: the step of the checkpoint the stage resumes from (its CSV log keeps
    the rows before it); ``record_time`` gets the attempt's elapsed seconds now and then;
    ``record_attempt`` what the attempt did (see :class:`AttemptRecord`).
    """
    quiet_lightning()
    callbacks = _callbacks(cfg, stage_dir.name, stage_dir / "checkpoints", monitor, mode, record_time, record_attempt)
    loggers = build_loggers(list(cfg.loggers), stage_dir, resume_step)
    return L.Trainer(
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        num_nodes=cfg.num_nodes,
        strategy=trainer_strategy(cfg),
        precision=cfg.precision,
        max_steps=cfg.max_steps,
        max_epochs=cfg.max_epochs,
        val_check_interval=cfg.val_check_interval,
        check_val_every_n_epoch=None,
        limit_val_batches=1.0 if cfg.limit_val_batches < 0 else cfg.limit_val_batches,
        log_every_n_steps=cfg.log_every_n_steps,
        gradient_clip_val=cfg.gradient_clip_val or None,
        accumulate_grad_batches=cfg.accumulate_grad_batches,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=loggers,
        default_root_dir=stage_dir,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        plugins=[AtomicCheckpointIO()],
    )


# ----------------------------------------------------------------------------- optimizer


def configure_adamw(params: Any, cfg: OptimConfig, max_steps: int) -> dict:
    """AdamW with linear warm-up and cosine decay to ``min_lr_ratio`` (or constant), per step."""
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=tuple(cfg.betas), eps=cfg.eps)
    if cfg.schedule not in ("cosine", "constant"):
        raise OcctrainError(f"optim.schedule '{cfg.schedule}' is not one of cosine, constant")

    def factor(step: int) -> float:
        if cfg.warmup_steps and step < cfg.warmup_steps:
            return (step + 1) / cfg.warmup_steps
        if cfg.schedule == "constant" or max_steps <= cfg.warmup_steps:
            return 1.0
        progress = min(1.0, (step - cfg.warmup_steps) / max(1, max_steps - cfg.warmup_steps))
        return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def freeze_prefixes(module: torch.nn.Module, prefixes: list[str]) -> int:
    """Freeze parameters whose names start with any prefix; returns how many tensors were frozen."""
    n = 0
    for name, p in module.named_parameters():
        if any(name.startswith(pre) for pre in prefixes):
            p.requires_grad_(False)
            n += 1
    if prefixes and n == 0:
        raise OcctrainError(f"freeze: no parameter name starts with {', '.join(prefixes)}")
    return n


# ----------------------------------------------------------------------------- world-model stages


def family_schema(base: type, family: str | None, with_world: bool) -> type:
    """``base`` with ``tasks`` typed by ``family``'s task settings and, ``with_world``, its
    world settings as ``model.<family>``: only what the stage uses is validated and hashed."""
    if family is None:
        return base
    world = get_world(family)
    fields: list[tuple[str, Any, Any]] = [("tasks", world.task_config, field(default_factory=world.task_config))]
    if with_world and world.world_config is not None:
        fields.append((family, world.world_config, field(default_factory=world.world_config)))
    return make_dataclass(f"{base.__name__}_{family}", fields, bases=(base,))


def evaluate_engine(engine: Any, request: EvalRequest) -> EvalResult:
    """Score ``engine``'s generated answers on ``request``'s split (see ``evaluate_export``)."""
    engine.prepare_inputs(request.data_root, request.cache_dir, request.shared_cache_dir)
    specs = engine.task_specs
    unknown = [t for t in request.tasks or [] if t not in specs]
    if unknown:
        raise ConfigError(
            f"--tasks: '{unknown[0]}' is not a task of the '{engine.family}' world model; its tasks are "
            f"{', '.join(specs)}"
        )
    tasks = request.tasks or scorable(specs, engine.tasks.weights)
    if not tasks:
        raise ConfigError(
            f"{request.export}: the stage trained no task with a generated answer to score; name some with --tasks"
        )
    lacking = lacking_tasks(request.data_root, tasks)
    if lacking and (request.tasks or len(lacking) == len(tasks)):
        task, why = next(iter(lacking.items()))
        raise ConfigError(
            f"task {task} {why} ({request.data_root}); score it on a dataset that has it, or leave it out of --tasks"
        )
    if lacking:
        console.print(
            f"[yellow]note[/]: {request.data_root} lacks what {', '.join(lacking)} need; scoring "
            f"{', '.join(t for t in tasks if t not in lacking)}"
        )
        tasks = [t for t in tasks if t not in lacking]
    evaluator = Evaluator(
        tasks, specs, record=request.record, priors=Priors.of(request.data_root), hooks=engine.spec.eval_hooks
    )
    torch.manual_seed(0)
    total = evaluator.total(engine, request.data_root, request.split, request.samples)
    if total == 0:
        raise ConfigError(
            f"{request.data_root}: its {request.split} split holds no item for {', '.join(evaluator.tasks)} "
            f"(a clip needs {engine.tasks.context_frames} frames of context and its future); score a dataset with "
            "longer scenes"
        )
    with progress_bar(
        total, f"evaluating {request.export.parent.name} on {request.split} ({', '.join(evaluator.tasks)})"
    ) as advance:
        evaluator.run(
            engine, request.data_root, request.split, request.batch_size, samples=request.samples, advance=advance
        )
    metrics = {k.removeprefix(f"{request.split}/"): v for k, v in evaluator.compute(request.split).items()}
    return EvalResult(metrics, evaluator.predictions if request.record else {})

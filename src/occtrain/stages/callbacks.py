"""The Lightning callbacks every stage's Trainer carries: the resumable data position, per-step
seeds, the heartbeat, the attempt record, step timing and peak memory."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

from occtrain.data.datamodule import ResumableLoader
from occtrain.data.shards import PAD_KEY


class TrackConsumed(Callback):
    """Points the resumable loader at the trainer's step count."""

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        loader = trainer.train_dataloader
        if isinstance(loader, ResumableLoader):
            acc = trainer.accumulate_grad_batches
            loader.consumed = lambda: trainer.global_step * acc


class StepSeed(Callback):
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


class Heartbeat(Callback):
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

    # Time spent validating or checkpointing is not a step's: the next step starts the clock.
    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = None

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        self._last = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = None

    @property
    def mean_s(self) -> float | None:
        kept = self.times[self.warmup :] or self.times
        return sum(kept) / len(kept) if kept else None


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

"""The Lightning callbacks every stage's Trainer carries: the resumable data position, per-step
seeds, the heartbeat, the attempt record, step timing and throughput, and peak memory."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback
from torch.utils.flop_counter import FlopCounterMode

from occtrain.data.datamodule import ResumableLoader
from occtrain.data.shards.positions import PAD_KEY
from occtrain.models.compiling import compile_all, use_cache_dir
from occtrain.progress import console
from occtrain.stages.stage import Stage, StepWork


@runtime_checkable
class MeteredStep(Protocol):
    """What ``StepMeter`` reads of the module it times; ``Stage`` declares both."""

    #: Whether the meter may count its first computing step's FLOPs (``FlopCounterMode``).
    count_flops: bool
    #: What its last step processed, or None: the batch's samples alone.
    step_work: StepWork | None


@runtime_checkable
class CompilesBlocks(Protocol):
    """What ``CompileBlocks`` reads of the module it compiles; ``Stage`` declares it."""

    def compiled_blocks(self) -> list[torch.nn.Module]: ...


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
        #: The last validation's samples on each rank (a final metrics file's provenance).
        self.val_samples_per_rank: list[int] | None = None
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
        self.val_samples_per_rank = self._per_rank(trainer, self.val_samples)
        self._report(trainer, {"val_samples_per_rank": self.val_samples_per_rank})


def _batch_samples(batch: Any) -> int:
    """Real samples in a collated batch: its tokens, none for a batch of padding alone."""
    if not isinstance(batch, dict) or batch.get(PAD_KEY):
        return 0
    return len(batch.get("token", ()))


#: Endings of the metrics that measure the machine rather than the model (step times,
#: rates, memory): the same training gives other values on another machine or load. The
#: padding share is the model's, but of the steps one attempt ran (a resumed stage's
#: differs from an uninterrupted one's), so it is left out of their comparisons too.
MEASURED = ("_per_s", "_step_s", "_rss_mb", "_gpu_mb", "_mfu", "_padding_share", "_phase_s")
#: The per-step rates in the training log (the dashboard's throughput charts).
LOGGED_RATES = ("tokens_per_s", "samples_per_s", "mfu", "padding_share")


class StepMeter(Callback):
    """A stage's training steps measured. ``train_step_s``: a step's wall time, loading its
    batch included (from one batch's start to the next one's; the intervals that hold a
    validation or a checkpoint left out). The rates: what each step processed (the module's
    ``step_work``) over its own time, from its batch's start to its end (forward, backward,
    optimizer; loading, validation and checkpoints outside it), as samples, tokens and model
    FLOPs per second of this device, and model FLOPs utilization, those FLOPs per second over
    the device's peak (``device_peak_flops``). The first ``warmup`` steps of an attempt are
    left out of both. Each step's rates are logged as ``train/tokens_per_s``,
    ``train/samples_per_s`` and ``train/mfu``, with ``train/padding_share``: of the token
    positions the LLM computed over, the share that were padding (``core.packing``).

    A stage kind that ``count_flops`` has its first step that computes anything (a warm-up
    step, never in the summary) run under torch's ``FlopCounterMode``: that step's forward,
    backward and optimizer FLOPs over its samples give every later step's FLOPs. The count
    rides in the checkpoint, so a resumed attempt reuses it rather than counting a step the
    uncut run did not (the counter's module hooks move gradients in the last bits: the
    resumed run would not end bit-exact with an uncut one). Not under ``trainer.compile``:
    the counter sees the eager operators, not a compiled graph's.

    Not Lightning's ``ThroughputMonitor``: it times from batch end to batch end, checkpoint
    writes included, over a sliding window, where these are a stage's whole training; its
    peak-FLOPs table (``get_available_flops``) gives a CUDA device's peak."""

    def __init__(self, warmup: int = 2, count_flops: bool = True):
        self.warmup = warmup
        #: Off under ``trainer.compile`` (see above).
        self.count_flops = count_flops
        self.times: list[float] = []  # batch start to the next batch start
        self.steps: list[tuple[float, StepWork]] = []  # batch start to its end, and the work done
        self.peak_flops: float | None = None
        self._last: float | None = None
        self._began: float | None = None
        self._counter: FlopCounterMode | None = None
        self._flops_per_sample: float | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if isinstance(pl_module, Stage):
            pl_module.step_meter = self

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.peak_flops = device_peak_flops(pl_module.device, str(trainer.precision))

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        counts = self.count_flops and isinstance(pl_module, MeteredStep) and pl_module.count_flops
        if counts and self._flops_per_sample is None and self._counter is None:
            self._counter = FlopCounterMode(display=False)
            self._counter.__enter__()
        now = time.perf_counter()
        if self._last is not None:
            self.times.append(now - self._last)
        self._last = self._began = now

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, *args: Any
    ) -> None:
        if self._began is None:
            return
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)  # the step's kernels are queued, not done
        seconds = time.perf_counter() - self._began
        work = pl_module.step_work if isinstance(pl_module, MeteredStep) else None
        work = work if work is not None else StepWork(samples=_batch_samples(batch))
        if self._counter is not None:  # the counted step: slowed by counting, so given no FLOPs
            self._stop_counting(work.samples)
        elif work.flops is None and self._flops_per_sample is not None:
            work = dataclasses.replace(work, flops=self._flops_per_sample * work.samples)
        self.steps.append((seconds, work))
        for name, value in self._rates([(seconds, work)]).items():
            if name in LOGGED_RATES:
                pl_module.log(f"train/{name}", value, batch_size=max(work.samples, 1))

    def restart_step(self) -> None:
        """What ran since this batch started is not the step's (a dagger round's driving and
        its world-model outputs, in the module's ``on_train_batch_start``, which Lightning
        calls after this callback's): the step's clock, and the interval to the next batch's
        start, start now, and a step being counted counts afresh."""
        self._last = self._began = time.perf_counter()
        if self._counter is not None:
            self._counter.__exit__(None, None, None)
            self._counter = FlopCounterMode(display=False)
            self._counter.__enter__()

    # Time spent validating or checkpointing is not a step's: the next step starts the clock.
    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = None

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        self._last = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = None
        if self._counter is not None:  # a step that never ended (an exception, a stop)
            self._stop_counting(0)

    def state_dict(self) -> dict[str, Any]:
        return {"flops_per_sample": self._flops_per_sample}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        value = state_dict.get("flops_per_sample")
        self._flops_per_sample = float(value) if value is not None else None

    def _stop_counting(self, samples: int) -> None:
        """Close the counter; a step that computed nothing (no sample, or none the model
        read: a planner's batch without a meta action) is not a step's cost, so the next
        one is counted instead."""
        assert self._counter is not None
        self._counter.__exit__(None, None, None)
        total = self._counter.get_total_flops()
        if samples > 0 and total > 0:
            self._flops_per_sample = total / samples
        self._counter = None

    def _kept(self, measured: list) -> list:
        return measured[self.warmup :] if len(measured) > self.warmup else measured

    def _rates(self, steps: list[tuple[float, StepWork]]) -> dict[str, float]:
        elapsed = sum(seconds for seconds, _ in steps)
        if not elapsed:
            return {}
        work = [w for _, w in steps]
        out = {"samples_per_s": sum(w.samples for w in work) / elapsed}
        if all(w.tokens is not None for w in work):
            out["tokens_per_s"] = sum(w.tokens or 0 for w in work) / elapsed
        if all(w.tokens is not None and w.positions for w in work):
            out["padding_share"] = 1.0 - sum(w.tokens or 0 for w in work) / sum(w.positions or 0 for w in work)
        if all(w.flops is not None for w in work):
            flops = sum(w.flops or 0.0 for w in work) / elapsed
            out["model_flops_per_s"] = flops
            if self.peak_flops:
                out["mfu"] = flops / self.peak_flops
        return out

    @property
    def mean_s(self) -> float | None:
        times = self._kept(self.times)
        return sum(times) / len(times) if times else None

    def summary(self) -> dict[str, float]:
        """The stage's mean step time and rates over its kept steps (``train_`` prefixed)."""
        out = {f"train_{k}": v for k, v in self._rates(self._kept(self.steps)).items()}
        if self.mean_s is not None:
            out["train_step_s"] = self.mean_s
        if self.peak_flops and self.steps:
            out["train_device_peak_flops_per_s"] = self.peak_flops
        return out


_PRECISION_DTYPES = {"bf16": torch.bfloat16, "16": torch.float16}


@functools.cache
def cpu_matmul_flops(threads: int, size: int = 1024) -> float:
    """What this CPU does on a large fp32 matmul at ``threads`` threads (FLOP/s, best of
    five): the peak MFU is measured against on a CPU, where there is no data-sheet figure
    to look up that holds for a container's share of a machine."""
    # Its own generator: drawing from the global one would leave a resumed process's random
    # state unlike an uninterrupted one's (this runs once per process, at training start).
    generator = torch.Generator().manual_seed(0)
    a, b = torch.randn(size, size, generator=generator), torch.randn(size, size, generator=generator)
    a @ b  # warm-up: allocation, the BLAS's thread pool
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best


def device_peak_flops(device: torch.device, precision: str) -> float | None:
    """The peak FLOP/s MFU divides by: Lightning's table of CUDA devices at the training
    precision's matmul dtype (bf16 / fp16 mixed or true, else fp32 or TF32), or on a CPU
    a measured fp32 matmul (:func:`cpu_matmul_flops`); None for a device neither covers."""
    if device.type == "cuda":
        from lightning.fabric.utilities.throughput import get_available_flops

        dtype = next((d for prefix, d in _PRECISION_DTYPES.items() if precision.startswith(prefix)), torch.float32)
        flops = get_available_flops(device, dtype)
        return float(flops) if flops else None
    if device.type == "cpu":
        return cpu_matmul_flops(torch.get_num_threads())
    return None


def current_rss_mb() -> float | None:
    """This process's resident memory now (MB), from /proc; None where there is no /proc."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class CompileBlocks(Callback):
    """``trainer.compile``: the stage's :meth:`~occtrain.stages.stage.Stage.compiled_blocks`
    compiled for training once the model is built (after ``configure_model``: sharded
    blocks compile as they will run); one log line says what, and where inductor caches it
    (``cache_dir``, e.g. ``RUN/cache/inductor``, unless the user set TORCHINDUCTOR_CACHE_DIR)."""

    def __init__(self, cache_dir: Path | None = None):
        self.cache_dir = cache_dir
        self._restore: Callable[[], None] = lambda: None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        cache = ""
        if self.cache_dir is not None:
            # Rank zero vets the cache before any rank writes into it.
            use = use_cache_dir(self.cache_dir, vet=trainer.is_global_zero)
            if trainer.world_size > 1:
                trainer.strategy.barrier("inductor cache")
            self._restore = use.restore
            cache = f"; inductor caches in {use.folder}"
            if use.emptied and trainer.is_global_zero:
                console.print(
                    f"[yellow]note[/]: {use.folder} was not made there (a run copied from elsewhere): inductor "
                    "unpickles its cache, so it was emptied and compiles afresh"
                )
        blocks = pl_module.compiled_blocks() if isinstance(pl_module, CompilesBlocks) else []
        compiled = compile_all(blocks)
        if trainer.is_global_zero:
            kinds = ", ".join(sorted({type(b).__name__ for b in blocks}))
            what = f"{compiled} block(s) ({kinds}) compiled" if blocks else "this stage kind has no block to compile"
            console.print(f"trainer.compile: {what} for training steps; evaluation stays eager{cache}")

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # Only training forwards compile: a later stage, or the caller's own torch.compile,
        # is not to write into this run.
        self._restore()
        self._restore = lambda: None


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

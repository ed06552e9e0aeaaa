"""The Trainer a stage runs under: its checks, callbacks, loggers, strategy and checkpointing."""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import lightning as L
import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint

from occtrain.config.groups import TrainerConfig
from occtrain.errors import ConfigError
from occtrain.stages.callbacks import (
    AttemptRecord,
    CompileBlocks,
    Heartbeat,
    PeakMemory,
    StepMeter,
    StepSeed,
    TrackConsumed,
)
from occtrain.stages.checkpoints import AtomicCheckpointIO
from occtrain.stages.loggers import build_loggers
from occtrain.stages.phases import PhaseProfiler
from occtrain.stages.sharding import trainer_strategy
from occtrain.stages.stage import shared_cache_dir
from occtrain.stages.step_progress import StepProgress

#: Where ``trainer.compile``'s inductor cache goes, in the run's shared caches (``RUN/cache/``).
INDUCTOR_CACHE = "inductor"


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


@dataclass(frozen=True)
class StageMeters:
    """What a stage's Trainer measures, held where the runner reads it: Lightning keeps its
    callbacks and profiler on attributes its ``Trainer`` does not declare."""

    steps: StepMeter
    memory: PeakMemory
    phases: PhaseProfiler
    #: None: no ``record_attempt`` was given.
    attempt: AttemptRecord | None


def _callbacks(
    cfg: TrainerConfig,
    name: str,
    ckpt_dir: Path,
    monitor: str | None,
    mode: str,
    meters: StageMeters,
    record_time: Callable[[float], None] | None,
) -> list[Callback]:
    """Checkpoints (last every N steps, best by ``monitor``), the resumable data position,
    per-step seeds, the learning rate, the progress bar, the ``meters`` and the heartbeat."""
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
        TrackConsumed(),
        StepSeed(cfg.seed),
        LearningRateMonitor(logging_interval="step"),
        StepProgress(name),
        meters.steps,
        meters.memory,
    ]
    if cfg.compile:
        callbacks.append(CompileBlocks(shared_cache_dir(ckpt_dir.parent) / INDUCTOR_CACHE))
    if record_time is not None:
        callbacks.append(Heartbeat(record_time))
    if meters.attempt is not None:
        callbacks.append(meters.attempt)
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


#: The precisions every stage kind trains at on the CPU (Lightning's legacy spellings
#: included), tried on the quickstart's five kinds: at 16-true the losses turn NaN, and at
#: bf16-true and 64-true a tokenizer's codebook update and a planner's head mix dtypes.
CPU_PRECISIONS = ("32-true", "32", "bf16-mixed", "bf16")


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
            precision=cast(Any, cfg.precision),  # Lightning checks it and names a bad value
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
    if on_cpu and str(cfg.precision) not in CPU_PRECISIONS:
        # Lightning takes it (checked above), and the first stage would fail on it raw, or train NaN.
        raise ConfigError(
            f"{key}.precision is {cfg.precision}, but on the CPU occtrain's stages train at 32-true or bf16-mixed "
            "only (at other precisions a tokenizer's or a planner's step fails, or the losses turn NaN); use one of "
            "those"
        )


def build_trainer(
    cfg: TrainerConfig,
    stage_dir: Path,
    monitor: str | None,
    mode: str = "max",
    resume_step: int | None = None,
    record_time: Callable[[float], None] | None = None,
    record_attempt: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[L.Trainer, StageMeters]:
    """A Trainer writing ``checkpoints/`` (last.ckpt every N steps, best by ``monitor``) and
    ``logs/``, and what it measures.

    ``resume_step``: the step of the checkpoint the stage resumes from (its CSV log keeps
    the rows before it); ``record_time`` gets the attempt's elapsed seconds now and then;
    ``record_attempt`` what the attempt did (see :class:`AttemptRecord`).
    """
    quiet_lightning()
    meters = StageMeters(
        steps=StepMeter(count_flops=not cfg.compile),
        memory=PeakMemory(),
        phases=PhaseProfiler(),
        attempt=AttemptRecord(record_attempt) if record_attempt is not None else None,
    )
    callbacks = _callbacks(cfg, stage_dir.name, stage_dir / "checkpoints", monitor, mode, meters, record_time)
    loggers = build_loggers(list(cfg.loggers), stage_dir, resume_step)
    trainer = L.Trainer(
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        num_nodes=cfg.num_nodes,
        strategy=trainer_strategy(cfg),
        precision=cast(Any, cfg.precision),  # checked by the dry build above
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
        profiler=meters.phases,
    )
    return trainer, meters

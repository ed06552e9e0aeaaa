"""One stage trained, validated and exported: what the runner calls for each stage it runs.

It builds the stage's module and data module, resumes from the last checkpoint, fits,
validates the final weights (unless fit just did), exports, and writes the stage's
``metrics.json`` with what it was measured on and the attempt's measurements (step rates,
where the time went, peak memory).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from occtrain.formats.metrics_file import Provenance, StageAttempt, write_metrics
from occtrain.progress import console
from occtrain.ranks import is_rank_zero
from occtrain.run.planning import PlannedStage
from occtrain.stages import Stage, StageContext, StageReport

if TYPE_CHECKING:  # imported where a stage is built (build_stage): parsing a recipe loads no torch
    import torch

    from occtrain.data.datamodule import ShardDataModule
    from occtrain.stages.trainer import StageMeters


def build_stage(stage: PlannedStage, stage_dir: Path, inputs: dict[str, Path]) -> tuple[Stage, ShardDataModule]:
    """The stage's module over the exports it consumes (``inputs``, by stage name) and the
    data module of its shards, seeded by its trainer's seed: what a run trains."""
    import lightning as L

    from occtrain.data.datamodule import ShardDataModule

    L.seed_everything(stage.trainer.seed, workers=True, verbose=False)
    ctx = StageContext(stage.spec, stage.model_cfg, stage.data, stage.trainer, stage_dir, inputs)
    module = stage.kind.build(ctx)
    entries = {split: module.entries(split) for split in ("train", "val")}
    return module, ShardDataModule(stage.data, stage.kind.data_kind, entries=entries, cameras=stage.reads_cameras)


def execute_stage(
    stage: PlannedStage,
    stage_dir: Path,
    inputs: dict[str, Path],
    record_time: Callable[[float], None] | None = None,
    record_attempt: Callable[[dict], None] | None = None,
    attempt: StageAttempt | None = None,
) -> dict:
    """Train ``stage`` in ``stage_dir`` over the exports it consumes (``inputs``), resuming
    from its last checkpoint, validate, export, and (rank zero) write its metrics file and
    samples: the manifest's result (metrics, artifacts, summary)."""
    from occtrain.stages.checkpoints import checkpoint_step, last_checkpoint
    from occtrain.stages.trainer import build_trainer

    module, datamodule = build_stage(stage, stage_dir, inputs)
    say = console.print if is_rank_zero() else (lambda line: None)
    ckpt = last_checkpoint(stage_dir, say=lambda line: say(f"[yellow]note[/]: {line}"))
    resume_step = checkpoint_step(ckpt) if ckpt is not None else None
    monitor, mode = module.monitored(stage.kind)
    trainer, meters = build_trainer(stage.trainer, stage_dir, monitor, mode, resume_step, record_time, record_attempt)
    if ckpt is not None:
        say(f"[yellow]resuming[/] {stage.spec.name} from {ckpt} (step {resume_step})")
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
    results: Sequence[Mapping[str, float | torch.Tensor]]
    if module.validated_at == trainer.global_step and trainer.global_step > 0:
        # fit validated the final weights already (generation makes validation costly).
        results = [{k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")}]
    else:
        results = trainer.validate(module, datamodule=datamodule, verbose=False)
    metrics = {k: float(v) for k, v in (results[0] if results else {}).items()}
    report = module.report()
    metrics.update(report.metrics)
    metrics.update(_measurements(meters))
    artifacts: dict[str, str] = {}
    exporting = time.perf_counter()
    module.prepare_export()  # every rank: a sharded stage gathers its weights for rank zero
    if trainer.is_global_zero:
        export_dir = module.export(stage_dir / "export")
        metrics["export_phase_s"] = time.perf_counter() - exporting
        provenance = _validation_provenance(stage, meters, report, module.split_items(), attempt or StageAttempt())
        write_metrics(stage_dir / "metrics.json", metrics, provenance)
        # Stages hand over raw scenes and texts; pictures are drawn here, not in the stages.
        if report.texts or report.scenes:
            from occtrain.dashboard import bev_comparison, write_samples

            write_samples(stage_dir, [(caption, bev_comparison(rows)) for caption, rows in report.scenes], report.texts)
        artifacts = {
            "export": str(export_dir),
            "metrics": str(stage_dir / "metrics.json"),
            "checkpoints": str(stage_dir / "checkpoints"),
            "logs": str(stage_dir / "logs"),
        }
    # Under DDP the next stage's processes read this export: none starts before rank zero wrote it.
    trainer.strategy.barrier("export")
    return {"metrics": metrics, "artifacts": artifacts, "summary": report.summary}


def _validation_provenance(
    stage: PlannedStage, meters: StageMeters, report: StageReport, split_items: int | None, attempt: StageAttempt
) -> Provenance:
    """What a stage's final validation measured: the val samples its batches held of what
    the split holds (``validation``: the shards' samples, or ``split_items`` where the stage
    validates fewer than the split holds), and the items its generation scored per task
    (the report's coverage and sample sets: a world model's validation generates on a
    subset, ``val_samples`` per task)."""
    from occtrain.data.datamodule import shards_dir
    from occtrain.data.identity import world_identity
    from occtrain.data.shards import shard_urls
    from occtrain.version import code_version

    record = meters.attempt
    validated = {}
    if record is not None and record.val_samples_per_rank is not None:
        total = (
            split_items
            if split_items is not None
            else shard_urls(shards_dir(stage.data), stage.kind.data_kind, "val")[1]
        )
        validated["validation"] = [sum(record.val_samples_per_rank), total]
    identity = world_identity(stage.data.root)
    return Provenance(
        by="validation at the end of training",
        split="val",
        coverage={**validated, **report.coverage},
        world=identity.key,
        world_version=identity.version,
        world_name=identity.name,
        code_version=code_version(),
        stage=attempt,
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        sample_sets=list(report.sample_sets),
    )


def _measurements(meters: StageMeters) -> dict[str, float]:
    """What this attempt measured (a measurement, not a result): its mean step time and
    throughput, where its time went and rank zero's peak memory."""
    from occtrain.stages.phases import phase_seconds

    out: dict[str, float] = meters.steps.summary()
    out.update(phase_seconds(meters.phases))
    memory = meters.memory
    if memory.peak_mb is not None:
        out["train_peak_rss_mb"] = memory.peak_mb
    if memory.peak_gpu_mb is not None:
        out["train_peak_gpu_mb"] = memory.peak_gpu_mb
    return out

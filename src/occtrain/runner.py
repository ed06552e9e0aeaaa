"""Run a recipe: stages in order, each consuming earlier exports; skip done, resume cut-off.

The run directory (see DESIGN.md) holds ``pipeline.yaml``, ``manifest.json`` and one
directory per stage with ``checkpoints/``, ``export/``, ``logs/`` and ``metrics.json``.
Under DDP, Lightning re-executes this command in each worker process; every process walks
the same plan from the same manifest snapshot, and only rank zero writes.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import shutil
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any


from occtrain.config import load_config, to_container, to_yaml
from occtrain.config.loading import validate_section
from occtrain.config.recipe import STAGE_DATA_KEYS, RecipeConfig, StageSpec
from occtrain.config.schema import DataConfig, TrainerConfig
from occtrain.errors import ConfigError, OcctrainError
from occtrain.io import atomic_write_json, atomic_write_text, is_rank_zero
from occtrain.manifest import Manifest
from occtrain.progress import console
from occtrain.stages import Stage, StageContext, StageKind, get_kind, kind_names

#: Trainer keys that change how often things are written, not what is learned.
OPERATIONAL_KEYS = ("log_every_n_steps", "ckpt_every_n_steps")


class StageFailed(OcctrainError):
    """A stage raised; the manifest records the one-line summary."""


@dataclass
class PlannedStage:
    spec: StageSpec
    kind: StageKind
    model_cfg: Any
    trainer: TrainerConfig
    config: dict  # resolved, hashed
    config_hash: str
    data: Any = None  # the recipe's DataConfig with the stage's loader keys applied


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def changed_keys(old: dict, new: dict) -> list[str]:
    """Dotted keys whose values differ between two resolved stage configs."""
    a, b = _flatten(old), _flatten(new)
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def plan_stages(recipe: RecipeConfig, source: str) -> list[PlannedStage]:
    """Validate every stage (kind, names, handoffs, model config) and hash its resolved config."""
    planned: list[PlannedStage] = []
    names: list[str] = []
    data = to_container(recipe.data)
    for i, spec in enumerate(recipe.stages):
        where = f"stages[{i}] ('{spec.name}') in {source}"
        kind = get_kind(spec.kind)
        if kind is None:
            raise ConfigError(f"unknown stage kind '{spec.kind}' for {where}; kinds are {', '.join(kind_names())}")
        if not (inspect.isclass(kind.module) and issubclass(kind.module, Stage)) or inspect.isabstract(kind.module):
            raise ConfigError(
                f"stage kind '{spec.kind}' of {where} is registered with {kind.module!r}, "
                "which is not a concrete occtrain.stages.Stage (it must subclass Stage and implement export)"
            )
        if spec.name in names:
            raise ConfigError(f"stage name '{spec.name}' is used twice in {source}")
        for dep in spec.consumes:
            if dep not in names:
                later = " (it runs later)" if any(s.name == dep for s in recipe.stages) else ""
                raise ConfigError(f"{where} consumes '{dep}', which is not an earlier stage{later}")
        kind.module.check_consumes(spec.kind, {dep: planned[names.index(dep)].spec.kind for dep in spec.consumes}, where)
        model_cfg = validate_section(kind.model_schema, spec.model or {}, f"stages[{i}].model", source)
        wrong = sorted(set(spec.data or {}) - set(STAGE_DATA_KEYS))
        if wrong:
            raise ConfigError(f"stages[{i}].data.{wrong[0]} in {source}: a stage sets only {', '.join(STAGE_DATA_KEYS)}; the dataset is the recipe's")
        stage_data = validate_section(DataConfig, {**data, **(spec.data or {})}, f"stages[{i}].data", source)
        trainer = validate_section(TrainerConfig, {**to_container(recipe.trainer), **(spec.trainer or {})}, f"stages[{i}].trainer", source)
        trainer_dict = {k: v for k, v in to_container(trainer).items() if k not in OPERATIONAL_KEYS}
        config = {
            "kind": spec.kind,
            "consumes": {dep: planned[names.index(dep)].config_hash for dep in spec.consumes},
            "freeze": list(spec.freeze),
            "model": to_container(model_cfg),
            "optim": to_container(spec.optim),
            "trainer": trainer_dict,
            "data": to_container(stage_data),
        }
        digest = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]
        planned.append(PlannedStage(spec, kind, model_cfg, trainer, config, digest, stage_data))
        names.append(spec.name)
    if not planned:
        raise ConfigError(f"{source} has no stages")
    return planned


def load_plugins(modules: list[str], source: str) -> None:
    """Import the recipe's plugin modules, which register their stage kinds."""
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError as err:
            raise ConfigError(f"plugin '{name}' in {source} cannot be imported ({err}); is it installed or on PYTHONPATH?") from None


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> tuple[RecipeConfig, list[PlannedStage]]:
    recipe = load_config(RecipeConfig, path, overrides)
    load_plugins(list(recipe.plugins), str(path))
    return recipe, plan_stages(recipe, str(path))


def _execute(stage: PlannedStage, recipe: RecipeConfig, stage_dir: Path, inputs: dict[str, Path]) -> dict:
    import lightning as L

    from occtrain.data.datamodule import ShardDataModule
    from occtrain.stages.common import build_trainer, last_checkpoint

    L.seed_everything(stage.trainer.seed, workers=True, verbose=False)
    ctx = StageContext(stage.spec, stage.model_cfg, stage.data, stage.trainer, stage_dir, inputs)
    module = stage.kind.build(ctx)
    entries = {split: module.entries(split) for split in ("train", "val")}
    datamodule = ShardDataModule(stage.data, stage.kind.data_kind, entries=entries)
    trainer = build_trainer(stage.trainer, stage_dir, stage.kind.monitor, stage.kind.mode)
    ckpt = last_checkpoint(stage_dir)
    if ckpt is not None and is_rank_zero():
        console.print(f"[yellow]resuming[/] {stage.spec.name} from {ckpt}")
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
    if module.validated_at == trainer.global_step and trainer.global_step > 0:
        # fit validated the final weights already (generation makes validation costly).
        results = [{k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")}]
    else:
        results = trainer.validate(module, datamodule=datamodule, verbose=False)
    metrics = {k: float(v) for k, v in (results[0] if results else {}).items()}
    report = module.report()
    metrics.update(report.metrics)
    artifacts: dict[str, str] = {}
    if trainer.is_global_zero:
        export_dir = module.export(stage_dir / "export")
        atomic_write_json(stage_dir / "metrics.json", metrics)
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
    return {"metrics": metrics, "artifacts": artifacts, "summary": report.summary}


def run(
    recipe_path: str | Path,
    overrides: list[str] | None = None,
    run_dir: str | Path | None = None,
    only: str | None = None,
    restart: str | None = None,
) -> Path:
    """Run (or continue) a recipe; returns the run directory. Raises OcctrainError on failure."""
    recipe, planned = load_recipe(recipe_path, overrides)
    names = [p.spec.name for p in planned]
    for flag, value in (("--only", only), ("--restart", restart)):
        if value is not None and value not in names:
            raise ConfigError(f"{flag} names stage '{value}', but {recipe_path} has stages {', '.join(names)}")
    run_dir = Path(run_dir) if run_dir else Path(recipe.runs_root) / recipe.name
    rank_zero = is_rank_zero()
    manifest = Manifest.load(run_dir, writable=rank_zero)
    manifest.name = recipe.name
    for p in planned:
        manifest.entry(p.spec.name, p.spec.kind)
    if rank_zero:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run_dir / "pipeline.yaml", to_yaml(recipe))
        if restart is not None:
            for p in planned[names.index(restart) :]:
                shutil.rmtree(run_dir / p.spec.name, ignore_errors=True)
                manifest.reset(p.spec.name)
        manifest.save()
        from occtrain.data.datamodule import ensure_data

        ensure_data(recipe.data)

    try:
        _run_stages(planned, manifest, run_dir, recipe, only, rank_zero)
    finally:
        if rank_zero:
            _write_dashboard(run_dir)
    return run_dir


def _write_dashboard(run_dir: Path) -> None:
    """The run's page, after success or failure alike; a page problem never fails a run."""
    from occtrain.dashboard import write_dashboard

    try:
        out = write_dashboard(run_dir)
        console.print(f"dashboard -> {out}")
    except Exception as err:  # noqa: BLE001 - the run's results are safe; the page is a view of them
        line = str(err).splitlines()[0] if str(err) else type(err).__name__
        console.print(f"[yellow]dashboard not written[/]: {type(err).__name__}: {line}")


def _run_stages(planned: list[PlannedStage], manifest: Manifest, run_dir: Path, recipe: RecipeConfig, only: str | None, rank_zero: bool) -> None:
    exports: dict[str, Path] = {}
    for p in planned:
        name, entry, stage_dir = p.spec.name, manifest.stages[p.spec.name], run_dir / p.spec.name
        if entry.status == "done":
            if entry.config_hash != p.config_hash:
                keys = changed_keys(entry.config, p.config)
                raise ConfigError(
                    f"stage '{name}' is done but its config changed ({', '.join(keys[:6]) or 'inputs'}); "
                    f"`--restart {name}` retrains it and the stages after it"
                )
            exports[name] = stage_dir / "export"
            if rank_zero:
                console.print(f"[green]done[/]    {name:14s} skipped (finished earlier; {entry.wall_time_s:.0f}s)")
            continue
        if only is not None and name != only:
            continue
        if entry.status in ("running", "failed") and entry.config_hash and entry.config_hash != p.config_hash and (stage_dir / "checkpoints").exists():
            keys = changed_keys(entry.config, p.config)
            raise ConfigError(
                f"stage '{name}' was cut off under a different config ({', '.join(keys[:6])}); "
                f"`--restart {name}` starts it afresh"
            )
        missing = [d for d in p.spec.consumes if d not in exports]
        if missing:
            raise ConfigError(f"stage '{name}' consumes the export of '{missing[0]}', which is not done; run it first (drop --only)")
        manifest.mark_running(name, p.config_hash, p.config)
        started = time.time()
        try:
            result = _execute(p, recipe, stage_dir, {d: exports[d] for d in p.spec.consumes})
        except KeyboardInterrupt:
            manifest.mark_failed(name, "interrupted", time.time() - started)
            raise
        except Exception as err:
            line = str(err).splitlines()[0] if str(err) else type(err).__name__
            summary = line if isinstance(err, OcctrainError) else f"{type(err).__name__}: {line}"
            manifest.mark_failed(name, summary, time.time() - started)
            if rank_zero and not isinstance(err, OcctrainError):
                atomic_write_text(stage_dir / "logs" / "traceback.txt", traceback.format_exc())
                summary += f" (traceback in {stage_dir / 'logs' / 'traceback.txt'})"
            raise StageFailed(f"stage '{name}' failed: {summary}") from err
        wall = time.time() - started
        manifest.mark_done(name, result["metrics"], result["artifacts"], wall)
        exports[name] = stage_dir / "export"
        if rank_zero:
            from occtrain.dashboard.page import headline

            # The model's main numbers first (as the dashboard's stage table); the rest,
            # baselines and teacher figures are in metrics.json.
            shown = ", ".join(f"{k}={result['metrics'][k]:.3g}" for k in headline(result["metrics"])[:5])
            console.print(f"[green]done[/]    {name:14s} {wall:6.0f}s  {result['summary']}  {shown}")

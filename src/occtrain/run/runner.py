"""Run a recipe: stages in order, each consuming earlier exports; skip done, resume cut-off.

The run directory (see DESIGN.md) holds ``pipeline.yaml``, ``manifest.json`` and one
directory per stage with ``checkpoints/``, ``export/``, ``logs/`` and ``metrics.json``.
Under DDP, Lightning re-executes this command in each worker process; every process walks
the same plan from the same manifest snapshot, and only rank zero writes.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import inspect
import json
import math
import re
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from occtrain.commands.compare import TABLE_FILE, check_table, show_table
from occtrain.config import load_config, to_container, to_yaml
from occtrain.config.groups import DataConfig, TrainerConfig, check_seed
from occtrain.config.loading import read_yaml, validate_section
from occtrain.config.recipe import STAGE_DATA_KEYS, RecipeConfig, StageSpec, check_name
from occtrain.core.registry import get_family
from occtrain.errors import ConfigError, OcctrainError, cause_line
from occtrain.formats.io import atomic_write_text, is_rank_zero, remove_inside
from occtrain.formats.metrics_file import Provenance, StageAttempt, write_metrics
from occtrain.progress import console
from occtrain.run.control import Interrupted, run_lock, stage_lock, stop_on_signals
from occtrain.run.manifest import PIPELINE_FILE, RESUMABLE, Manifest
from occtrain.stages import Stage, StageContext, StageKind, get_kind, kind_names

if TYPE_CHECKING:  # imported where a stage is built (build_stage), as before
    from occtrain.data.datamodule import ShardDataModule

#: Trainer keys that change how often things are written, or how the same steps are
#: computed (``compile``: the same losses to float tolerance), not what is learned: a done
#: stage is not refused for them, and a stopped one resumes under them.
OPERATIONAL_KEYS = ("log_every_n_steps", "ckpt_every_n_steps", "loggers", "compile")


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
    #: The family whose parts the stage trains (None: none, e.g. a vision stage).
    family: str | None = None
    #: Its batches carry the camera images (``Stage.camera_input``).
    reads_cameras: bool = False


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
        kind, where = _stage_kind(spec, i, source)
        if spec.name in names:
            raise ConfigError(f"stage name '{spec.name}' is used twice in {source}")
        _check_consumes(spec, names, [s.name for s in recipe.stages], where)
        consumed = {dep: planned[names.index(dep)] for dep in spec.consumes}
        kind.module.check_consumes(spec.kind, {dep: p.spec.kind for dep, p in consumed.items()}, where)
        family, model_cfg = _model_config(kind, spec, consumed, f"stages[{i}].model", source, where)
        kind.module.check_model(model_cfg, f"stages.{spec.name}.model")
        check_model_counts(model_cfg, f"stages.{spec.name}.model", source)
        wrong = sorted(set(spec.data or {}) - set(STAGE_DATA_KEYS))
        if wrong:
            raise ConfigError(
                f"stages[{i}].data.{wrong[0]} in {source}: a stage sets only {', '.join(STAGE_DATA_KEYS)}; the dataset "
                "is the recipe's"
            )
        stage_data = validate_section(DataConfig, {**data, **(spec.data or {})}, f"stages[{i}].data", source)
        trainer = validate_section(
            TrainerConfig, {**to_container(recipe.trainer), **(spec.trainer or {})}, f"stages[{i}].trainer", source
        )
        if trainer.max_steps <= 0:
            key = (
                f"stages.{spec.name}.trainer.max_steps" if "max_steps" in (spec.trainer or {}) else "trainer.max_steps"
            )
            raise ConfigError(
                f"{key} is {trainer.max_steps} in {source}: a stage trains for a positive number of optimizer steps "
                "(training streams data without end, so there is no 'until the data runs out')"
            )
        for section, value, own in (
            ("trainer", trainer, spec.trainer),
            ("data", stage_data, spec.data),
            ("optim", spec.optim, None),
        ):
            check_ranges(section, value, spec.name, own, source)
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
        cameras = kind.module.camera_input(model_cfg)
        planned.append(PlannedStage(spec, kind, model_cfg, trainer, config, digest, stage_data, family, cameras))
        names.append(spec.name)
    if not planned:
        raise ConfigError(f"{source} has no stages")
    return planned


def _stage_kind(spec: StageSpec, i: int, source: str) -> tuple[StageKind, str]:
    """The registered kind of the recipe's ``i``-th stage (its name and kind checked first),
    and how errors name the stage."""
    for key in ("name", "kind"):
        if OmegaConf.is_missing(spec, key):
            raise ConfigError(
                f"stages[{i}] in {source} has no '{key}:'; every stage needs a name and a kind "
                f"({', '.join(kind_names())})"
            )
    check_name(spec.name, f"stages[{i}].name", source, "a stage")
    where = f"stages[{i}] ('{spec.name}') in {source}"
    kind = get_kind(spec.kind)
    if kind is None:
        raise ConfigError(f"unknown stage kind '{spec.kind}' for {where}; kinds are {', '.join(kind_names())}")
    if not (inspect.isclass(kind.module) and issubclass(kind.module, Stage)) or inspect.isabstract(kind.module):
        raise ConfigError(
            f"stage kind '{spec.kind}' of {where} is registered with {kind.module!r}, "
            "which is not a concrete occtrain.stages.Stage (it must subclass Stage and implement export)"
        )
    return kind, where


def _check_consumes(spec: StageSpec, earlier: list[str], every: list[str], where: str) -> None:
    """A stage consumes the exports of stages that run before it."""
    for dep in spec.consumes:
        if dep == spec.name:
            raise ConfigError(f"{where} consumes itself; a stage consumes the exports of earlier stages")
        if dep not in earlier:
            later = " (it runs later)" if dep in every else ""
            raise ConfigError(f"{where} consumes '{dep}', which is not an earlier stage{later}")


#: Settings whose type alone lets through values that fail late, deep in Lightning or
#: torch: the least each may be, per section (``None``: any finite number).
_LEAST: dict[str, dict[str, float | None]] = {
    "trainer": {
        "devices": 1,
        "num_nodes": 1,
        "val_check_interval": 1,
        "log_every_n_steps": 1,
        "ckpt_every_n_steps": 1,
        "accumulate_grad_batches": 1,
        "limit_val_batches": -1,
        "gradient_clip_val": 0,
    },
    "data": {
        "batch_size": 1,
        "num_workers": 0,
        "shuffle_buffer": -1,
        "samples_per_shard": 1,
        "history": 0,
        "future": 0,
    },
    "optim": {"lr": 0, "weight_decay": 0, "warmup_steps": 0, "min_lr_ratio": 0, "eps": 0},
}
#: Seeds per section (dotted below it): numpy takes 0 to 2**32 - 1 and raises deep in
#: Lightning's seeding, the synthesis or a loader otherwise.
_SEEDS: dict[str, tuple[str, ...]] = {"trainer": ("seed",), "data": ("seed", "synth.seed")}


#: Counts in a stage's ``model:`` that size a batch or a loop, whichever kinds have them:
#: the least each may be. Out of range they fail late and raw (``val_batch_size: 0``:
#: ``range() arg 3 must not be zero`` once validation generates) or do nothing at all
#: (a negative one validates no item).
_MODEL_LEAST = {"val_batch_size": 1, "prior_batches": 0}


def check_model_counts(model: Any, key: str, source: str) -> None:
    """Refuse a ``model:`` count out of range (``_MODEL_LEAST``) in one line naming its key."""
    for name, least in _MODEL_LEAST.items():
        value = getattr(model, name, None)
        if isinstance(value, int) and value < least:
            raise ConfigError(f"{key}.{name} is {value} in {source}: it must be at least {least}")


def check_ranges(section: str, cfg: Any, stage: str, own: dict | None, source: str) -> None:
    """Refuse a value out of its range (``batch_size: 0``, ``lr: -1``, ``lr: nan``,
    ``val_check_interval: 0``) in one line naming its key, before anything is written."""
    for name, least in _LEAST[section].items():
        value = getattr(cfg, name)
        if section == "trainer" and name == "devices" and value == -1:  # Lightning's "every device"
            continue
        if isinstance(value, float) and not math.isfinite(value) or (least is not None and value < least):
            key = (
                f"stages.{stage}.{section}.{name}" if section == "optim" or name in (own or {}) else f"{section}.{name}"
            )
            wanted = (
                "a finite number" if isinstance(value, float) and not math.isfinite(value) else f"at least {least:g}"
            )
            if name == "devices":
                wanted += ", or -1 for every device"
            raise ConfigError(f"{key} is {value} in {source}: it must be {wanted}")
    for name in _SEEDS.get(section, ()):
        seed = cfg
        for part in name.split("."):
            seed = getattr(seed, part)
        key = f"stages.{stage}.{section}.{name}" if name in (own or {}) else f"{section}.{name}"
        check_seed(seed, key, f" in {source}")
    if section == "optim" and (
        len(cfg.betas) != 2 or not all(0 <= b < 1 for b in cfg.betas) or cfg.schedule not in ("cosine", "constant")
    ):
        key = "schedule" if cfg.schedule not in ("cosine", "constant") else "betas"
        raise ConfigError(
            f"stages.{stage}.optim.{key} is {getattr(cfg, key)} in {source}: schedule is cosine or constant, betas two "
            "numbers in [0, 1)"
        )


def _model_config(
    kind: StageKind, spec: StageSpec, consumed: dict, key: str, source: str, where: str
) -> tuple[str | None, Any]:
    """The stage's family and its ``model:`` validated against the schema for that family
    (only the chosen family's settings: registering another family changes no hash)."""
    raw = to_container(spec.model) if spec.model is not None else {}
    raw = raw if isinstance(raw, dict) else {}
    family = kind.module.family_of(raw, consumed)
    named = raw.get("family")
    if named and named != family:
        get_family(str(named), f"{key}.family in {source}")  # a typo is named as one
        raise ConfigError(
            f"{key}.family in {source} is '{named}', but the stage tunes the consumed '{family}' world model; leave it "
            "out"
        )
    kind.module.check_family(family, consumed, where)
    return family, validate_section(kind.module.model_schema(kind, family, raw), spec.model or {}, key, source)


#: A dotted Python module name: what ``plugins:`` lists.
PLUGIN_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


def load_plugins(modules: list[str], source: str) -> None:
    """Import the recipe's plugin modules, which register their stage kinds and families;
    whatever one raises is one line naming it (``core.registry.load_plugin``)."""
    from functools import partial

    from occtrain.core.registry import load_plugin

    for name in modules:
        if not PLUGIN_NAME.fullmatch(str(name)):
            # importlib would take a path for a relative import, or a file name for a package
            # and its module, and say so in its own terms.
            raise ConfigError(
                f"plugin '{name}' in {source}: a plugin is a Python module name (e.g. my_package.occtrain_plugin), "
                "importable on sys.path"
            )
        load_plugin(partial(importlib.import_module, name), f"plugin '{name}' in {source}", name)


def _stage_names(path: str | Path) -> list[str]:
    """Stage names of a recipe file as written (for addressing stages in overrides)."""
    stages = read_yaml(Path(path)).get("stages") or []
    return [str(s.get("name")) for s in stages if isinstance(s, dict)] if isinstance(stages, list) else []


def stage_override(item: str, names: list[str], source: str) -> str:
    """``stages.<name>.key=v`` and ``stages.<i>.key=v`` -> ``stages[<i>].key=v``; others unchanged."""
    key = item.split("=", 1)[0].strip()
    parts = key.split(".")
    if parts[0] != "stages" or len(parts) < 3:
        return item
    ref = parts[1]
    if ref.isdigit() and int(ref) < len(names):
        index = int(ref)
    elif ref in names:
        index = names.index(ref)
    else:
        forms = "stages.<name>.<key>=, stages.<index>.<key>= or stages[<index>].<key>="
        raise ConfigError(
            f"override '{item}': {source} has no stage '{ref}' (stages: {', '.join(names) or 'none'}); address one as "
            f"{forms}"
        )
    return f"stages[{index}].{'.'.join(parts[2:])}={item.split('=', 1)[1]}" if "=" in item else item


def shadowed_overrides(recipe: RecipeConfig, overrides: list[str]) -> list[str]:
    """One note per command-line ``trainer.<key>=`` that some stage's own ``trainer:`` overrides."""
    notes = []
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if not key.startswith("trainer.") or "=" not in item:
            continue
        sub = key.split(".", 1)[1]
        own = [s.name for s in recipe.stages if sub in (s.trainer or {})]
        if own:
            notes.append(
                f"{key}={item.split('=', 1)[1]} applies to every stage except {', '.join(own)}, which set their own "
                f"(override one with stages.{own[0]}.trainer.{sub}=...)"
            )
    return notes


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> tuple[RecipeConfig, list[PlannedStage]]:
    """The recipe with its overrides, and its stages planned and validated."""
    overrides = list(overrides or [])
    if any(o.startswith("stages.") for o in overrides):
        names = _stage_names(path)
        overrides = [stage_override(o, names, str(path)) for o in overrides]
    recipe = load_config(RecipeConfig, path, overrides)
    if OmegaConf.is_missing(recipe, "name"):
        raise ConfigError(f"{path} has no 'name:'; a recipe names its run (the run directory is <runs_root>/<name>)")
    check_name(recipe.name, "name", str(path), "a run")
    load_plugins(list(recipe.plugins), str(path))
    planned = plan_stages(recipe, str(path))
    check_table(recipe.table, [p.spec.name for p in planned], str(path))
    return recipe, planned


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


def _execute(
    stage: PlannedStage,
    recipe: RecipeConfig,
    stage_dir: Path,
    inputs: dict[str, Path],
    record_time: Callable[[float], None] | None = None,
    record_attempt: Callable[[dict], None] | None = None,
    attempt: StageAttempt | None = None,
) -> dict:
    from occtrain.stages.checkpoints import checkpoint_step, last_checkpoint
    from occtrain.stages.trainer import build_trainer

    module, datamodule = build_stage(stage, stage_dir, inputs)
    say = console.print if is_rank_zero() else (lambda line: None)
    ckpt = last_checkpoint(stage_dir, say=lambda line: say(f"[yellow]note[/]: {line}"))
    resume_step = checkpoint_step(ckpt) if ckpt is not None else None
    monitor, mode = module.monitored(stage.kind)
    trainer = build_trainer(stage.trainer, stage_dir, monitor, mode, resume_step, record_time, record_attempt)
    if ckpt is not None:
        say(f"[yellow]resuming[/] {stage.spec.name} from {ckpt} (step {resume_step})")
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
    if module.validated_at == trainer.global_step and trainer.global_step > 0:
        # fit validated the final weights already (generation makes validation costly).
        results = [{k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")}]
    else:
        results = trainer.validate(module, datamodule=datamodule, verbose=False)
    metrics = {k: float(v) for k, v in (results[0] if results else {}).items()}
    report = module.report()
    metrics.update(report.metrics)
    metrics.update(_measurements(trainer.callbacks))
    artifacts: dict[str, str] = {}
    module.prepare_export()  # every rank: a sharded stage gathers its weights for rank zero
    if trainer.is_global_zero:
        export_dir = module.export(stage_dir / "export")
        provenance = _validation_provenance(stage, trainer.callbacks, report.coverage, attempt or StageAttempt())
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
    stage: PlannedStage, callbacks: list, coverage: dict[str, list[int]], attempt: StageAttempt
) -> Provenance:
    """What a stage's final validation measured: the val samples its batches held of the
    split's (``validation``), and the items its generation scored per task (``coverage``:
    a world model's validation generates on a subset, ``val_samples`` per task)."""
    from occtrain.data.datamodule import shards_dir
    from occtrain.data.layout import world_identity
    from occtrain.data.shards import shard_urls
    from occtrain.stages.callbacks import AttemptRecord
    from occtrain.version import code_version

    record = next((c for c in callbacks if isinstance(c, AttemptRecord)), None)
    validated = {}
    if record is not None and record.val_samples_per_rank is not None:
        total = shard_urls(shards_dir(stage.data), stage.kind.data_kind, "val")[1]
        validated["validation"] = [sum(record.val_samples_per_rank), total]
    identity = world_identity(stage.data.root)
    return Provenance(
        by="validation at the end of training",
        split="val",
        coverage={**validated, **coverage},
        world=identity.key,
        world_version=identity.version,
        world_name=identity.name,
        code_version=code_version(),
        stage=attempt,
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )


def _measurements(callbacks: list) -> dict[str, float]:
    """What this attempt measured (a measurement, not a result): its mean step time and
    throughput and rank zero's peak memory."""
    from occtrain.stages.callbacks import PeakMemory, StepMeter

    meter = next(c for c in callbacks if isinstance(c, StepMeter))
    out: dict[str, float] = meter.summary()
    memory = next(c for c in callbacks if isinstance(c, PeakMemory))
    if memory.peak_mb is not None:
        out["train_peak_rss_mb"] = memory.peak_mb
    if memory.peak_gpu_mb is not None:
        out["train_peak_gpu_mb"] = memory.peak_gpu_mb
    return out


def run(
    recipe_path: str | Path,
    overrides: list[str] | None = None,
    run_dir: str | Path | None = None,
    only: str | None = None,
    restart: str | None = None,
) -> Path:
    """Run (or continue) a recipe; returns the run directory.

    Raises OcctrainError on bad input or a failed stage, :class:`Interrupted` on SIGTERM /
    SIGINT (the running stage is then recorded as ``interrupted``). A refused run (a done
    stage whose config changed, ...) writes nothing. Rank zero holds the run directory's
    lock for the whole run.
    """
    check = check_run(recipe_path, overrides, run_dir, only, restart)
    recipe, planned, run_dir, restarted = check.recipe, check.planned, check.run_dir, check.restarted
    rank_zero = is_rank_zero()
    if rank_zero:
        for note in shadowed_overrides(recipe, list(overrides or [])):
            console.print(f"[yellow]note[/]: {note}")
    with _holding(run_dir, rank_zero) as held:
        # Read again under the lock: the manifest this run writes is the one it checked.
        manifest = Manifest.load(run_dir, writable=rank_zero)
        if rank_zero:  # an earlier --restart killed before it settled
            note = manifest.settle_aside()
            if note:
                console.print(f"[yellow]note[/]: {note}")
        refuse_changed(planned, manifest, restarted, only)
        manifest.name = recipe.name
        for p in planned:
            manifest.entry(p.spec.name, p.spec.kind)
        try:
            if rank_zero:
                _prepare(recipe, manifest, [p.spec.name for p in planned if p.spec.name in restarted], held)
            try:
                _run_stages(planned, manifest, run_dir, recipe, only, rank_zero)
            except (Exception, Interrupted) as err:
                if rank_zero and restarted:
                    _put_back(err, manifest.settle_aside())
                raise
            else:
                if rank_zero:
                    manifest.settle_aside(succeeded=True)
            finally:
                if rank_zero:
                    _write_table(run_dir, recipe, manifest)
                    _write_dashboard(run_dir)  # after the table: the page shows it
        except Interrupted as stop:
            if not str(stop).startswith("stage "):
                stop = stop.with_message(f"{stop} before any stage trained; run the same command again to continue")
            raise stop from None
    return run_dir


@contextlib.contextmanager
def _holding(run_dir: Path, rank_zero: bool) -> Iterator[contextlib.ExitStack]:
    """Stop signals turned into :class:`Interrupted`, the run directory's lock (rank zero),
    and a stack the stage locks a restart takes join for the run's life."""
    with stop_on_signals(), contextlib.ExitStack() as held:
        if rank_zero:
            held.enter_context(run_lock(run_dir))
        yield held


def _prepare(recipe: RecipeConfig, manifest: Manifest, restarted: list[str], held: contextlib.ExitStack) -> None:
    """What rank zero writes before training: the recipe, the manifest, the data, and for a
    restart its stages set aside, once no eval or drive scores them (their locks then held
    in ``held`` for the run's life: none writes into a stage replaced under it)."""
    from occtrain.data.datamodule import ensure_data

    pipeline = manifest.path.parent / PIPELINE_FILE
    if not restarted:
        atomic_write_text(pipeline, to_yaml(recipe))
    manifest.save()
    ensure_data(recipe.data)
    if restarted:  # last before training: nothing else can fail with the stages away
        for name in restarted:
            held.enter_context(restart_lock(manifest.path.parent, name))
        # The old pipeline.yaml goes aside with the stages it describes, and comes back with
        # them if this attempt stops before it takes.
        manifest.set_aside(restarted)
        atomic_write_text(pipeline, to_yaml(recipe))


def restart_lock(run_dir: Path, stage: str) -> contextlib.AbstractContextManager[None]:
    """The lock a ``--restart`` holds on a stage it replaces: none while the stage is being
    scored (``occtrain eval`` and ``drive`` share it while they read and write it)."""
    busy = (
        f"{run_dir / stage} is being scored by `occtrain eval` or `occtrain drive` in another process; wait for it "
        f"to finish (or stop it), then --restart {stage}"
    )
    return stage_lock(run_dir, stage, shared=False, busy=busy)


def _put_back(err: BaseException, note: str) -> None:
    """Say, in the failure's own line, that the stages a restart replaced are back."""
    if note and isinstance(err, (OcctrainError, Interrupted)) and err.args:
        err.args = (f"{err.args[0]}; {note}", *err.args[1:])


@dataclass
class RunCheck:
    """A recipe checked from end to end before anything is written (``check_run``)."""

    recipe: RecipeConfig
    planned: list[PlannedStage]
    run_dir: Path
    restarted: set[str]
    #: What the run will do with its data (synthesize it, write shards, read them).
    data: str


def check_run(
    recipe_path: str | Path,
    overrides: list[str] | None = None,
    run_dir: str | Path | None = None,
    only: str | None = None,
    restart: str | None = None,
) -> RunCheck:
    """Every check ``occtrain run`` makes before it writes anything (``occtrain validate``
    runs exactly these): the recipe's schema, stage kinds, families and architectures,
    handoffs, value ranges, the run directory's manifest, and the data (checked, not
    written: a dataset that exists is opened and its shards compared with it)."""
    from occtrain.data.datamodule import check_data

    recipe, planned = load_recipe(recipe_path, overrides)
    names = [p.spec.name for p in planned]
    for flag, value in (("--only", only), ("--restart", restart)):
        if value is not None and value not in names:
            raise ConfigError(f"{flag} names stage '{value}', but {recipe_path} has stages {', '.join(names)}")
    run_dir = Path(run_dir) if run_dir else Path(recipe.runs_root) / recipe.name
    restarted = set(names[names.index(restart) :]) if restart is not None else set()
    manifest = Manifest.load(run_dir, writable=False)
    refuse_changed(planned, manifest, restarted, only)
    for name in restarted:
        with restart_lock(run_dir, name):
            pass
    for p in planned:  # a checkpoint the run would resume from must load (weights only)
        entry = manifest.stages.get(p.spec.name)
        if entry is not None and entry.status in RESUMABLE and p.spec.name not in restarted:
            from occtrain.stages.checkpoints import last_checkpoint

            last_checkpoint(run_dir / p.spec.name)
    refuse_without_cameras(planned, recipe.data)
    will_train = [
        p
        for p in planned
        if (only is None or p.spec.name == only)
        and (p.spec.name in restarted or getattr(manifest.stages.get(p.spec.name), "status", "pending") != "done")
    ]
    data = check_data(recipe.data, [p.spec.name for p in will_train if p.kind.data_kind == "clips"])
    refuse_missing_tasks(will_train, recipe.data)
    refuse_unrunnable_trainers(will_train)
    return RunCheck(recipe, planned, run_dir, restarted, data)


def refuse_unrunnable_trainers(planned: list[PlannedStage]) -> None:
    """A GPU config on a CPU machine, more devices than exist, a strategy the accelerator
    does not take (or ``fsdp`` for a stage kind that does not shard), a logger that is
    unknown or not installed: refused before the first stage writes anything."""
    from occtrain.stages.loggers import check_loggers
    from occtrain.stages.sharding import SHARDED
    from occtrain.stages.trainer import check_trainer_setup

    keys = ("accelerator", "devices", "num_nodes", "strategy", "precision")
    checked: set[tuple] = set()
    for p in planned:
        if p.trainer.strategy == SHARDED and not p.kind.module.shards:
            key = (
                f"stages.{p.spec.name}.trainer.strategy" if "strategy" in (p.spec.trainer or {}) else "trainer.strategy"
            )
            raise ConfigError(
                f"{key} is {SHARDED}, but a {p.spec.kind} stage does not shard (the pretrain and instruct stages do); "
                f"train '{p.spec.name}' with stages.{p.spec.name}.trainer.strategy=ddp"
            )
    for p in planned:
        setup = tuple(getattr(p.trainer, k) for k in keys)
        if setup in checked:
            continue
        checked.add(setup)
        own = set(p.spec.trainer or {}) & set(keys)
        check_trainer_setup(p.trainer, f"stages.{p.spec.name}.trainer" if own else "trainer")
    for p in planned:
        check_loggers(
            list(p.trainer.loggers),
            f"stages.{p.spec.name}.trainer.loggers" if "loggers" in (p.spec.trainer or {}) else "trainer.loggers",
        )


def refuse_missing_tasks(planned: list[PlannedStage], data: DataConfig) -> None:
    """Check each stage's task settings, and refuse a task (weighted above 0) whose sidecar
    the dataset lacks: a plain Occ3D release has occupancy and ego poses only."""
    from occtrain.data.layout import ANNOTATIONS_FILE
    from occtrain.stages.stage import lacking_tasks

    root = Path(data.root)
    exists = (root / ANNOTATIONS_FILE).is_file()  # a world still to be synthesized has every sidecar
    for p in planned:
        tasks = getattr(p.model_cfg, "tasks", None)
        if tasks is None or not OmegaConf.is_config(tasks):
            continue
        key = f"stages.{p.spec.name}.model.tasks"
        settings = OmegaConf.to_object(tasks)
        if hasattr(settings, "validate"):
            settings.validate(key)
        weighted = [task for task, weight in (settings.weights or {}).items() if weight > 0]
        for task, why in (lacking_tasks(root, weighted) if exists and weighted else {}).items():
            raise ConfigError(f"task {task} {why} ({root}); add the sidecar or set {key}.weights.{task}=0")


def refuse_without_cameras(planned: list[PlannedStage], data: DataConfig) -> None:
    """Raise (before anything is written) when a stage reads camera images the dataset lacks."""
    readers = [p.spec.name for p in planned if p.reads_cameras]
    if not readers:
        return
    from occtrain.data.layout import ANNOTATIONS_FILE, DatasetIndex

    root = Path(data.root)
    if (root / ANNOTATIONS_FILE).is_file():
        if not DatasetIndex.open(root).has_cameras:
            raise ConfigError(
                f"stage '{readers[0]}' reads camera images, and {root} has none (no camera_sensor records or no "
                "imgs/); "
                "point data.root at a dataset with cameras, or move this one away to synthesize one"
            )
    elif data.synth.camera_height <= 0:
        raise ConfigError(f"stage '{readers[0]}' reads camera images; data.synth.camera_height=0 synthesizes none")


def refuse_changed(planned: list[PlannedStage], manifest: Manifest, restarted: set[str], only: str | None) -> None:
    """Raise (before anything is written) when a done stage's config changed, or a cut-off
    stage that would resume has a checkpoint from another config."""
    for p in planned:
        name, entry = p.spec.name, manifest.stages.get(p.spec.name)
        if entry is None or name in restarted or not entry.config_hash or entry.config_hash == p.config_hash:
            continue
        keys = ", ".join(changed_keys(entry.config, p.config)[:6]) or "inputs"
        if entry.status == "done":
            raise ConfigError(
                f"stage '{name}' is done but its config changed ({keys}); `--restart {name}` retrains it and the "
                "stages after it"
            )
        resumes = only is None or only == name
        if resumes and entry.status in RESUMABLE and (manifest.path.parent / name / "checkpoints").exists():
            raise ConfigError(
                f"stage '{name}' was cut off under a different config ({keys}); `--restart {name}` starts it afresh"
            )


def _rerun_starts(stage_dir: Path) -> str:
    """Where a rerun of a stopped stage starts, as its checkpoints say (the end of its line)."""
    from occtrain.stages.checkpoints import LAST_CKPT, checkpoint_step, last_checkpoint

    try:
        ckpt = last_checkpoint(stage_dir)
        step = checkpoint_step(ckpt) if ckpt is not None else None
    except Exception:  # noqa: BLE001 - the stop's line comes out whatever the checkpoint holds
        ckpt = None
    if ckpt is None:
        unreadable = (stage_dir / "checkpoints" / LAST_CKPT).is_file()
        when = " with no readable checkpoint" if unreadable else " before its first checkpoint"
        return f"{when}; rerun the same command to start it over"
    return f"; rerun the same command to resume it from its checkpoint at step {step} ({ckpt})"


def _record_failure(manifest: Manifest, name: str, summary: str, seconds: float, status: str) -> None:
    """Record a stopped stage; when even that write fails (a full disk), the manifest keeps
    its last good state (``running``: a rerun resumes) and the original error is reported."""
    try:
        manifest.mark_failed(name, summary, seconds, status=status)
    except OcctrainError:
        pass


def _write_dashboard(run_dir: Path) -> None:
    """The run's page, after success or failure alike; a page problem never fails a run."""
    from occtrain.dashboard import write_dashboard

    try:
        out = write_dashboard(run_dir)
        console.print(f"dashboard -> {out}")
    except Exception as err:  # noqa: BLE001 - the run's results are safe; the page is a view of them
        line = str(err).splitlines()[0] if str(err) else type(err).__name__
        console.print(f"[yellow]dashboard not written[/]: {type(err).__name__}: {line}")


def _write_table(run_dir: Path, recipe: RecipeConfig, manifest: Manifest) -> None:
    """Print the recipe's table and write ``table.md`` once every stage is done; until then
    there is none (a stale one would show a retrained stage's old figures). Like the page, a
    problem with it never fails a run."""
    try:
        if recipe.table is not None and all(manifest.stages[s.name].status == "done" for s in recipe.stages):
            console.print(f"table -> {show_table(run_dir, recipe.table, manifest)}")
        else:
            remove_inside(run_dir / TABLE_FILE, run_dir)
    except (OcctrainError, OSError) as err:
        line = str(err).splitlines()[0] if str(err) else type(err).__name__
        console.print(f"[yellow]table not written[/]: {line}")


def _run_stages(
    planned: list[PlannedStage],
    manifest: Manifest,
    run_dir: Path,
    recipe: RecipeConfig,
    only: str | None,
    rank_zero: bool,
) -> None:
    exports: dict[str, Path] = {}
    for p in planned:
        name, entry, stage_dir = p.spec.name, manifest.stages[p.spec.name], run_dir / p.spec.name
        if entry.status == "done":
            exports[name] = stage_dir / "export"
            if rank_zero:
                console.print(f"[green]done[/]    {name:14s} skipped (finished earlier; {entry.wall_time_s:.0f}s)")
            continue
        if only is not None and name != only:
            continue
        missing = [d for d in p.spec.consumes if d not in exports]
        if missing:
            raise ConfigError(
                f"stage '{name}' consumes the export of '{missing[0]}', which is not done; run it first (drop --only)"
            )
        manifest.mark_running(name, p.config_hash, p.config)
        started = time.time()
        try:
            result = _execute(
                p,
                recipe,
                stage_dir,
                {d: exports[d] for d in p.spec.consumes},
                record_time=lambda seconds, name=name: manifest.record_time(name, seconds),
                record_attempt=lambda facts, name=name: manifest.record_attempt(name, facts),
                attempt=StageAttempt(entry.config_hash, entry.attempts, entry.started),
            )
        except Interrupted as stop:
            _record_failure(manifest, name, f"{stop}", time.time() - started, "interrupted")
            raise stop.with_message(f"stage '{name}' of {run_dir} {stop}{_rerun_starts(stage_dir)}") from None
        except Exception as err:
            line = str(err).splitlines()[0] if str(err) else type(err).__name__
            summary = line if isinstance(err, OcctrainError) else cause_line(err)
            _record_failure(manifest, name, summary, time.time() - started, "failed")
            if rank_zero and not isinstance(err, OcctrainError):
                try:
                    atomic_write_text(stage_dir / "logs" / "traceback.txt", traceback.format_exc())
                    summary += f" (traceback in {stage_dir / 'logs' / 'traceback.txt'})"
                except OcctrainError:
                    pass
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

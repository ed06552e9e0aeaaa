"""What ``occtrain validate`` (and ``run`` before it trains anything) refuses: trainers this
machine cannot run, tasks the data cannot feed, camera stages on a world without cameras,
done stages whose config changed."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from occtrain.config.groups import DataConfig
from occtrain.config.recipe import RecipeConfig
from occtrain.errors import ConfigError
from occtrain.formats.manifest import RESUMABLE, Manifest
from occtrain.run.control import restart_lock
from occtrain.run.planning import PlannedStage, changed_keys, load_recipe


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
        with restart_lock(run_dir, name, str(restart)):
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
    from occtrain.core.shared_tasks import TaskConfig
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
        if not isinstance(settings, TaskConfig):  # a family's task settings extend it (the registry checks)
            continue
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

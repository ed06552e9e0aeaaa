"""``occtrain eval RUN_DIR/STAGE``: score a stage's export on a split.

The stage's kind says how (``Stage.evaluate_export``; the kinds that can are the
registered ones with ``evaluable``): a world model's export is loaded exactly as a later
stage would load it, its answers are generated on every item of the split and scored with
its family's scorers; a tokenizer's reconstructs every frame of the split. The metrics go
to ``<stage>/eval/<split>/metrics.json``. ``--save-predictions DIR`` also writes the
predictions in the formats ``occtrain score`` reads, so both paths give one number.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_write_json, atomic_write_npz, check_output, remove_inside
from occtrain.formats.metrics_file import MetricsFile, Provenance, read_metrics, write_metrics
from occtrain.progress import print_wide
from occtrain.run.control import scoring_lock
from occtrain.run.done_stage import DoneStage, done_stage

if TYPE_CHECKING:  # the stages (Lightning) load where a stage is read, not when the CLI starts
    from occtrain.stages.stage import EvalResult


def eval_metrics_file(
    stage_dir: str | Path,
    split: str = "val",
    data_root: str | Path | None = None,
    world: str = "",
    blank_cameras: bool = False,
) -> Path:
    """Where ``evaluate`` writes its metrics: ``eval/<split>/`` on the run's dataset,
    ``eval/<folder>-<world key>/<split>/`` on another (see ``world_key``; ``world`` when the
    caller has it already), so two worlds in folders of one name never share a file; with
    its cameras blanked, ``<split>+blank_cameras/`` beside the split's own scores."""
    from occtrain.data.blank_cameras import BLANK_SUFFIX

    out = Path(stage_dir) / "eval"
    if data_root is not None:
        from occtrain.data.shards import world_key

        out = out / f"{Path(data_root).resolve().name}-{world or world_key(data_root)}"
    return out / (split + BLANK_SUFFIX if blank_cameras else split) / "metrics.json"


def evaluate(
    stage_dir: str | Path,
    split: str = "val",
    tasks: list[str] | None = None,
    save_predictions: str | Path | None = None,
    samples: int = -1,
    batch_size: int = 16,
    data_root: str | Path | None = None,
    blank_cameras: bool = False,
) -> dict[str, float]:
    """Metrics of ``stage_dir``'s export on ``split`` (see the module docstring) of the run's
    dataset, or of ``data_root`` (e.g. a world synthesized from another seed): then the
    metrics go to ``eval/<its directory name>-<world key>/<split>/`` and its baselines come
    from its own train split. With ``blank_cameras``, of that dataset's view with every
    camera image black (``data.blank_cameras``, made once in the run's cache): a stage
    that learned from its cameras scores lower there. The metrics file records what they were measured on
    (``formats.metrics_file``). The stage is held (a shared lock) while it is scored, so a
    ``--restart`` of it waits its turn, and the scores of a model that changed meanwhile are
    never written."""
    from occtrain.data.shards import world_key
    from occtrain.stages.stage import EvalRequest, shared_cache_dir, stage_cache_dir

    stage_dir = Path(stage_dir)
    done = _evaluable_stage(stage_dir, split, samples, batch_size)
    source = str(data_root) if data_root is not None else done.recipe.data.root
    world = world_key(source)
    # Scored beside the split's own scores on the dataset named, whatever view of it is read.
    metrics_file = eval_metrics_file(stage_dir, split, data_root, world, blank_cameras)
    _check_outputs(stage_dir, done.spec.kind, done.kind.module.saves_predictions, metrics_file, save_predictions)
    root = source
    if blank_cameras:
        root = str(blanked_data(done, Path(source), world))
        world = world_key(root)
    # Prompts and generation length come from the export: exactly what the model trained with.
    # Inputs encoded by frozen encoders are looked up in the stage's cache of this world (made
    # by the same encoder; built if the stage trained without one). Scenes are in the run's
    # shared cache, keyed by the encoder and the dataset they were made from.
    _refuse_unscorable(tasks or [], root)
    with scoring_lock(stage_dir, "occtrain eval"):
        done.refuse_changed("occtrain eval")  # retrained between the check above and the lock
        request = EvalRequest(
            stage_dir / "export",
            [stage_dir.parent / dep / "export" for dep in done.spec.consumes],
            root,
            split,
            tasks,
            samples,
            batch_size,
            stage_cache_dir(stage_dir, root),
            shared_cache_dir(stage_dir),
            save_predictions is not None,
        )
        result = done.kind.module.evaluate_export(request)
        done.refuse_changed("occtrain eval")
        _save(metrics_file, result.metrics, eval_provenance(done, root, split, result, world))
        if save_predictions is not None:
            write_predictions(Path(save_predictions), result.predictions)
    return result.metrics


def blanked_data(done: DoneStage, root: Path, world: str) -> Path:
    """The blanked view of the dataset at ``root`` (``world``: its ``world_key``), once the
    stage ``done`` reads cameras."""
    from occtrain.data.blank_cameras import blank_camera_view

    if not reads_cameras(done):
        raise ConfigError(
            f"--blank-cameras: stage '{done.spec.name}' reads no camera images (nor does a stage it consumes); "
            "leave the flag out"
        )
    return blank_camera_view(root, done.stage_dir.parent / "cache" / "blank_cameras" / world)


def reads_cameras(done: DoneStage) -> bool:
    """Whether the stage, or one it consumes (a frozen camera encoder), reads camera images."""
    from occtrain.run.planning import plan_stages

    planned = {p.spec.name: p for p in plan_stages(done.recipe, str(done.stage_dir.parent / "pipeline.yaml"))}
    todo, seen = [done.spec.name], set()
    while todo:
        name = todo.pop()
        if name in seen or name not in planned:
            continue
        seen.add(name)
        if planned[name].reads_cameras:
            return True
        todo += list(planned[name].spec.consumes)
    return False


def eval_provenance(done: DoneStage, root: str, split: str, result: EvalResult, dataset: str) -> Provenance:
    """What ``occtrain eval``'s numbers of ``done`` on ``root``'s ``split`` were measured on
    (``dataset``: its ``world_key``): the items of each task and of each number (``result``'s)."""
    from occtrain.data.identity import world_identity
    from occtrain.version import code_version

    identity = world_identity(root)
    return Provenance(
        by="occtrain eval",
        split=split,
        coverage=result.coverage,
        world=identity.key,
        world_version=identity.version,
        world_name=identity.name,
        dataset=dataset,
        code_version=code_version(),
        stage=done.attempt,
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        sample_sets=list(result.sample_sets),
    )


def _evaluable_stage(stage_dir: Path, split: str, samples: int, batch_size: int) -> DoneStage:
    """The run's recipe, the stage's spec, kind and attempt, once the arguments, the stage's
    kind and its status (done: an interrupted stage's export is stale) allow an eval."""
    from occtrain.data.layout import SPLITS

    if split not in SPLITS:
        raise ConfigError(f"--split {split}: a dataset's splits are {', '.join(SPLITS)}")
    if samples == 0 or samples < -1:
        raise ConfigError(
            f"--samples {samples}: score a positive number of items per task, or -1 (the default) for all"
        )
    if batch_size < 1:
        raise ConfigError(f"--batch-size {batch_size}: must be at least 1")
    return done_stage(stage_dir, "occtrain eval", "scores", lambda module: module.evaluable)


def _check_outputs(stage_dir: Path, kind: str, saves: bool, metrics: Path, save_predictions: str | Path | None) -> None:
    """Refuse, before the evaluation's minutes, a place its results could not be written."""
    if save_predictions is not None:
        if not saves:
            raise ConfigError(
                f"--save-predictions {save_predictions}: a {kind} stage's eval has metrics only, no predictions to "
                "save "
                "(world-model stages' evals have); leave the flag out"
            )
        check_output(save_predictions, "--save-predictions", kind="dir")
        earlier = _earlier_prediction(Path(save_predictions))
        if earlier is not None:
            raise ConfigError(
                f"{earlier}: exists, and --save-predictions would overwrite it; choose an empty or new directory, or "
                "move the earlier predictions away"
            )
        out = Path(save_predictions)
        other = next((p for p in out.rglob("*") if not p.is_dir()), None) if out.is_dir() else None
        if other is not None:
            raise ConfigError(
                f"--save-predictions {save_predictions}: holds {other.relative_to(out)}; the predictions go in whole "
                "into an empty or new directory: choose one"
            )
    fix = (
        f"eval writes its metrics into {stage_dir}; make it writable, "
        "or copy the run to a writable place and eval the copy"
    )
    check_output(metrics, "the eval directory", fix=fix)


def _earlier_prediction(out: Path) -> Path | None:
    """A file an earlier eval's predictions left in ``out`` (None: none): this eval would
    overwrite it, or, a forecast of another sample, leave it among its own for `score` to read."""
    for name in PREDICTION_FILES:
        if (out / name).exists():
            return out / name
    forecasts = out / FORECAST_DIR
    return next((p for p in sorted(forecasts.rglob("*")) if not p.is_dir()), None) if forecasts.is_dir() else None


def _refuse_unscorable(tasks: list[str], root: str) -> None:
    """Named tasks must be scorable on the dataset (the defaults are trimmed later, with a note)."""
    if not tasks:
        return
    from occtrain.stages.stage import lacking_tasks

    for task, why in lacking_tasks(root, tasks).items():
        raise ConfigError(f"--tasks {task}: the task {why} ({root}); score it on a dataset that has it")


#: What ``--save-predictions DIR`` writes (those of the tasks evaluated), and the folder of
#: the forecasts (``forecast/<scene>/<token>/forecast.npz``).
PREDICTION_FILES = (
    "planning_pred.json",
    "planning_gt.json",
    "qa_questions.json",
    "qa_pred.json",
    "captions_pred.json",
    "captions_ref.json",
    "meta_actions.json",
)
FORECAST_DIR = "forecast"


def _save(out_file: Path, metrics: dict[str, float], provenance: Provenance) -> None:
    """Write ``metrics`` with their provenance, keeping what an earlier eval of the same
    dataset (as it was on disk) and stage attempt wrote for other tasks: never another
    world's or model's (the run's dataset may have changed since, the stage been retrained)."""
    from occtrain.errors import DataError

    earlier: MetricsFile | None = None
    if out_file.is_file():
        try:
            earlier = read_metrics(out_file)
        except DataError:
            raise ConfigError(
                f"{out_file}: holds unreadable metrics; move it away to start the stage's eval afresh"
            ) from None
    before = earlier.provenance if earlier is not None else None
    if earlier is not None and before is not None and before.same_model_and_data(provenance):
        write_metrics(out_file, {**earlier.metrics, **metrics}, provenance.merged(before))
    else:
        write_metrics(out_file, metrics, provenance)
    legacy = out_file.parent / "world.json"  # where evaluations before provenance kept the world's key
    if legacy.is_file():
        legacy.unlink()


def write_predictions(out: Path, predictions: dict[str, dict]) -> None:
    """The evaluator's recorded predictions in ``occtrain score``'s input formats, all at
    once: written into ``.<out>.partial`` beside ``out`` and renamed into place, so a kill
    midway leaves a folder named partial, never an ``out`` that looks whole."""
    partial = out.with_name(f".{out.name}.partial")
    if partial.exists():
        remove_inside(partial, out.parent)  # an earlier eval's, killed while it wrote
    _write_predictions(partial, predictions)
    if out.is_dir():
        if any(not p.is_dir() for p in out.rglob("*")):  # a file put there while the eval ran
            raise ConfigError(f"{out}: files appeared in it while eval ran; the predictions are in {partial}")
        remove_inside(out, out.parent)  # empty folders at most
    os.replace(partial, out)


def _write_predictions(out: Path, predictions: dict[str, dict]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    predictions = {
        k: predictions.get(k, {})
        for k in ("planning", "planning_gt", "forecast", "qa", "captions", "captions_gt", "meta_actions")
    }
    if predictions["planning"]:
        atomic_write_json(out / "planning_pred.json", predictions["planning"])
        atomic_write_json(out / "planning_gt.json", predictions["planning_gt"])
    for token, (scene, semantics) in predictions["forecast"].items():
        atomic_write_npz(
            out / FORECAST_DIR / scene / token / "forecast.npz", {"semantics": np.asarray(semantics, dtype=np.uint8)}
        )
    if predictions["qa"]:
        # NuScenes-QA's format: answers in the order of a questions file, written beside them.
        questions, answers = zip(*predictions["qa"].values())
        atomic_write_json(out / "qa_questions.json", {"questions": list(questions)})
        atomic_write_json(out / "qa_pred.json", list(answers))
    if predictions["captions"]:
        atomic_write_json(out / "captions_pred.json", predictions["captions"])
        atomic_write_json(out / "captions_ref.json", predictions["captions_gt"])
    if predictions["meta_actions"]:
        # Per clip: the generated chain, the meta action read from it and the truth.
        atomic_write_json(out / "meta_actions.json", predictions["meta_actions"])


def sample_count(name: str, metrics: dict[str, float]) -> float | None:
    """How many samples ``name`` was computed on: the ``<family>_samples`` (or
    ``_questions``) entry of the longest family prefix of ``name`` that has one."""
    if name.startswith(("meta_", "baseline_prior_meta_", "baseline_repeat_last_meta_")):
        return metrics.get("meta_action_samples")
    parts = name.split("_")
    for n in range(len(parts), 0, -1):
        prefix = "_".join(parts[:n])
        # A forecast's average is over its horizons; each horizon counts its own frames.
        for suffix in ("_samples", "_questions", f"_frames_{parts[-1]}", "_frames_1s"):
            if prefix + suffix in metrics:
                return metrics[prefix + suffix]
    return None


def print_metrics(metrics: dict[str, float], title: str) -> None:
    """A table of the metrics with the sample count each was computed on."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("samples", justify="right")
    for name in sorted(metrics):
        if name.endswith(("_samples", "_questions")) or "_frames_" in name:
            continue  # shown in the samples column
        n = sample_count(name, metrics)
        table.add_row(name, f"{metrics[name]:.4g}", "" if n is None else f"{n:.0f}")
    print_wide(table)

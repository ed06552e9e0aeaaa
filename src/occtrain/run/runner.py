"""Run a recipe: stages in order, each consuming earlier exports; skip done, resume cut-off.

The run directory holds ``pipeline.yaml``, ``manifest.json`` and one directory per stage
with ``checkpoints/``, ``export/``, ``logs/`` and ``metrics.json``; ``run.execution``
trains each stage.
Under DDP, Lightning re-executes this command in each worker process; every process walks
the same plan from the same manifest snapshot, and only rank zero writes.
"""

from __future__ import annotations

import contextlib
import time
import traceback
from collections.abc import Iterator
from functools import partial
from pathlib import Path

from occtrain.config import to_yaml
from occtrain.config.recipe import RecipeConfig
from occtrain.errors import ConfigError, OcctrainError, cause_line
from occtrain.formats.io import atomic_write_text, remove_inside
from occtrain.formats.manifest import PIPELINE_FILE, Manifest
from occtrain.formats.metrics_file import StageAttempt
from occtrain.progress import console
from occtrain.ranks import is_rank_zero
from occtrain.report.compare import TABLE_FILE, show_table
from occtrain.run.checks import check_run, refuse_changed
from occtrain.run.control import Interrupted, restart_lock, run_lock, stop_on_signals
from occtrain.run.execution import execute_stage
from occtrain.run.planning import PlannedStage, shadowed_overrides


class StageFailed(OcctrainError):
    """A stage raised; the manifest records the one-line summary."""


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
        atomic_write_text(pipeline, _pipeline_text(recipe, pipeline, manifest))
    manifest.save()
    ensure_data(recipe.data)
    if restarted:  # last before training: nothing else can fail with the stages away
        for name in restarted:
            held.enter_context(restart_lock(manifest.path.parent, name, restarted[0]))
        # The old pipeline.yaml goes aside with the stages it describes, and comes back with
        # them if this attempt stops before it takes.
        manifest.set_aside(restarted)
        atomic_write_text(pipeline, to_yaml(recipe))


def _pipeline_text(recipe: RecipeConfig, pipeline: Path, manifest: Manifest) -> str:
    """The run's ``pipeline.yaml``: the recipe, and the stages an earlier recipe trained in
    this directory that this one does not hold (a base recipe run again over a directory it
    shares with one that extends it: ``eval`` and ``drive`` of those stages read their spec
    here). Kept when the manifest records them and what they consume is still described."""
    from omegaconf import OmegaConf

    text = to_yaml(recipe)
    try:
        earlier = OmegaConf.to_container(OmegaConf.create(pipeline.read_text())) if pipeline.is_file() else {}
    except Exception:  # noqa: BLE001 - an unreadable earlier pipeline keeps nothing of it
        return text
    stages = (earlier or {}).get("stages") if isinstance(earlier, dict) else None
    if not isinstance(stages, list):
        return text
    written = OmegaConf.to_container(OmegaConf.create(text))
    assert isinstance(written, dict)
    names = [s["name"] for s in written["stages"]]
    for stage in stages:
        name = stage.get("name") if isinstance(stage, dict) else None
        if name in names or name not in manifest.stages or not set(stage.get("consumes") or []) <= set(names):
            continue
        written["stages"].append(stage)
        names.append(name)
        console.print(f"[yellow]note[/]: {pipeline} keeps stage '{name}', which an earlier recipe trained here")
    return to_yaml(written)


def _put_back(err: BaseException, note: str) -> None:
    """Say, in the failure's own line, that the stages a restart replaced are back."""
    if note and isinstance(err, (OcctrainError, Interrupted)) and err.args:
        err.args = (f"{err.args[0]}; {note}", *err.args[1:])


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
            result = execute_stage(
                p,
                stage_dir,
                {d: exports[d] for d in p.spec.consumes},
                record_time=partial(manifest.record_time, name),
                record_attempt=partial(manifest.record_attempt, name),
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

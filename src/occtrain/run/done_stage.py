"""A done stage as the commands that read it (``occtrain eval``, ``drive``) find it: the
run's recipe and plugins, the stage's spec and kind, and the attempt that trained what it
exports, so that results of a model retrained meanwhile are never written."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occtrain.config import load_config
from occtrain.config.recipe import RecipeConfig, StageSpec
from occtrain.errors import ConfigError
from occtrain.formats.manifest import ASIDE_DIR, Manifest
from occtrain.formats.metrics_file import StageAttempt
from occtrain.run.control import lock_holder
from occtrain.run.planning import load_plugins

if TYPE_CHECKING:  # the stages (Lightning) load where a stage is read, not when the CLI starts
    from occtrain.stages import StageKind


@dataclass(frozen=True)
class DoneStage:
    """A done stage as a command that reads it finds it: the run's recipe, the stage's spec
    and kind, and which attempt trained what it exports."""

    stage_dir: Path
    recipe: RecipeConfig
    spec: StageSpec
    kind: StageKind
    attempt: StageAttempt

    def refuse_changed(self, command: str) -> None:
        """Refuse when the stage was retrained (or is being) since this was read."""
        entry = Manifest.load(self.stage_dir.parent, writable=False).stages.get(self.spec.name)
        now = None if entry is None else StageAttempt(entry.config_hash, entry.attempts, entry.started)
        if entry is None or entry.status != "done" or now != self.attempt:
            raise ConfigError(
                f"{self.stage_dir}: the stage was retrained while {command} read it, so its results of the model it "
                f"loaded are not written; run {command} again"
            )


def done_stage(stage_dir: Path, command: str, verb: str, capable: Callable[[Any], bool]) -> DoneStage:
    """The run's recipe, the stage's spec, kind and attempt, once the stage is of a kind
    ``command`` serves (``capable`` of its module; ``verb`` says what the command does to
    it) and done (an interrupted stage's export is stale)."""
    from occtrain.stages import get_kind, kind_names  # Lightning loads where a stage is read

    pipeline = stage_dir.parent / "pipeline.yaml"
    if not pipeline.is_file():
        raise ConfigError(f"{stage_dir}: not a stage of a run directory (no {pipeline}); pass RUN_DIR/STAGE")
    recipe = load_config(RecipeConfig, pipeline)
    load_plugins(list(recipe.plugins), str(pipeline))  # a plugin's stage kinds and families
    spec = next((s for s in recipe.stages if s.name == stage_dir.name), None)
    if spec is None:
        raise ConfigError(
            f"{pipeline} has no stage '{stage_dir.name}'; stages are {', '.join(s.name for s in recipe.stages)}"
        )
    kind = get_kind(spec.kind)
    if kind is None or not capable(kind.module):
        served = [k for k in kind_names() if (other := get_kind(k)) is not None and capable(other.module)]
        raise ConfigError(f"{command} {verb} {', '.join(served)} stages; '{spec.name}' is a {spec.kind} stage")
    manifest = Manifest.load(stage_dir.parent, writable=False)
    entry = manifest.stages.get(spec.name)
    killed = manifest.after_a_killed_restart() if lock_holder(stage_dir.parent) is None else {}
    if entry is not None and entry.status != "done" and killed.get(spec.name, "").startswith("done"):
        raise ConfigError(
            f"{stage_dir}: a --restart of the run was killed before its first checkpoint and set stage "
            f"'{spec.name}' aside in {stage_dir.parent / ASIDE_DIR}; the next `occtrain run` over "
            f"{stage_dir.parent} puts it back as it was (any recipe: the run settles it first), or rerun the "
            "--restart to retrain it"
        )
    if entry is None or entry.status != "done":
        status = "never run" if entry is None else entry.status
        raise ConfigError(
            f"{stage_dir}: stage '{spec.name}' is {status}, not done, so its export is missing or stale; "
            f"finish it with `occtrain run {pipeline} --run-dir {stage_dir.parent}` first"
        )
    return DoneStage(stage_dir, recipe, spec, kind, StageAttempt(entry.config_hash, entry.attempts, entry.started))

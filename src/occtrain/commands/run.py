"""``occtrain run`` and ``occtrain validate``: a recipe's stages run, or checked and listed
with what each would do, writing nothing."""

from __future__ import annotations

from pathlib import Path


def run(recipe: str, overrides: list[str], run_dir: str | None, only: str | None, restart: str | None) -> Path:
    """Run (or continue) the recipe; rank zero prints the run directory."""
    from occtrain.ranks import is_rank_zero
    from occtrain.run.runner import run as run_recipe

    out = run_recipe(recipe, overrides, run_dir=run_dir, only=only, restart=restart)
    if is_rank_zero():
        print(f"run directory: {out}")
    return out


def validate(recipe: str, overrides: list[str], run_dir: str | None, only: str | None, restart: str | None) -> None:
    """Check the recipe as ``run`` would and list its stages with their state in the run
    directory: pending, done, to retrain, or aside after a killed ``--restart``."""
    from occtrain.formats.manifest import Manifest
    from occtrain.run.checks import check_run
    from occtrain.run.control import lock_holder

    check = check_run(recipe, overrides, run_dir=run_dir, only=only, restart=restart)
    manifest = Manifest.load(check.run_dir, writable=False)
    # A --restart killed midway: its stages are aside until the next run settles them.
    killed = manifest.after_a_killed_restart() if lock_holder(check.run_dir) is None else {}
    n = len(check.planned)
    print(f"{recipe}: ok, {n} stage{'' if n == 1 else 's'}; nothing was written")
    for p in check.planned:
        entry = manifest.stages.get(p.spec.name)
        status = "to retrain" if p.spec.name in check.restarted else entry.status if entry else "pending"
        status = killed.get(p.spec.name, status) if p.spec.name not in check.restarted else status
        family = f", {p.family}" if p.family else ""
        consumes = f", consumes {', '.join(p.spec.consumes)}" if p.spec.consumes else ""
        print(f"  {p.spec.name:12s} {p.spec.kind}{family}: {p.trainer.max_steps} steps{consumes} [{status}]")
    print(check.data)
    print(f"run directory: {check.run_dir}")

"""``occtrain run`` and ``occtrain validate``: a recipe's stages, run or checked."""

from __future__ import annotations

import argparse


def _cmd_run(args: argparse.Namespace) -> int:
    if args.dry_run:
        return _cmd_validate(args)
    from occtrain.run.runner import is_rank_zero, run

    run_dir = run(args.recipe, args.overrides, run_dir=args.run_dir, only=args.only, restart=args.restart)
    if is_rank_zero():
        print(f"run directory: {run_dir}")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from occtrain.formats.manifest import Manifest
    from occtrain.run.checks import check_run
    from occtrain.run.control import lock_holder

    check = check_run(args.recipe, args.overrides, run_dir=args.run_dir, only=args.only, restart=args.restart)
    manifest = Manifest.load(check.run_dir, writable=False)
    # A --restart killed midway: its stages are aside until the next run settles them.
    killed = manifest.after_a_killed_restart() if lock_holder(check.run_dir) is None else {}
    n = len(check.planned)
    print(f"{args.recipe}: ok, {n} stage{'' if n == 1 else 's'}; nothing was written")
    for p in check.planned:
        entry = manifest.stages.get(p.spec.name)
        status = "to retrain" if p.spec.name in check.restarted else entry.status if entry else "pending"
        status = killed.get(p.spec.name, status) if p.spec.name not in check.restarted else status
        family = f", {p.family}" if p.family else ""
        consumes = f", consumes {', '.join(p.spec.consumes)}" if p.spec.consumes else ""
        print(f"  {p.spec.name:12s} {p.spec.kind}{family}: {p.trainer.max_steps} steps{consumes} [{status}]")
    print(check.data)
    print(f"run directory: {check.run_dir}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run a recipe's stages in order (skips done stages, resumes cut-off ones)")
    p.add_argument("recipe", help="recipe YAML, e.g. recipes/quickstart.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, e.g. trainer.max_steps=10 trainer.devices=2")
    p.add_argument("--run-dir", help="run directory (default: runs/<recipe name>)")
    p.add_argument("--only", metavar="STAGE", help="run just this stage (its inputs must be done)")
    p.add_argument("--restart", metavar="STAGE", help="retrain this stage and every stage after it")
    p.add_argument(
        "--dry-run", action="store_true", help="check everything `run` checks first, then stop (as `occtrain validate`)"
    )
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "validate",
        help="check a recipe end to end (schema, kinds, families, handoffs, ranges, run directory, data) "
        "without writing anything",
    )
    p.add_argument("recipe", help="recipe YAML, e.g. recipes/quickstart.yaml")
    p.add_argument("overrides", nargs="*", help="key=value overrides, as for run")
    p.add_argument("--run-dir", help="run directory (default: runs/<recipe name>)")
    p.add_argument("--only", metavar="STAGE", help="as for run")
    p.add_argument("--restart", metavar="STAGE", help="as for run")
    p.set_defaults(func=_cmd_validate)

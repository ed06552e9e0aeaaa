"""``occtrain run`` and ``occtrain validate``: a recipe's stages, run or checked (``commands.run``)."""

from __future__ import annotations

import argparse


def _cmd_run(args: argparse.Namespace) -> int:
    if args.dry_run:
        return _cmd_validate(args)
    from occtrain.commands.run import run

    run(args.recipe, args.overrides, args.run_dir, args.only, args.restart)
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from occtrain.commands.run import validate

    validate(args.recipe, args.overrides, args.run_dir, args.only, args.restart)
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

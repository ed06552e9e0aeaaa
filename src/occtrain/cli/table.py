"""``occtrain table``: a run's comparison table (``commands.table``)."""

from __future__ import annotations

import argparse


def _cmd_table(args: argparse.Namespace) -> int:
    from occtrain.commands.table import table

    table(args.run_dir)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "table", help="print a run's comparison table (the recipe's table:) and rewrite RUN_DIR/table.md"
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory, e.g. runs/tokenizer_ablation")
    p.set_defaults(func=_cmd_table)

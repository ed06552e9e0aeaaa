"""``occtrain table``: a run's comparison table (``report.compare``)."""

from __future__ import annotations

import argparse


def _cmd_table(args: argparse.Namespace) -> int:
    from occtrain.progress import console
    from occtrain.report.compare import load_run_table, show_table

    table, manifest = load_run_table(args.run_dir)
    pending = [
        r.stage for r in table.rows if r.stage not in manifest.stages or manifest.stages[r.stage].status != "done"
    ]
    if pending:
        console.print(f"[yellow]note[/]: not done yet, shown as –: {', '.join(dict.fromkeys(pending))}")
    console.print(f"table -> {show_table(args.run_dir, table, manifest)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "table", help="print a run's comparison table (the recipe's table:) and rewrite RUN_DIR/table.md"
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory, e.g. runs/tokenizer_ablation")
    p.set_defaults(func=_cmd_table)

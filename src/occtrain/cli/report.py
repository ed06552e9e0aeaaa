"""``occtrain report RUN [RUN ...]``: the command line of ``report.results`` (what the page
holds and how it is built is said there)."""

from __future__ import annotations

import argparse
from pathlib import Path

from occtrain.formats.io import atomic_write_text, check_output
from occtrain.report import results
from occtrain.report.results import Run, report


def _cmd_report(args: argparse.Namespace) -> int:
    if args.out:
        check_output(args.out, "--out")  # before the runs are read
    results.check_split(args.split)
    runs = [Run.read(Path(p), args.split) for p in args.runs]
    command = results.command_line(len(runs), args.split, args.title, args.allow_mixed)
    page = report(runs, args.split, command, args.title, args.allow_mixed)
    if args.out:
        atomic_write_text(Path(args.out), page)
    else:
        print(page, end="")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="headline numbers of scored runs beside their baselines, as markdown",
        description=(results.__doc__ or "").split("\n\n")[0].replace("``", "`"),
    )
    p.add_argument("runs", nargs="+", metavar="RUN", help="run directories (scored with occtrain eval)")
    p.add_argument("--split", default="val", help="the split the stages were scored on (default val)")
    p.add_argument("--title", default="", help="the page's heading (a docs page needs one)")
    p.add_argument("--out", help="write the page here (atomically) instead of to stdout")
    p.add_argument(
        "--allow-mixed",
        action="store_true",
        help="set runs side by side although their worlds, scored subsets or code differ (the page says how)",
    )
    p.set_defaults(func=_cmd_report)

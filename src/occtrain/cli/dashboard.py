"""``occtrain dashboard RUN_DIR [--out FILE]``: the command line of ``dashboard.write_dashboard``."""

from __future__ import annotations

import argparse
from pathlib import Path


def _cmd_dashboard(args: argparse.Namespace) -> int:
    from occtrain.dashboard import write_dashboard

    print(write_dashboard(Path(args.run_dir), Path(args.out) if args.out else None))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dashboard", help="write RUN_DIR/dashboard.html: stages, curves, metrics vs papers, samples")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory, e.g. runs/quickstart")
    p.add_argument("--out", metavar="FILE", help="where to write the page (default: RUN_DIR/dashboard.html)")
    p.set_defaults(func=_cmd_dashboard)

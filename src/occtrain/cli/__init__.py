"""The ``occtrain`` command: argument parsing only; the work happens in the library.

One module here per command (or group: ``data``, ``config``, ``score``), each with
``register(subparsers)``; the commands' bodies live in ``commands/`` and below."""

from __future__ import annotations

import argparse
import re
import sys

from occtrain.cli import config as cli_config
from occtrain.cli import dashboard as cli_dashboard
from occtrain.cli import data as cli_data
from occtrain.cli import drive as cli_drive
from occtrain.cli import evaluate as cli_evaluate
from occtrain.cli import plan_memory as cli_plan_memory
from occtrain.cli import report as cli_report
from occtrain.cli import run as cli_run
from occtrain.cli import score as cli_score
from occtrain.cli import table as cli_table
from occtrain.errors import OcctrainError
from occtrain.version import __version__

#: The commands, in the order ``occtrain --help`` lists them: each module registers its
#: own arguments (``register(subparsers)``) and loads its body when it runs, so that
#: parsing (and ``--help``) imports neither torch nor Lightning.
COMMANDS = (
    cli_run,
    cli_evaluate,
    cli_plan_memory,
    cli_table,
    cli_config,
    cli_drive,
    cli_data,
    cli_score,
    cli_report,
    cli_dashboard,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="occtrain", description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"occtrain {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.register(sub)
    return parser


_WORKER_ERROR = re.compile(r"^occtrain\.errors\.\w+Error: (.*)$", re.MULTILINE)


def _one_line(err: OcctrainError) -> str:
    """The user-facing line of an error, also when it crossed a DataLoader worker."""
    # The message alone: a library that appends context to an exception's args (webdataset
    # adds its stream and url) would otherwise print as a tuple.
    text = err.args[0] if err.args and isinstance(err.args[0], str) else str(err)
    found = _WORKER_ERROR.findall(text)
    return found[-1] if found else text.splitlines()[0] if text else type(err).__name__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Overrides may come after options too (`run R --only x a.b=1`): argparse's positional
    # list stops at the first option, so the rest arrive as extras.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if not hasattr(args, "overrides") or any(e.startswith("-") for e in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*(args.overrides or []), *extra]
    from occtrain.allocator import keep_freed_memory
    from occtrain.run.control import Interrupted

    keep_freed_memory()  # before anything allocates a tensor (occtrain.allocator says why)
    try:
        return int(args.func(args) or 0)
    except Interrupted as stop:
        print(f"interrupted: {stop}", file=sys.stderr)
        return stop.exit_code
    except OcctrainError as err:
        print(f"error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

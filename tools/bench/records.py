"""What a benchmark measured, kept as a record the performance page is generated from.

A benchmark prints its figures as it always has and hands them to ``record``: rows of what
was compared and what was measured, the text made from the measured values. When
``OCCTRAIN_BENCH_RECORDS`` names a folder (``tools/performance_page.py measure`` sets it),
``record`` also writes them there as ``<name>.json`` (``OCCTRAIN_BENCH_NAME``, or one made
from the command), stamped with the command that
reruns it, the code, the day, the machine and how busy the machine was while it ran (the
1-minute load average when the benchmark started and when it recorded): the figures of a
benchmark that shared its cores are read as such.
"""

from __future__ import annotations

import datetime
import os
import platform
import re
import shlex
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, TypedDict

from occtrain.data.validate import Len

REPO = Path(__file__).resolve().parents[2]
ENV = "OCCTRAIN_BENCH_RECORDS"
NAME_ENV = "OCCTRAIN_BENCH_NAME"  # the record's name, as the page calls it (else from the command)
_LOAD_AT_START = os.getloadavg()[0]  # imported as the benchmark starts


@dataclass(frozen=True)
class Row:
    """One comparison: what ran side by side, and what each measured."""

    what: str
    measured: str


class RowRecord(TypedDict):
    what: str
    measured: str


class Record(TypedDict):
    """A record file as :func:`record` writes it (and ``tools/performance_page.py`` checks it)."""

    command: str
    code: str
    day: str
    machine: str
    torch: str
    #: The 1-minute load average at the benchmark's start and at its end.
    load: Annotated[list[float], Len(2)]
    rows: list[RowRecord]


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _command() -> str:
    script = Path(sys.argv[0]).resolve()
    shown = script.relative_to(REPO) if script.is_relative_to(REPO) else script.name
    return shlex.join(["python", str(shown), *sys.argv[1:]])


def record_name(argv: list[str]) -> str:
    """A record's file name from its command: the script and its arguments, e.g.
    ``data-fingerprint`` for ``data.py fingerprint`` (paths by their last two parts)."""
    parts = [Path(argv[0]).stem]
    for arg in argv[1:]:
        arg = "/".join(Path(arg).parts[-2:]) if "/" in arg else arg
        parts.append(re.sub(r"[^\w.]+", "_", arg.lstrip("-")))
    return "-".join(p for p in parts if p)


def record(rows: list[Row]) -> Path | None:
    """Write ``rows`` to the records folder, if one is set; the file written."""
    folder = os.environ.get(ENV)
    if not folder:
        return None
    import torch

    from occtrain.formats.io import atomic_write_json
    from occtrain.version import code_version

    stamp = {
        "command": _command(),
        "code": code_version(),
        "day": datetime.datetime.now(datetime.UTC).date().isoformat(),
        "machine": f"{len(os.sched_getaffinity(0))} cores, {_cpu()}",
        "torch": torch.__version__,
        "load": [round(_LOAD_AT_START, 2), round(os.getloadavg()[0], 2)],
    }
    path = Path(folder) / f"{os.environ.get(NAME_ENV) or record_name(sys.argv)}.json"
    return atomic_write_json(path, {**stamp, "rows": [asdict(r) for r in rows]})


__all__ = ["ENV", "NAME_ENV", "Record", "Row", "record", "record_name"]

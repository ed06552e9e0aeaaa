"""The performance page, generated from the benchmarks' records.

    python tools/performance_page.py measure [--only NAME ...] [--records tools/bench/results]
    python tools/performance_page.py page [--records tools/bench/results] [--out docs/performance.md]

``measure`` runs the benchmarks of ``BENCHMARKS`` one after another, each writing its record
(``tools/bench/records.py``) into the records folder; a benchmark whose inputs are missing
(a finished quickstart run in ``runs/quickstart``, the proofs' runs) is skipped and named.
Run it from a checkout where those runs lie, on a machine with nothing else running: each
record keeps the machine's load while it ran.

``page`` writes ``docs/performance.md`` from ``tools/bench/performance.md``: every
``<!-- benchmarks: NAME[,NAME...] -->`` line becomes a table of those records' rows (what ran
side by side, what it measured, the command that reruns it), followed by each record's
stamp (code, day, machine, load). A listed benchmark without a record is said to be not
measured; nothing on the page is typed.

A mistake (a records folder that is not there, a record that is not one, an ``--out`` that
cannot be written) is one line, ``error: ...`` naming the file, with exit status 2, and the
page is left as it was.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "tools" / "bench"
TEMPLATE = BENCH / "performance.md"
RECORDS = BENCH / "results"
PAGE = REPO / "docs" / "performance.md"
sys.path.insert(0, str(BENCH))

from records import ENV, NAME_ENV, Record  # noqa: E402

from occtrain.data.validate import first_problem  # noqa: E402
from occtrain.errors import ConfigError, DataError, OcctrainError  # noqa: E402
from occtrain.formats.io import atomic_write_text, check_output, parse_json  # noqa: E402

MARKER = re.compile(r"^<!-- benchmarks: ([\w.,-]+) -->$", re.M)


@dataclass(frozen=True)
class Benchmark:
    """One command of the page, the name its record takes, and the paths it reads (relative
    to the checkout)."""

    name: str
    command: str
    needs: tuple[str, ...] = ()

    @property
    def argv(self) -> list[str]:
        return shlex.split(self.command)


QUICKSTART = "runs/quickstart"
BENCHMARKS = (
    Benchmark("synthesis", "python tools/bench/data.py --frames 40"),
    Benchmark("fingerprint", "python tools/bench/data.py fingerprint", ("data/quickstart",)),
    Benchmark("transfer", "python tools/bench/data.py transfer", (f"{QUICKSTART}/tokenizer",)),
    Benchmark("shard-bytes", "python tools/bench/data_bytes.py", ("data/quickstart/shards",)),
    Benchmark("overhead", "python tools/bench/overhead.py --steps 30"),
    Benchmark("ddp", "python tools/bench/ddp.py --steps 40"),
    Benchmark("world-model", "python tools/bench/world_model.py"),
    Benchmark("tokenizers", "python tools/bench/tokenizer.py --skip-training"),
    Benchmark("allocator", "python tools/bench/allocator.py", ("data/quickstart",)),
    Benchmark(
        "decode",
        f"python tools/bench/tokenizer.py --decode {QUICKSTART}/tokenizer/export",
        (f"{QUICKSTART}/tokenizer",),
    ),
    Benchmark(
        "generation", f"python tools/bench/generation.py --stage {QUICKSTART}/instruct", (f"{QUICKSTART}/instruct",)
    ),
    Benchmark(
        "stages", "python tools/bench/stages.py --stages tokenizer,pretrain,instruct,planner,distill", (QUICKSTART,)
    ),
    Benchmark("evaluation", "python tools/bench/evaluation.py", (f"{QUICKSTART}/distill",)),
    Benchmark(
        "throughput",
        "python tools/bench/throughput.py recipes/quickstart.yaml --stage pretrain --steps 24 --warmup 8",
        (f"{QUICKSTART}/tokenizer",),
    ),
    Benchmark(
        "occvla", "python tools/bench/occvla.py --stage runs/occvla_proof/stage2 --samples -1", ("runs/occvla_proof",)
    ),
    Benchmark("sparse-planner", "python tools/bench/sparseoccvla.py planner", ("runs/sparseoccvla/planner",)),
    Benchmark("chamfer", "python tools/bench/sparseoccvla.py chamfer"),
    Benchmark(
        "sparse-tokens",
        "python tools/bench/sparseoccvla.py tokens --dense runs/occvla_proof/stage1",
        ("runs/sparseoccvla/stage2", "runs/occvla_proof/stage1"),
    ),
    Benchmark("scale", "python tools/bench/scale.py"),
    Benchmark("suite", "python tools/bench/suite.py"),
)


def measure(records: Path, only: list[str]) -> int:
    env = {**os.environ, ENV: str(records.resolve())}
    chosen = [b for b in BENCHMARKS if not only or b.name in only]
    failed = 0
    for i, bench in enumerate(chosen, 1):
        missing = [p for p in bench.needs if not (REPO / p).exists()]
        if missing:
            print(f"[{i}/{len(chosen)}] skipped {bench.command}: {', '.join(missing)} is missing", flush=True)
            continue
        print(f"[{i}/{len(chosen)}] {bench.command}", flush=True)
        done = subprocess.run([sys.executable, *bench.argv[1:]], cwd=REPO, env={**env, NAME_ENV: bench.name})
        if done.returncode:
            failed += 1
            print(f"  failed (exit {done.returncode}); its record, if any, is the last one it wrote", flush=True)
    return 1 if failed else 0


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def read_record(path: Path) -> Record:
    try:
        rec = parse_json(path.read_bytes())
        problem = first_problem(rec, Record)
    except (OSError, ValueError) as err:
        problem = str(err)
    if problem:
        raise DataError(
            f"{path}: not a benchmark record ({problem}); rerun its benchmark "
            f"(`python tools/performance_page.py measure --only {path.stem}`)"
        )
    return rec


def table(names: list[str], records: Path) -> str:
    """The rows of the named benchmarks' records, then their stamps."""
    rows, stamps, missing = ["| what | measured | command |", "|---|---|---|"], [], []
    for name in names:
        path = records / f"{name}.json"
        if not path.is_file():
            missing.append(name)
            continue
        rec = read_record(path)
        if any(arg.startswith("/") for arg in shlex.split(rec["command"])):
            raise DataError(
                f"{path}: its command names a path of the machine that ran it ({rec['command']}); rerun it "
                "with `python tools/performance_page.py measure` from the checkout, on its runs/"
            )
        for row in rec["rows"]:
            rows.append(f"| {_cell(row['what'])} | {_cell(row['measured'])} | `{rec['command']}` |")
        start, end = rec["load"]
        stamps.append(
            f"- `{rec['command']}`: code {rec['code']}, measured {rec['day']} on {rec['machine']} "
            f"(torch {rec['torch']}), 1-minute load {start:.1f} at its start and {end:.1f} at its end"
        )
    parts = ["\n".join(rows)] if len(rows) > 2 else []
    parts += ["\n".join(stamps)] if stamps else []
    if missing:
        parts.append("Not measured: " + ", ".join(f"`{m}`" for m in missing) + ".")
    return "\n\n".join(parts)


def render(template: str, records: Path) -> str:
    known = {b.name for b in BENCHMARKS}
    for names in MARKER.findall(template):
        unknown = sorted(set(names.split(",")) - known)
        if unknown:
            raise ConfigError(f"{TEMPLATE}: no benchmark named {', '.join(unknown)} in BENCHMARKS")
    head = (
        "<!-- Generated by `python tools/performance_page.py page` from tools/bench/performance.md and the "
        "benchmarks' records (tools/bench/results/): edit those, not this page. -->\n"
    )
    return head + MARKER.sub(lambda m: table(m.group(1).split(","), records), template)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    m = sub.add_parser("measure", help="run the benchmarks, each writing its record")
    m.add_argument("--only", nargs="*", default=[], metavar="NAME", help="record names, e.g. data-fingerprint")
    m.add_argument("--records", type=Path, default=RECORDS)
    p = sub.add_parser("page", help="write the page from the records")
    p.add_argument("--records", type=Path, default=RECORDS)
    p.add_argument("--out", type=Path, default=PAGE)
    args = parser.parse_args(argv)
    try:
        if args.what == "measure":
            unknown = sorted(set(args.only) - {b.name for b in BENCHMARKS})
            if unknown:
                names = ", ".join(b.name for b in BENCHMARKS)
                raise ConfigError(f"--only: no benchmark named {', '.join(unknown)}; the benchmarks: {names}")
            return measure(args.records, args.only)
        write_page(args.records, args.out)
    except OcctrainError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


def write_page(records: Path, out: Path) -> None:
    if not records.is_dir():
        what = "is a file" if records.exists() else "no such directory"
        raise DataError(f"{records}: {what}; --records takes the folder `measure` writes the records into")
    check_output(out, "--out")
    atomic_write_text(out, render(TEMPLATE.read_text(), records))
    print(f"wrote {out}")


if __name__ == "__main__":
    sys.exit(main())

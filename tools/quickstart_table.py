"""The quickstart's whole-split results over training seeds, from run directories.

    python tools/quickstart_table.py RUN_DIR [RUN_DIR ...]      # e.g. runs of trainer.seed=0, 1, 2

Each RUN_DIR is a finished ``occtrain run recipes/quickstart.yaml`` whose stages were scored
with ``occtrain eval RUN_DIR/STAGE`` (``STAGE/eval/val/metrics.json``); the table prints one
column per run in the order given, the mean and the spread (min to max), and each metric's
baselines on the same samples from the first run. Its first line names the world the evals
were scored on (``eval/val/world.json``), and a run scored on another world than the first
is refused: a table mixes no worlds. Nothing is typed by hand: docs/getting-started.md's table is this
command's output.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Row:
    """One metric of one stage: where it is, how it prints, and what it is set beside."""

    stage: str
    label: str
    key: str
    digits: int = 1
    baselines: tuple[tuple[str, str], ...] = ()  # (label, key)


ROWS = (
    Row(
        "tokenizer",
        "reconstruction mIoU (`occworld`)",
        "occworld_mIoU",
        baselines=(("empty scene", "baseline_free_occworld_mIoU"),),
    ),
    Row(
        "tokenizer",
        "reconstruction IoU (`occworld`)",
        "occworld_IoU",
        baselines=(("empty scene", "baseline_free_occworld_IoU"),),
    ),
    Row("tokenizer", "movable-class mIoU (`occworld`)", "occworld_movable_mIoU", 2),
    Row(
        "pretrain",
        "forecast mIoU at 1 s (`occworld`)",
        "forecast_occworld_mIoU_1s",
        baselines=(
            ("Copy&Paste of the reconstruction", "baseline_copy_reconstruction_forecast_occworld_mIoU_1s"),
            ("copy the scene", "baseline_copy_forecast_occworld_mIoU_1s"),
            ("the scene moved at constant velocity", "baseline_cv_moved_forecast_occworld_mIoU_1s"),
        ),
    ),
    Row(
        "pretrain",
        "forecast movable mIoU at 1 s (`occworld`)",
        "forecast_occworld_movable_mIoU_1s",
        2,
        baselines=(
            ("Copy&Paste of the reconstruction", "baseline_copy_reconstruction_forecast_occworld_movable_mIoU_1s"),
        ),
    ),
    Row(
        "pretrain",
        "direct plan L2 avg (`stp3`, m)",
        "plan_direct_L2_stp3_avg",
        3,
        baselines=(
            ("constant velocity", "baseline_constant_velocity_L2_stp3_avg"),
            ("standing still", "baseline_stationary_L2_stp3_avg"),
        ),
    ),
    Row(
        "instruct",
        "NuScenes-QA accuracy (%)",
        "qa_overall",
        baselines=(("commonest answer per type", "baseline_prior_qa_overall"),),
    ),
    Row(
        "instruct",
        "meta action right (%)",
        "meta_action_overall",
        baselines=(
            ("commonest", "baseline_prior_meta_action_overall"),
            ("repeat the last past one", "baseline_repeat_last_meta_action_overall"),
        ),
    ),
    Row(
        "instruct",
        "plan after the chain of thought, L2 avg (`stp3`, m)",
        "plan_cot_L2_stp3_avg",
        3,
        baselines=(("constant velocity", "baseline_constant_velocity_L2_stp3_avg"),),
    ),
    Row("instruct", "chain of thought CIDEr", "cot_caption_CIDEr", 3),
    Row(
        "planner",
        "head on true meta actions, L2 avg (`stp3`, m)",
        "head_gt_meta_L2_stp3_avg",
        3,
        baselines=(("constant velocity", "constant_velocity_L2_stp3_avg"),),
    ),
    Row(
        "planner",
        "head on generated meta actions, L2 avg (`stp3`, m)",
        "head_generated_meta_L2_stp3_avg",
        3,
        baselines=(("constant velocity", "constant_velocity_L2_stp3_avg"),),
    ),
    Row(
        "distill",
        "student NuScenes-QA accuracy (%)",
        "qa_overall",
        baselines=(("commonest answer per type", "baseline_prior_qa_overall"),),
    ),
    Row("distill", "student meta action right (%)", "meta_action_overall"),
)


def _metrics(run: Path, stage: str) -> dict[str, float]:
    path = run / stage / "eval" / "val" / "metrics.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _world(run: Path) -> tuple[str, str]:
    """The world the run's evals were scored on: its version (what a table may not mix) and
    its key (``eval/val/world.json``; the fingerprint of that copy of the dataset)."""
    versions, keys = set(), set()
    for stage in sorted({r.stage for r in ROWS}):
        path = run / stage / "eval" / "val" / "world.json"
        if path.is_file():
            saved = json.loads(path.read_text())
            versions.add(saved.get("world_version") or "unrecorded")
            keys.add(saved.get("world", "?"))
    return ", ".join(sorted(versions)) or "not scored", ", ".join(sorted(keys)) or "-"


def _stamp(run: Path) -> tuple[str, str, str]:
    """What the run was trained with and when it was scored: code versions, training seeds
    (``manifest.json``), and the date of its latest eval."""
    stages = json.loads((run / "manifest.json").read_text()).get("stages", {})
    code = sorted({e.get("code_version") or "?" for e in stages.values()})
    seeds = sorted({str((e.get("config") or {}).get("trainer", {}).get("seed", "?")) for e in stages.values()})
    evals = [p.stat().st_mtime for p in run.glob("*/eval/val/metrics.json")]
    date = time.strftime("%Y-%m-%d", time.gmtime(max(evals))) if evals else "not scored"
    return ", ".join(code), ", ".join(seeds), date


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table(runs: list[Path]) -> str:
    """The markdown table (see the module docstring); raises SystemExit when the runs' worlds differ."""
    worlds = [_world(run)[0] for run in runs]
    if len(set(worlds)) > 1:
        raise SystemExit(
            f"error: the runs were scored on different worlds ({', '.join(f'{r}: {w}' for r, w in zip(runs, worlds))})"
        )
    scored = {(run, stage): _metrics(run, stage) for run in runs for stage in {r.stage for r in ROWS}}
    stamps = [_stamp(run) for run in runs]
    lines = [
        f"World {worlds[0]}; whole val split (`occtrain eval`). Generated by `python tools/quickstart_table.py` from:",
        "",
        *(
            f"- run {i}: `{run}`, training seed {seed}, code {code}, data key {_world(run)[1]}, scored {date}"
            for i, (run, (code, seed, date)) in enumerate(zip(runs, stamps))
        ),
        "",
        f"| stage | metric | {' / '.join(f'run {i}' for i in range(len(runs)))} | mean (min to max) | baselines (run "
        "0's samples) |",
        "|---|---|---|---|---|",
    ]
    for row in ROWS:
        values = [scored[run, row.stage].get(row.key) for run in runs]
        have = [v for v in values if v is not None]
        if not have:
            continue
        mean = sum(have) / len(have)
        spread = (
            f"{_fmt(mean, row.digits)} ({_fmt(min(have), row.digits)} to {_fmt(max(have), row.digits)})"
            if len(have) > 1
            else "-"
        )
        first = scored[runs[0], row.stage]
        base = (
            "; ".join(f"{label} {_fmt(first.get(key), row.digits)}" for label, key in row.baselines if key in first)
            or "-"
        )
        lines.append(
            f"| {row.stage} | {row.label} | {' / '.join(_fmt(v, row.digits) for v in values)} | {spread} | {base} |"
        )
    return "\n".join(lines) + "\n" + wall_times(runs)


def wall_times(runs: list[Path]) -> str:
    """Each stage's training wall time per run (``manifest.json``: the attempts' sum, not
    counting the world's synthesis and shards, which come before the first stage)."""
    manifests = [json.loads((run / "manifest.json").read_text()).get("stages", {}) for run in runs]
    stages = list(manifests[0])
    if not stages:
        return ""
    lines = [
        "",
        f"| stage | training wall time, s: {' / '.join(f'run {i}' for i in range(len(runs)))} | mean |",
        "|---|---|---|",
    ]
    totals = [0.0] * len(runs)
    for stage in stages:
        times = [m.get(stage, {}).get("wall_time_s") for m in manifests]
        have = [t for t in times if isinstance(t, (int, float))]
        for i, t in enumerate(times):
            totals[i] += t if isinstance(t, (int, float)) else 0.0
        shown = " / ".join("-" if t is None else f"{t:.0f}" for t in times)
        lines.append(f"| {stage} | {shown} | {sum(have) / len(have):.0f} |" if have else f"| {stage} | {shown} | - |")
    lines.append(f"| all stages | {' / '.join(f'{t:.0f}' for t in totals)} | {sum(totals) / len(totals):.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR")
    args = parser.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / "manifest.json").is_file()]
    if missing:
        print(f"error: not a run directory (no manifest.json): {', '.join(missing)}", file=sys.stderr)
        return 2
    print(table(args.runs), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

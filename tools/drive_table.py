"""Planners closed loop and open loop on the same routes, one table.

    python tools/drive_table.py runs/quickstart/planner runs/occllm_proof/instruct ... --out docs/results/driving.md

For each stage given (RUN/STAGE, a drivable stage: a planner, or a world model that plans),
``occtrain drive`` runs on the same routes (skipped when its ``summary.json`` exists), and
the table puts every stage beside the baselines of those routes (the expert, constant
velocity, standing still): open-loop L2 and collision rate on the routes (ST-P3's
convention, the expert driving and every planner planning at each frame), then the
closed-loop driving score (CARLA), PDM score (NAVSIM), route completion and infractions per
route. It ends with whether open-loop L2 orders the drivers as the driving score does
(Kendall's tau over the drivers, scipy's).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from scipy.stats import kendalltau

from occtrain.commands.drive import BASELINES, drive_dir
from occtrain.data.synthesize import FORMAT_VERSION
from occtrain.errors import DataError, OcctrainError
from occtrain.formats.io import atomic_write_text
from occtrain.metrics.closed_loop_scores import TABLE_COLUMNS

COLUMNS = TABLE_COLUMNS


def _fmt(value: float | None, fmt: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value)


def summaries(stages: list[Path], scenes: int, seed: int, seconds: float, drive: bool, workers: int = 1) -> list[dict]:
    """Each stage's ``occtrain drive`` summary, driving it first when there is none."""
    out = []
    for stage in stages:
        path = drive_dir(stage, seed, seconds) / "summary.json"
        if not path.is_file():
            if not drive:
                raise DataError(f"{path} is missing; drive {stage} first (leave out --no-drive)")
            cmd = ["drive", str(stage), "--scenes", str(scenes), "--seed", str(seed), "--seconds", f"{seconds:g}"]
            cmd += ["--workers", str(workers)]
            print("$ occtrain " + " ".join(cmd), file=sys.stderr, flush=True)
            res = subprocess.run([sys.executable, "-m", "occtrain", *cmd])
            if res.returncode:
                raise DataError(f"`occtrain {' '.join(cmd)}` exited {res.returncode}")
        out.append(json.loads(path.read_text()) | {"stage_dir": str(stage)})
    return out


def rows(found: list[dict]) -> list[tuple[str, dict[str, float]]]:
    """(label, scores) for every stage, then the baselines of the first stage's routes."""
    table = [(label(s), s["drivers"][s["stage"]]) for s in found]
    table += [(name, found[0]["drivers"][name]) for name in BASELINES if name in found[0]["drivers"]]
    return table


def rank_agreement(table: list[tuple[str, dict[str, float]]]) -> tuple[float, int]:
    """Kendall's tau between open-loop L2 (lower first) and driving score (higher first), and the drivers counted."""
    pairs = [
        (-s["open_loop_L2_stp3_avg"], s["driving_score"])
        for _, s in table
        if s.get("open_loop_L2_stp3_avg") is not None and not math.isnan(s["open_loop_L2_stp3_avg"])
    ]
    if len(pairs) < 3:
        return float("nan"), len(pairs)
    tau = kendalltau([p[0] for p in pairs], [p[1] for p in pairs]).statistic
    return float(tau), len(pairs)


def _run(summary: dict) -> tuple[str, list[str], list[str]]:
    """The run a stage belongs to: its recipe's name, its training seeds and code versions."""
    manifest = json.loads((Path(summary["stage_dir"]).parent / "manifest.json").read_text())
    entries = manifest.get("stages", {}).values()
    code = sorted({e.get("code_version") or "?" for e in entries})
    seeds = sorted({str((e.get("config") or {}).get("trainer", {}).get("seed", "?")) for e in entries})
    return str(manifest.get("name", "?")), seeds, code


def label(summary: dict) -> str:
    """A row's name: recipe/stage and training seed, never a path on the machine that drove it."""
    recipe, seeds, _ = _run(summary)
    return f"{recipe}/{Path(summary['stage_dir']).name} (seed {', '.join(seeds)})"


def stamp(summary: dict) -> str:
    """Which run a row comes from: its recipe, training seeds and code, the routes, the date driven."""
    stage = Path(summary["stage_dir"])
    recipe, seeds, code = _run(summary)
    version = (summary.get("provenance") or {}).get("world_version") or FORMAT_VERSION
    path = drive_dir(stage, summary["seed"], summary["seconds"]) / "summary.json"
    driven = time.strftime("%Y-%m-%d", time.gmtime(path.stat().st_mtime))
    took = ""
    if "wall_s" in summary and not summary.get("resumed"):
        minutes, seconds = divmod(round(summary["wall_s"]), 60)
        took = f" in {minutes} min {seconds:02d} s by {summary['workers']} worker{'s' * (summary['workers'] > 1)}"
    return (
        f"{label(summary)}: recipe {recipe}, training seed {', '.join(seeds)}, code {', '.join(code)}, "
        f"data the routes of seed {summary['seed']} (world v{version}), scored {driven} (driven{took})"
    )


#: How many of the pairs open-loop L2 and the driving score order apart a page shows.
WIDEST_SWAPS = 5


@dataclass(frozen=True)
class Swap:
    """Two drivers open-loop L2 puts one way and the driving score the other."""

    closer: str  # the lower open-loop L2
    drives_better: str
    l2_gap: float  # metres, >= 0
    score_gap: float  # driving-score points, >= 0


def swapped_pairs(table: list[tuple[str, dict[str, float]]]) -> list[Swap]:
    """The pairs of drivers open-loop L2 puts one way and the driving score the other, the
    widest driving-score gap first."""
    scored = [(label, s) for label, s in table if not math.isnan(s.get("open_loop_L2_stp3_avg", math.nan))]
    out = []
    for i, (a, sa) in enumerate(scored):
        for b, sb in scored[i + 1 :]:
            l2 = sa["open_loop_L2_stp3_avg"] - sb["open_loop_L2_stp3_avg"]
            score = sa["driving_score"] - sb["driving_score"]
            if l2 * score > 0:  # lower L2 should mean a higher driving score
                closer, other = (a, b) if l2 < 0 else (b, a)
                out.append(Swap(closer, other, abs(l2), abs(score)))
    return sorted(out, key=lambda s: -s.score_gap)


def swaps_table(swaps: list[Swap], pairs: int) -> str:
    """How many pairs the two orders disagree on, and the widest few as a table."""
    shown = swaps[:WIDEST_SWAPS]
    head = f"{len(swaps)} of {pairs} pairs are ordered the other way round closed loop"
    head += ":" if len(swaps) <= WIDEST_SWAPS else f"; the {len(shown)} with the widest driving-score gap:"
    lines = [head, "", "| plans closer to the log | drives better | L2 gap (m) | score gap |", "|---|---|---|---|"]
    lines += [f"| {s.closer} | {s.drives_better} | {s.l2_gap:.2f} | {s.score_gap:.1f} |" for s in shown]
    return "\n".join(lines)


def markdown(found: list[dict]) -> str:
    first = found[0]
    routes = {(s["routes"], s["seed"], s["seconds"]) for s in found}
    if len(routes) != 1:
        raise DataError(f"the stages were driven on different routes {sorted(routes)}; drive them alike")
    table = rows(found)
    tau, counted = rank_agreement(table)
    lines = [
        "# Planners closed loop and open loop",
        "",
        f"{first['routes']} routes of {first['seconds']:g} s drawn from seed {first['seed']} (no training world's), "
        "the same for every row. Generated by `python tools/drive_table.py RUN/STAGE ...` over the stages "
        "listed below (`occtrain drive` of each). Driving score: "
        + first["conventions"]["driving_score"]
        + "; PDM score: "
        + first["conventions"]["pdm_score"]
        + ". Infractions per route; open loop: the expert drives, every planner plans at each frame.",
        "",
        *(f"- {stamp(s)}" for s in found),
        "",
        "| driver | " + " | ".join(h for h, _, _ in COLUMNS) + " |",
        "|---|" + "---|" * len(COLUMNS),
    ]
    for label, scores in table:
        lines.append(f"| {label} | " + " | ".join(_fmt(scores.get(k), f) for _, k, f in COLUMNS) + " |")
    if math.isnan(tau):
        verdict = f"Too few drivers with an open-loop L2 ({counted}) to compare the orders."
    else:
        agree = "orders them much as" if tau >= 0.6 else ("partly as" if tau > 0 else "does not order them as")
        verdict = (
            f"Open-loop L2 {agree} the driving score does: Kendall's tau {tau:.2f} over {counted} drivers "
            "(1: the same order, 0: unrelated, -1: reversed)."
        )
        swapped = swapped_pairs(table)
        if swapped:
            verdict += "\n\n" + swaps_table(swapped, counted * (counted - 1) // 2)
    notes = [verdict]
    same = same_drive(table, "constant_velocity", "constant_acceleration")
    if same:
        notes.append(
            "Constant acceleration drives exactly as constant velocity closed loop: it plans from the first "
            "frame, where there is no past move (acceleration 0), and its own constant-speed plans leave it none "
            "after. Open loop, where the expert drove the past, it reads a real acceleration."
        )
    return "\n\n".join(["\n".join(lines), *notes]) + "\n"


def same_drive(table: list[tuple[str, dict[str, float]]], a: str, b: str) -> bool:
    """Whether drivers ``a`` and ``b`` drove alike: the same closed-loop scores and infractions."""
    rows_ = dict(table)
    if a not in rows_ or b not in rows_:
        return False
    keys = [k for _, k, _ in COLUMNS if not k.startswith("open_loop")]
    return all(_alike(rows_[a].get(k), rows_[b].get(k)) for k in keys)


def _alike(x: float | None, y: float | None) -> bool:
    """Equal scores, or both not recorded."""
    missing = [v is None or (isinstance(v, float) and math.isnan(v)) for v in (x, y)]
    if any(missing):
        return all(missing)
    return math.isclose(float(x), float(y), abs_tol=1e-9)  # type: ignore[arg-type]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stages", nargs="+", help="RUN/STAGE directories of drivable stages")
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--workers", type=int, default=1, help="occtrain drive's --workers for stages not yet driven")
    parser.add_argument("--no-drive", action="store_true", help="only tabulate drives that exist")
    parser.add_argument("--out", help="also write the table here (e.g. docs/results/driving.md)")
    args = parser.parse_args()
    try:
        found = summaries(
            [Path(s) for s in args.stages], args.scenes, args.seed, args.seconds, not args.no_drive, args.workers
        )
        table = markdown(found)
    except OcctrainError as err:  # one line and exit 2, as occtrain's own commands
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.out:
        atomic_write_text(Path(args.out), table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

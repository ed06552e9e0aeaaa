"""The four families side by side on one world: OccLLaMA, Occ-LLM, OccVLA and SparseOccVLA.

    python tools/compare_families.py                 # run what is missing, score, print and write the table
    python tools/compare_families.py --no-train      # only score and tabulate finished runs

Each family trains its shipped recipe (``recipes/quickstart.yaml`` is OccLLaMA's) on the
quickstart world through the real CLI (``occtrain run``: done stages are skipped, cut-off
ones resume), every stage the table reads is scored on the whole val split with
``occtrain eval`` (skipped when its ``eval/val/metrics.json`` is newer than its export),
and the table goes to ``runs/families.md`` (and ``.json``). The same val split, the same
metric code and the same conventions for all four: forecast mIoU in the OccWorld
convention over every val clip with a whole 3 s future (camera mask off), plans in ST-P3's
convention, NuScenes-QA accuracy, captions' CIDEr from pycocoevalcap. Step time and peak
resident memory are each stage's training measurement (``metrics.json``), so they are only
comparable between runs on the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from occtrain.core import registry
from occtrain.core.registry import Showcase
from occtrain.core.vocab import scene_length
from occtrain.data.cameras import CAMERA_NAMES
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_json, atomic_write_text
from occtrain.formats.metrics_file import read_metrics
from occtrain.report.results import Run

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Family:
    """A family's row: its name and where its numbers come from (its registration's showcase)."""

    name: str
    showcase: Showcase


#: Every registered family with a showcase, in the registry's order of names.
FAMILIES = tuple(
    Family(spec.paper, spec.showcase) for _, spec in sorted(registry.families().items()) if spec.showcase is not None
)


def _cli(*args: str) -> None:
    print("$ occtrain " + " ".join(args), file=sys.stderr, flush=True)
    res = subprocess.run(
        [sys.executable, "-m", "occtrain", *args], cwd=REPO, env=dict(os.environ, PYTHONWARNINGS="ignore")
    )
    if res.returncode:
        raise SystemExit(f"error: `occtrain {' '.join(args)}` exited {res.returncode}")


def _scored(stage: Path) -> dict[str, float]:
    """The stage's whole-val-split metrics, scoring it first when they are missing, stale or
    of a subset (their provenance says which)."""
    out = stage / "eval" / "val" / "metrics.json"
    export = stage / "export" / "config.json"
    measured = read_metrics(out) if out.is_file() else None
    if (
        measured is None
        or measured.provenance is None
        or measured.provenance.subset
        or out.stat().st_mtime < export.stat().st_mtime
    ):
        _cli("eval", str(stage))
        measured = read_metrics(out)
    return measured.metrics


def _world(stage: Path) -> str:
    """The world version the stage's whole-split eval was scored on (its metrics' provenance)."""
    out = stage / "eval" / "val" / "metrics.json"
    provenance = read_metrics(out).provenance if out.is_file() else None
    return (provenance.world_version if provenance is not None else "") or "unrecorded"


def _tokens_per_frame(stage: Path) -> str:
    """What the LLM reads per frame of scene, from the world model's export."""
    cfg = json.loads((stage / "export" / "config.json").read_text())
    vocab, world = cfg["vocab"], cfg["world"]
    if vocab.get("image"):
        rows, cols = world["occvla"]["image_tokens"]
        cameras = len(CAMERA_NAMES)
        return f"{cameras * rows * cols} image ({cameras} cameras x {rows} x {cols})"
    n = scene_length(vocab["codebook_sizes"], vocab["scene_hw"], int(vocab.get("patch", 0)))
    extra = sum(1 for t in vocab.get("extra", []) if t.startswith("<global_"))
    return f"{n} + {extra} global" if extra else str(n)


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _stage_costs(run: Path) -> str:
    manifest = json.loads((run / "manifest.json").read_text())
    parts = []
    for name, stage in manifest["stages"].items():
        m = stage.get("metrics", {})
        step, rss = m.get("train_step_s"), m.get("train_peak_rss_mb")
        parts.append(f"{name} {_fmt(step and 1e3 * step, 0)} ms / {_fmt(rss, 0)} MB")
    return "; ".join(parts)


def row(family: Family, runs: Path) -> dict:
    show = family.showcase
    run = runs / show.recipe
    out: dict = {
        "family": family.name,
        "recipe": f"recipes/{show.recipe}.yaml",
        "scene": show.note,
        "tokens_per_frame": _tokens_per_frame(run / show.world),
        "costs": _stage_costs(run),
    }
    scored = [s for s in (show.forecast, show.plan, show.qa, show.caption) if s]
    if show.forecast:
        m = _scored(run / show.forecast)
        out["forecast"] = {h: m.get(f"forecast_occworld_mIoU_{h}") for h in ("1s", "2s", "3s")}
        out["copy_forecast"] = {h: m.get(f"baseline_copy_forecast_occworld_mIoU_{h}") for h in ("1s", "2s", "3s")}
        out["forecast_stage"] = show.forecast
    if show.plan:
        m = _scored(run / show.plan)
        p = show.plan_metric
        cv = next(
            (m[k] for k in ("constant_velocity_L2_stp3_avg", "baseline_constant_velocity_L2_stp3_avg") if k in m), None
        )
        out["plan"] = {
            "L2": m.get(f"{p}_L2_stp3_avg"),
            "collision": m.get(f"{p}_collision_stp3_avg"),
            "constant_velocity_L2": cv,
        }
        out["plan_stage"] = show.plan
    if show.qa:
        m = _scored(run / show.qa)
        out["qa"] = m.get("qa_overall")
        out["qa_baseline"] = m.get("baseline_prior_qa_overall")
        out["qa_stage"] = show.qa
    if show.caption:
        m = _scored(run / show.caption)
        out["cider"] = m.get("caption_CIDEr")
        out["cider_baseline"] = m.get("baseline_typical_caption_CIDEr")
        out["caption_stage"] = show.caption
    out["worlds"] = sorted({_world(run / stage) for stage in scored})
    try:
        out["stamp"] = Run.read(run, "val").stamp()
    except DataError as err:
        out["stamp"] = f"not scored ({err})"
    return out


def _cell(value: str, baseline: str, stage: str) -> str:
    return f"{value} vs {baseline} ({stage})"


def markdown(rows: list[dict]) -> str:
    """The comparison, each number beside its trivial baseline on the family's own samples
    (the families' clips differ in how much history they need, so the baselines differ)."""
    horizons = ("1s", "2s", "3s")
    worlds = sorted({w for r in rows for w in r["worlds"]})
    lines = [
        "# Four families on one world",
        "",
        f"World: {', '.join(worlds)} (the version `occtrain data stats` prints; unrecorded: scored before evals "
        "recorded it). Generated by `python tools/compare_families.py` from:",
        "",
        *(f"- {r['family']}: {r.get('stamp', 'not scored')}" for r in rows),
        "",
        "| family (recipe) | LLM tokens per frame of scene | forecast mIoU 1 / 2 / 3 s (`occworld`) vs copying the "
        "current scene "
        "| plan L2 avg (`stp3`) vs constant velocity; collision avg | NuScenes-QA vs commonest answer per type "
        "| caption CIDEr vs the typical caption |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        fc = r.get("forecast")
        forecast = (
            _cell(
                " / ".join(_fmt(fc[h]) for h in horizons),
                " / ".join(_fmt(r["copy_forecast"][h]) for h in horizons),
                r["forecast_stage"],
            )
            if fc
            else "-"
        )
        plan = r.get("plan")
        plans = (
            _cell(
                f"{_fmt(plan['L2'], 2)} m",
                f"{_fmt(plan['constant_velocity_L2'], 2)} m; {_fmt(plan['collision'], 2)} %",
                r["plan_stage"],
            )
            if plan
            else "-"
        )
        qa = (
            _cell(f"{_fmt(r['qa'])} %", f"{_fmt(r['qa_baseline'])} %", r["qa_stage"])
            if r.get("qa") is not None
            else "-"
        )
        cider = (
            _cell(_fmt(r["cider"], 3), _fmt(r["cider_baseline"], 3), r["caption_stage"])
            if r.get("cider") is not None
            else "-"
        )
        lines.append(
            f"| {r['family']} (`{r['recipe']}`) | {r['tokens_per_frame']}: {r['scene']} | {forecast} | {plans} | {qa} "
            f"| {cider} |"
        )
    lines += ["", "| family | per stage: train step (ms) / peak RSS (MB) |", "|---|---|"]
    lines += [f"| {r['family']} | {r['costs']} |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-train", action="store_true", help="only score and tabulate runs that are already done")
    parser.add_argument("--runs", default="runs", help="where the recipes' run directories are (default runs/)")
    parser.add_argument("--out", help="also write the table here (e.g. docs/results/families.md)")
    args = parser.parse_args()
    runs = (REPO / args.runs).resolve()
    for family in FAMILIES:
        if not args.no_train:
            _cli("run", f"recipes/{family.showcase.recipe}.yaml", "--run-dir", str(runs / family.showcase.recipe))
    rows = [row(f, runs) for f in FAMILIES]
    table = markdown(rows)
    atomic_write_json(runs / "families.json", rows)
    atomic_write_text(runs / "families.md", table)
    if args.out:
        atomic_write_text(Path(args.out), table)
    print(table)
    print(f"table -> {runs / 'families.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

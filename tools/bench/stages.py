"""What each stage of a finished run measured of its own training: throughput and MFU.

    python tools/bench/stages.py [--run runs/quickstart] [--stages tokenizer,pretrain,...]

Every stage's ``metrics.json`` carries its training steps' rates (rank zero, the first two
steps of an attempt left out; see the page's "Training throughput"): samples/s, tokens/s
for the world-model stages, step time and model FLOPs over the device's peak (MFU),
counted by formula for the LLM stages and by torch's ``FlopCounterMode`` for the others.
With them, where each stage's time went (``occtrain.stages.phases``): loading, forward,
backward, the optimizer, validation, checkpoints, the export and the first step's excess,
in seconds and as shares of the stage's wall time. This reads them; it trains nothing.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from records import Row, record

from occtrain.stages.phases import PHASES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, default=Path("runs/quickstart"))
    parser.add_argument("--stages", default="", help="comma-separated (default: every stage of the run)")
    args = parser.parse_args()
    manifest = json.loads((args.run / "manifest.json").read_text())
    measured = {
        stage: json.loads(path.read_text())
        for stage in manifest["stages"]
        if (path := args.run / stage / "metrics.json").is_file()
        and (not args.stages or stage in args.stages.split(","))
    }
    codes = sorted({m.get("provenance", {}).get("code_version", "?") for m in measured.values()})
    peak = next(
        (m["train_device_peak_flops_per_s"] for m in measured.values() if "train_device_peak_flops_per_s" in m), 0
    )
    shown = []
    for stage, metrics in measured.items():
        if "train_samples_per_s" not in metrics:
            continue
        parts = [f"{metrics['train_samples_per_s']:.1f} samples/s"]
        if "train_tokens_per_s" in metrics:
            parts.append(f"{metrics['train_tokens_per_s']:,.0f} tokens/s")
        if "train_mfu" in metrics:
            parts.append(f"MFU {100 * metrics['train_mfu']:.1f} %")
        if "train_step_s" in metrics:
            parts.append(f"step {metrics['train_step_s']:.3f} s")
        shown.append(f"{stage} " + ", ".join(parts))
        print(shown[-1])
    where = []
    for stage, metrics in measured.items():
        wall = manifest["stages"][stage].get("wall_time_s")
        phases = {p: metrics[f"{p}_phase_s"] for p in PHASES if f"{p}_phase_s" in metrics}
        if not phases or not wall:
            continue
        parts = [f"{p.replace('_', ' ')} {s:.0f} s ({100 * s / wall:.0f} %)" for p, s in phases.items()]
        where.append(f"{stage} {wall:.0f} s: " + ", ".join(parts))
        print(where[-1])
    what = f"a {manifest['name']} run (its `metrics.json`, trained by code " + ", ".join(codes) + ")"
    rows = [
        Row(
            f"each stage's training steps of {what}",
            "; ".join(shown) + (f" (the MFU's peak: {peak / 1e12:.3f} TFLOP/s)" if peak else ""),
        )
    ]
    if where:
        # The phases overlap nowhere but in the first step's excess (its forward and
        # backward are in theirs too); what they leave of the wall time is the stage's
        # building, data setup and the runner's own work.
        rows.append(Row(f"where each stage's time went in {what}, of its wall time", "; ".join(where)))
    record(rows)


if __name__ == "__main__":
    main()

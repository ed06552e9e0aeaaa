"""A GPU check, ready to run whenever a GPU is lent: the quickstart's stages on the GPU, then a
~1B-parameter Llama world-model stage in bf16, eager, compiled, and sharded by FSDP2 on one
rank, with tokens/s and MFU against this file's own dense bf16 peaks. About 6 minutes on one
H100 or H200 (8 at most).

    python tools/bench/gpu_check.py [--out DIR] [--steps 16] [--skip-quickstart]

1. The quickstart recipe at a few steps a stage on a small world (``trainer.accelerator=gpu
   trainer.precision=bf16-mixed``): that every stage trains, validates and exports on the
   GPU, each stage's step time, tokens/s and MFU as its step meter measured them.
2. ``tools/bench/throughput.py``'s measurement of that run's pretrain stage with its LLM
   replaced by a Llama of Llama 3.2 1B's shape (``--size 1b``), ``--steps`` steps after a
   warm-up, bf16-mixed: eager, compiled (``trainer.compile``) and FSDP2 (``trainer.strategy=
   fsdp`` on one rank). MFU is the model FLOPs per second the step meter counts
   (``models.flops``) over ``DENSE_BF16_TFLOPS`` of the card the CUDA driver names.

Its rows go to the performance page's records as every benchmark's do (``records.record``);
no test depends on it. Without a GPU it says so in one line and exits 2.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from records import REPO, Row, record

#: Dense bf16 tensor-core peaks (TFLOP/s, no sparsity) of the cards a check may meet, from
#: NVIDIA's data sheets: the H200 is the H100 SXM's GH100 with more and faster memory.
DENSE_BF16_TFLOPS = {
    "H200": 989.4,
    "H100 SXM": 989.4,
    "H100 80GB HBM3": 989.4,  # what the driver calls an H100 SXM5
    "H100 NVL": 835.5,
    "H100 PCIe": 756.5,
}
#: Steps a quickstart stage takes here: enough to train, validate and export once.
QUICK_STEPS = {"tokenizer": 60, "pretrain": 40, "instruct": 40, "planner": 200, "distill": 40}


def card_peak(name: str) -> float | None:
    """The dense bf16 peak (FLOP/s) of the card the driver names ``name``, None if unknown."""
    for key, tflops in DENSE_BF16_TFLOPS.items():
        if key.lower() in name.lower():
            return tflops * 1e12
    return None


def quickstart(root: Path) -> dict[str, dict]:
    """The quickstart at ``QUICK_STEPS`` on the GPU; each stage's step meter figures."""
    overrides = [
        f"data.root={root / 'world'}",
        "data.synth.train_scenes=4",
        "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=24",
        "trainer.accelerator=gpu",
        "trainer.precision=bf16-mixed",
    ]
    for i, steps in enumerate(QUICK_STEPS.values()):
        overrides += [f"stages[{i}].trainer.max_steps={steps}", f"stages[{i}].trainer.val_check_interval={steps}"]
    run = root / "run"
    command = [sys.executable, "-m", "occtrain", "run", "recipes/quickstart.yaml", *overrides, "--run-dir", str(run)]
    start = time.perf_counter()
    subprocess.run(command, cwd=REPO, check=True)
    took = time.perf_counter() - start
    manifest = json.loads((run / "manifest.json").read_text())
    out = {"_wall_s": {"wall": took}}
    for stage, entry in manifest["stages"].items():
        metrics = entry.get("metrics", {})
        out[stage] = {k: metrics[k] for k in ("train_step_s", "train_tokens_per_s", "train_mfu") if k in metrics}
    return out


def llm_1b(run: Path, steps: int, peak: float | None) -> dict[str, dict[str, float]]:
    """The pretrain stage with a 1B Llama: eager, compiled, FSDP2 on one rank (bf16-mixed)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from throughput import measure, variant_overrides

    common = ["trainer.accelerator=gpu", "trainer.precision=bf16-mixed", "stages.pretrain.data.batch_size=8"]
    variants = {
        "eager": variant_overrides("pretrain", False, False, "1b"),
        "compiled": variant_overrides("pretrain", True, False, "1b"),
        "FSDP2, 1 rank": [*variant_overrides("pretrain", False, False, "1b"), "trainer.strategy=fsdp"],
    }
    out = {}
    for name, overrides in variants.items():
        m = measure(str(REPO / "recipes" / "quickstart.yaml"), "pretrain", run, [*common, *overrides], steps, 4)
        flops = m.get("train_model_flops_per_s")
        own = flops / peak if flops and peak else float("nan")
        out[name] = {**m, "mfu_own_peak": own}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="keep the quickstart run here (default: a temp dir)")
    parser.add_argument("--steps", type=int, default=16, help="measured steps of the 1B stage per variant")
    parser.add_argument("--skip-quickstart", action="store_true", help="reuse --out's run")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print("error: no CUDA device here; run tools/bench/gpu_check.py on a machine with a GPU", file=sys.stderr)
        return 2
    name = torch.cuda.get_device_name(0)
    peak = card_peak(name)
    root = args.out or Path(tempfile.mkdtemp(prefix="occtrain-gpu-check-"))
    rows = []
    if not args.skip_quickstart:
        stages = quickstart(root)
        wall = stages.pop("_wall_s")["wall"]
        per = "; ".join(
            f"{s} {m.get('train_step_s', float('nan')):.3f} s/step, {m.get('train_tokens_per_s', float('nan')):,.0f} "
            f"tokens/s, MFU {100 * m.get('train_mfu', float('nan')):.1f} %"
            for s, m in stages.items()
        )
        rows.append(
            Row(f"the quickstart's five stages on one {name}, bf16-mixed, a few steps each", f"{wall:.0f} s; {per}")
        )
        print(rows[-1].measured)
    measured = llm_1b(root / "run", args.steps, peak)
    shown = []
    for variant, m in measured.items():
        tps, own = m.get("train_tokens_per_s", float("nan")), 100 * m["mfu_own_peak"]
        shown.append(
            f"{variant} {tps:,.0f} tokens/s, MFU {own:.1f} % of {peak / 1e12 if peak else float('nan'):.0f} TFLOP/s"
        )
    rows.append(
        Row(
            f"the pretrain stage with a 1B Llama (Llama 3.2 1B's shape) on one {name}, bf16-mixed, batch 8, "
            f"{args.steps} steps after 4 of warm-up: eager vs compiled vs FSDP2 on one rank",
            "; ".join(shown),
        )
    )
    print(rows[-1].measured)
    os.environ.setdefault("OCCTRAIN_BENCH_NAME", "gpu_check")
    record(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

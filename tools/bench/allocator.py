"""The quickstart tokenizer's training step with freed memory kept (``occtrain.allocator``)
against glibc's defaults, side by side.

    python tools/bench/allocator.py [--data data/quickstart] [--steps 10] [--pairs 3]

Each measurement is a fresh process (the allocator's settings are the process's): the
quickstart's tokenizer (``configs/model/occllama_tokenizer_small.yaml``) and its batch of 2
train frames of ``--data``, 2 threads, 2 warm-up steps, then ``--steps`` timed steps
(forward, backward, AdamW). The two settings alternate, kept / defaults, ``--pairs`` times,
and each pair gives a ratio, so a machine whose speed drifts moves both alike. Also each
process's system CPU seconds (page faults are system time) and peak resident memory.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

from records import REPO, Row, record

PROBE = """
import resource, sys, time, torch
from occtrain.allocator import keep_freed_memory
keep_freed_memory()
from omegaconf import OmegaConf
from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.data.layout import DatasetIndex
from occtrain.families.occllama import OccLLaMATokenizerConfig
torch.set_num_threads(2)
torch.manual_seed(0)
raw = OmegaConf.load("configs/model/occllama_tokenizer_small.yaml")
cfg = OmegaConf.merge(OmegaConf.structured(OccLLaMATokenizerConfig), raw.occllama_tokenizer)
model = build_tokenizer("occllama_tokenizer", cfg)
opt = torch.optim.AdamW(model.parameters(), 1e-3)
index = DatasetIndex.open(sys.argv[1])
samples = list(index.samples("train"))[::37][:2]
x = torch.stack([torch.from_numpy(index.labels(s, t)["semantics"]).long() for s, t in samples])
def step():
    model(x).losses["loss"].backward(); opt.step(); opt.zero_grad()
for _ in range(2):
    step()
n = int(sys.argv[2])
start = time.perf_counter()
for _ in range(n):
    step()
took = (time.perf_counter() - start) / n
usage = resource.getrusage(resource.RUSAGE_SELF)
print(took, usage.ru_stime, usage.ru_maxrss / 1024)
"""


def probe(data: Path, steps: int, kept: bool) -> tuple[float, float, float]:
    env = {**os.environ, "OCCTRAIN_MALLOC": "" if kept else "system"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(data), str(steps)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
        cwd=REPO,
    )
    seconds, system, mib = out.stdout.split()
    return float(seconds), float(system), float(mib)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO / "data" / "quickstart")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--pairs", type=int, default=3)
    args = parser.parse_args()
    kept, system = [], []
    for i in range(args.pairs):
        kept.append(probe(args.data, args.steps, True))
        system.append(probe(args.data, args.steps, False))
        print(f"pair {i + 1}: kept {kept[-1][0]:.3f} s/step, glibc's defaults {system[-1][0]:.3f} s/step")
    ratios = [k[0] / s[0] for k, s in zip(kept, system, strict=True)]
    med = statistics.median
    text = (
        f"kept {med(k[0] for k in kept):.3f} s/step, defaults {med(s[0] for s in system):.3f} s/step: "
        f"ratio {med(ratios):.2f} (pairs {min(ratios):.2f}-{max(ratios):.2f}); system CPU "
        f"{med(k[1] for k in kept):.1f} vs {med(s[1] for s in system):.1f} s a process; peak RSS "
        f"{med(k[2] for k in kept):.0f} vs {med(s[2] for s in system):.0f} MiB"
    )
    print(text)
    record(
        [
            Row(
                f"the quickstart tokenizer's training step (batch 2, 2 threads, {args.steps} steps a process, "
                f"{args.pairs} pairs): freed memory kept (occtrain.allocator) vs glibc's defaults",
                text,
            )
        ]
    )


if __name__ == "__main__":
    main()

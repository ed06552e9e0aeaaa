"""Where a scene tokenizer's movable voxels go: train an OccLLaMA tokenizer variant on the
train frames for a few hundred steps, then print its reconstruction per class on the val
frames and, for the moving classes, what their voxels come back as.

    python tools/diagnose/tokenizer_classes.py '{"class_balance": 0.5}' --steps 300

The first argument overrides ``configs/model/occllama_tokenizer_tiny.yaml`` (JSON). It is
the experiment behind "Switches beyond the papers" (docs/families/occllama.md): it trains outside the runner (no
checkpoints, no run directory) so that variants compare on the same frames and steps.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from omegaconf import OmegaConf

from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.data.frames import frames_batch
from occtrain.data.layout import DatasetIndex
from occtrain.families.occllama import OccLLaMATokenizerConfig
from occtrain.formats.occ3d import CLASS_INDEX, CLASS_NAMES, MOVABLE_CLASSES, NUM_CLASSES
from occtrain.metrics.occupancy import OccupancyMetric


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="?", default="{}", help="JSON settings over the tiny config")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--data", default="data/quickstart")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    base = OmegaConf.to_container(OmegaConf.load("configs/model/occllama_tokenizer_tiny.yaml")["occllama_tokenizer"])
    cfg = OmegaConf.merge(OmegaConf.structured(OccLLaMATokenizerConfig), {**base, **json.loads(args.overrides)})
    model = build_tokenizer("occllama_tokenizer", cfg)
    index = DatasetIndex.open(args.data)
    train = [(s, t) for s in index.splits["train"] for t in index.scenes[s]]
    val = [(s, t) for s in index.splits["val"] for t in index.scenes[s]][::2]
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=0.0)
    # Warm-up then cosine, as the tokenizer stage's schedule.
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / 20) * 0.5 * (1 + np.cos(np.pi * min(s, args.steps) / args.steps))
    )
    rng = np.random.default_rng(args.seed)
    start = time.time()
    for step in range(args.steps):
        pick = [train[i] for i in rng.choice(len(train), 2, replace=False)]
        loss = model(frames_batch(index, pick)["semantics"].long()).losses["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 50 == 0:
            print(f"step {step}/{args.steps}: loss {float(loss):.3f}, {time.time() - start:.0f} s", flush=True)
    model.eval()
    metric = OccupancyMetric(convention="occworld", subsets={"movable": MOVABLE_CLASSES})
    confusion = torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.long)
    with torch.no_grad():
        for i in range(0, len(val), 4):
            sem = frames_batch(index, val[i : i + 4])["semantics"].long()
            pred = model.decode(model.encode(sem)).argmax(1)
            metric.update(pred, sem)
            confusion += torch.bincount((sem * NUM_CLASSES + pred).reshape(-1), minlength=NUM_CLASSES**2).view(
                NUM_CLASSES, NUM_CLASSES
            )
    r = metric.compute()
    print(
        f"{args.overrides}, {args.steps} steps: mIoU {float(r['mIoU']):.1f}, IoU {float(r['IoU']):.1f}, "
        f"movable mIoU {float(r['movable_mIoU']):.1f} (occworld, {len(val)} val frames)"
    )
    print("per class:", ", ".join(f"{k} {float(v):.1f}" for k, v in r["per_class"].items()))
    for name in ("car", "bus", "truck", "trailer", "pedestrian"):
        row = confusion[CLASS_INDEX[name]]
        top = row.argsort(descending=True)[:3]
        print(
            f"  {name} voxels come back as: "
            + ", ".join(f"{CLASS_NAMES[t]} {100 * float(row[t]) / max(1, int(row.sum())):.1f} %" for t in top)
        )


if __name__ == "__main__":
    main()

"""The two scene tokenizers side by side: step time and peak memory at paper size, and
reconstruction quality after the same training budget.

    python tools/bench/tokenizer.py [--steps 120] [--skip-training]

1. For each tokenizer at its paper-size default config (OccWorld VQ-VAE: 14.17 M params,
   50x50 latent; OccLLaMA: K=2048, 50x50x256), one forward + backward at 200x200x16, batch
   1, in a fresh process each: wall time and peak resident memory (goal <= 4 GB).
2. Unless ``--skip-training``: ``recipes/ablations/tokenizer_decoupled_vs_vqvae.yaml`` with
   ``--steps`` steps per tokenizer, and the reconstruction mIoU/IoU (OccWorld convention)
   each reaches on the val split.
3. With ``--decode EXPORT --data ROOT``: decoding a trained tokenizer's codes of every val
   frame to labels, the argmax of the full class scores (``decode``) vs ``decode_labels``,
   alternating per batch of 8; the labels compared voxel by voxel.

    python tools/bench/tokenizer.py --decode runs/quickstart/tokenizer/export --data data/quickstart
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from records import Row, record

REPO = Path(__file__).resolve().parents[2]

PROBE = """
import resource, time, torch
from omegaconf import OmegaConf
from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.families.occllama import OccLLaMATokenizerConfig
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAEConfig
from occtrain.models import count_parameters
torch.set_num_threads(2)
arch = "{arch}"
cfg = OmegaConf.structured(OccWorldVQVAEConfig if arch == "occworld_vqvae" else OccLLaMATokenizerConfig)
model = build_tokenizer(arch, cfg)
x = torch.randint(0, 18, (1, 200, 200, 16))
model(x).losses["loss"].backward()  # warm-up
start = time.perf_counter()
model(x).losses["loss"].backward()
took = time.perf_counter() - start
print(count_parameters(model), took, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20)
"""


def probe(arch: str) -> tuple[int, float, float]:
    out = subprocess.run([sys.executable, "-c", PROBE.format(arch=arch)], capture_output=True, text=True, check=True)
    params, seconds, gib = out.stdout.split()
    return int(params), float(seconds), float(gib)


def train(steps: int) -> dict[str, dict]:
    with tempfile.TemporaryDirectory() as tmp:
        overrides = []
        for i in range(2):
            overrides += [f"stages[{i}].trainer.max_steps={steps}", f"stages[{i}].trainer.val_check_interval={steps}"]
        cmd = [
            sys.executable,
            "-m",
            "occtrain",
            "run",
            "recipes/ablations/tokenizer_decoupled_vs_vqvae.yaml",
            *overrides,
            "--run-dir",
            tmp,
        ]
        subprocess.run(cmd, cwd=REPO, check=True, capture_output=True)
        manifest = json.loads((Path(tmp) / "manifest.json").read_text())
        return {
            name: {**entry["metrics"], "wall_s": entry["wall_time_s"]} for name, entry in manifest["stages"].items()
        }


def decode(export: Path, data: Path, threads: int = 2) -> None:
    import time

    import torch

    from occtrain.core.tokenizer_exports import load_tokenizer
    from occtrain.data.frames import frames_batch
    from occtrain.data.layout import DatasetIndex

    torch.set_num_threads(threads)
    model = load_tokenizer(export).eval()
    index = DatasetIndex.open(data)
    frames = [(scene, token) for scene in index.splits["val"] for token in index.scenes[scene]]
    seconds = {"decode().argmax(1)": 0.0, "decode_labels": 0.0}
    differing = voxels = 0
    with torch.no_grad():
        for i in range(0, len(frames), 8):
            codes = model.encode(frames_batch(index, frames[i : i + 8], cameras=False)["semantics"].long())
            start = time.perf_counter()
            full = model.decode(codes).argmax(1)
            seconds["decode().argmax(1)"] += time.perf_counter() - start
            start = time.perf_counter()
            labels = model.decode_labels(codes)
            seconds["decode_labels"] += time.perf_counter() - start
            differing += int((full != labels).sum())
            voxels += full.numel()
    for name, took in seconds.items():
        print(f"{name:20s} {len(frames)} val frames: {took:6.2f} s, {took / len(frames) * 1e3:6.1f} ms per scene")
    ratio = seconds["decode().argmax(1)"] / seconds["decode_labels"]
    print(f"decode_labels is {ratio:.2f}x faster; {differing} of {voxels:,} voxels differ")
    per_scene = {k: 1e3 * v / len(frames) for k, v in seconds.items()}
    record(
        [
            Row(
                f"decoding a trained tokenizer's codes of the {len(frames)} val frames to labels, batches of 8, "
                f"{threads} threads: the argmax of the full class scores vs `decode_labels` (the semantics head read "
                "only where the status head says occupied)",
                f"{per_scene['decode().argmax(1)']:.0f} vs {per_scene['decode_labels']:.0f} ms per scene "
                f"({ratio:.2f}x); {differing} of {voxels:,} voxels differ",
            )
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--skip-training", action="store_true")
    parser.add_argument("--decode", type=Path, help="a tokenizer export: time decoding to labels, nothing else")
    parser.add_argument("--data", type=Path, default=REPO / "data" / "quickstart")
    args = parser.parse_args()
    if args.decode:
        decode(args.decode, args.data)
        return
    probed = []
    for arch in ("occworld_vqvae", "occllama_tokenizer"):
        params, seconds, gib = probe(arch)
        probed.append(f"{arch} ({params / 1e6:.2f} M) {seconds:.1f} s, {gib:.2f} GiB")
        print(
            f"{arch:20s} paper size: {params / 1e6:6.2f} M params, fwd+bwd batch 1 {seconds:5.2f} s, peak RSS "
            f"{gib:.2f} GiB"
        )
    rows = [
        Row(
            "the two scene tokenizers at paper size (200 x 200 x 16), one forward and backward at batch 1 in a fresh "
            "process each: wall time and peak RSS",
            "; ".join(probed) + " (goal <= 4 GB)",
        )
    ]
    if not args.skip_training:
        trained = train(args.steps)
        for name, m in trained.items():
            print(
                f"{name:20s} after {args.steps} steps ({m['wall_s']:.0f} s): val occworld mIoU "
                f"{m['val/occworld_mIoU']:.1f}, "
                f"IoU {m['val/occworld_IoU']:.1f}; occ3d mIoU {m['val/occ3d_mIoU']:.1f}"
            )
        rows.append(
            Row(
                f"both tokenizers after {args.steps} steps of "
                "`recipes/ablations/tokenizer_decoupled_vs_vqvae.yaml`: val reconstruction, `occworld` convention",
                "; ".join(f"{n} mIoU {m['val/occworld_mIoU']:.1f} ({m['wall_s']:.0f} s)" for n, m in trained.items()),
            )
        )
    record(rows)


if __name__ == "__main__":
    main()

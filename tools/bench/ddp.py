"""CPU DDP throughput: the tokenizer stage with 1 process vs 2 gloo processes on the same cores.

    python tools/bench/ddp.py [--steps 40]

Runs ``recipes/tokenizer.yaml`` (OccLLaMA's tokenizer at quickstart size, batch 2 per
process) through the real CLI twice, back to back, and prints training samples/s of each
from the manifest's wall time (which includes validation and checkpoints, identical in
both) and their ratio.
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


def samples_per_s(devices: int, steps: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "occtrain",
            "run",
            "recipes/tokenizer.yaml",
            f"trainer.devices={devices}",
            f"trainer.strategy={'ddp' if devices > 1 else 'auto'}",
            f"stages[0].trainer.max_steps={steps}",
            f"stages[0].trainer.val_check_interval={steps}",
            "stages[0].trainer.limit_val_batches=1",
            "--run-dir",
            tmp,
        ]
        subprocess.run(cmd, cwd=REPO, check=True, capture_output=True)
        manifest = json.loads((Path(tmp) / "manifest.json").read_text())
        wall = manifest["stages"]["tokenizer"]["wall_time_s"]
        batch = 2  # configs/data/quickstart.yaml's batch size, per process
        return steps * batch * devices / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    one = samples_per_s(1, args.steps)
    two = samples_per_s(2, args.steps)
    print(
        f"tokenizer stage, {args.steps} steps: 1 process {one:.2f} samples/s, 2 DDP processes {two:.2f} samples/s "
        f"-> {two / one:.2f}x"
    )
    record(
        [
            Row(
                f"the tokenizer stage ({args.steps} steps, batch 2 a process) in one process vs two DDP processes "
                "over gloo on the same cores, through the CLI",
                f"{one:.2f} vs {two:.2f} samples/s ({two / one:.2f}x)",
            )
        ]
    )


if __name__ == "__main__":
    main()

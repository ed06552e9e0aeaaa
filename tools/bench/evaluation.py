"""What a whole-split evaluation costs a user: ``occtrain eval RUN/STAGE`` of each stage of a
finished run, timed as a user meets it (a fresh process, its imports included).

    python tools/bench/evaluation.py [--run runs/quickstart] [--stages tokenizer,pretrain,...]

Each stage's evaluation runs once, one after another, on the run's val split; the goal is
60 s or less for each quickstart stage. The stages' scores are rewritten as they were (the
same export, the same split).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from records import Row, record

STAGES = "tokenizer,pretrain,instruct,planner,distill"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, default=Path("runs/quickstart"))
    parser.add_argument("--stages", default=STAGES)
    args = parser.parse_args()
    seconds = {}
    for stage in args.stages.split(","):
        start = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "occtrain", "eval", str(args.run / stage)], check=True, stdout=subprocess.DEVNULL
        )
        seconds[stage] = time.perf_counter() - start
        print(f"occtrain eval {args.run / stage}: {seconds[stage]:.0f} s", flush=True)
    record(
        [
            Row(
                f"whole-split `occtrain eval` of each stage of a finished {args.run.name} run, a fresh process each "
                "(imports included)",
                ", ".join(f"{stage} {s:.0f} s" for stage, s in seconds.items())
                + f" (goal <= 60 s each; {sum(s > 60 for s in seconds.values())} over)",
            )
        ]
    )


if __name__ == "__main__":
    main()

"""What a world model's plan tokens say: its plans on val clips decoded greedily (the
papers) and by the bins' expected value, beside constant velocity, from one export.

    python tools/diagnose/plan_decoding.py runs/quickstart/pretrain/export [--data data/quickstart]

Prints the first clips' forward waypoints against the truth and each decoding's mean L2
over the six waypoints (every other val clip with a whole 3 s future; a plain mean, not
the ST-P3 or UniAD averages ``occtrain eval`` reports). The export is copied to a
temporary directory for each decoding; the original is not touched.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

import occtrain
from occtrain.core.shared_tasks import known_future
from occtrain.data.clips import frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.models.planning_heads import constant_velocity


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("export", type=Path)
    parser.add_argument("--data", default="data/quickstart")
    parser.add_argument("--show", type=int, default=2, help="clips whose waypoints are printed")
    args = parser.parse_args()
    torch.set_num_threads(2)
    for decoding in ("greedy", "expected"):
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / "export"
            shutil.copytree(args.export, copy)
            config = json.loads((copy / "config.json").read_text())
            config["vocab"]["action_decoding"] = decoding
            (copy / "config.json").write_text(json.dumps(config))
            model = occtrain.load(copy)
            model.clip(args.data)
            index = DatasetIndex.open(args.data)
            clips = list(frame_clips(index, "val", model.engine.tasks.context_frames, 6, partial_history=False))[::2]
            errors, cv_errors = [], []
            for clip in clips:
                truth = known_future(clip)
                if truth is None:
                    continue
                plan = np.asarray(model.plan(clip))[: len(truth)]
                errors.append(np.linalg.norm(plan - truth[: len(plan)], axis=1).mean())
                cv_errors.append(np.linalg.norm(constant_velocity([clip.anchor])[0].numpy() - truth, axis=1).mean())
                if len(errors) <= args.show:
                    print(f"{decoding}: truth x {truth[:, 0].round(1).tolist()}, plan x {plan[:, 0].round(1).tolist()}")
            print(
                f"{decoding}: {len(errors)} clips, mean L2 {np.mean(errors):.2f} m; constant velocity "
                f"{np.mean(cv_errors):.2f} m",
                flush=True,
            )


if __name__ == "__main__":
    main()

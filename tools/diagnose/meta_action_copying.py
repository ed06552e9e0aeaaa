"""Does OccVLA's chain of thought copy its prompt? For every other val clip: the generated
meta action against the truth and against repeating the last past one (which the prompt
lists); whether the generated "History:" sentence equals the reference's; and accuracy
split by whether the generated scene caption names the ego's motion right.

    python tools/diagnose/meta_action_copying.py runs/occvla/stage2/export [--data data/quickstart]
"""

from __future__ import annotations

import argparse
import re
from collections import Counter

import torch

import occtrain
from occtrain.core.scorers import last_past_meta_action
from occtrain.data.clips import frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.data.text_formats import parse_meta_action

HISTORY = re.compile(r"History:[^.]*\.[^.]*\.")
MOTION = re.compile(r"The ego car is (\w+ \w+)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("export")
    parser.add_argument("--data", default="data/quickstart")
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = occtrain.load(args.export)
    engine = model.engine
    model.clip(args.data)
    index = DatasetIndex.open(args.data)
    n = Counter()
    for clip in list(frame_clips(index, "val", engine.tasks.context_frames, 6, partial_history=False))[::2]:
        items = engine.task_items("meta_action", clip)
        if not items:
            continue
        reference = items[0][-1].text
        last = last_past_meta_action(clip, engine.tasks.meta_actions)
        truth = parse_meta_action(reference, last)  # "as before" (tasks.meta_action_prior) is the last one
        text, _ = model.chain_of_thought(clip)
        said = parse_meta_action(text, last)
        history = [HISTORY.search(t) for t in (reference, text)]
        motion = [MOTION.search(t) for t in (reference, text)]
        motion_right = all(motion) and motion[0].group(1) == motion[1].group(1)
        n["clips"] += 1
        n["model right"] += said == truth
        n["repeat-last right"] += last == truth
        n["model says the last one"] += said == last
        n["history sentence copied"] += all(history) and history[0].group(0) == history[1].group(0)
        n["caption motion right"] += motion_right
        n["right, caption motion right"] += motion_right and said == truth
        n["right, caption motion wrong"] += (not motion_right) and said == truth
    for key, value in n.items():
        print(f"{key}: {value}")


if __name__ == "__main__":
    main()

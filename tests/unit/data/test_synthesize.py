"""Writing the synthetic world: the files do not depend on how many processes wrote them,
nor on where an interrupted write resumed."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from occtrain.config import SynthConfig
from occtrain.data.layout import ANNOTATIONS_FILE, FRAMES_DIR
from occtrain.data.synth import generate_scene
from occtrain.data.synth.scene import count_events, scene_events
from occtrain.data.synthesize import FORMAT_CHANGES, FORMAT_VERSION, scene_plan, synthesis_workers, synthesize

CFG = SynthConfig(train_scenes=2, val_scenes=1, frames_per_scene=1, seed=4, camera_height=18, camera_width=32)


def digest(root: Path) -> dict[str, str]:
    return {
        str(f.relative_to(root)): hashlib.sha256(f.read_bytes()).hexdigest() for f in root.rglob("*") if f.is_file()
    }


def test_worker_processes_write_the_files_one_writes_and_resume_an_interrupted_write(tmp_path):
    synthesize(tmp_path / "one", CFG, verbose=False, workers=1)
    one = digest(tmp_path / "one")
    assert any(name.startswith("imgs/") for name in one) and any(name.startswith("gts/") for name in one)
    root = tmp_path / "two"
    synthesize(root, CFG, verbose=False, workers=2)
    assert digest(root) == one
    # As a write killed in the second scene leaves it: no dataset records, no later sidecar.
    (root / ANNOTATIONS_FILE).unlink()
    sidecars = sorted((root / FRAMES_DIR).glob("*.json"))
    assert len(sidecars) == 3
    for sidecar in sidecars[1:]:
        sidecar.unlink()
    synthesize(root, CFG, verbose=False, workers=2)
    assert digest(root) == one


def test_small_worlds_are_written_in_process():
    assert synthesis_workers(99) == 1 and synthesis_workers(560) >= 1


def test_val_scenes_are_drawn_until_they_turn_and_train_scenes_keep_their_seeds():
    cfg = SynthConfig(train_scenes=2, val_scenes=2, frames_per_scene=13, seed=0)
    plan = scene_plan(cfg)
    assert plan == scene_plan(cfg)  # deterministic: a resumed synthesis writes the same scenes
    assert [(name, split) for name, split, _ in plan] == [
        ("scene-0000", "train"),
        ("scene-0001", "train"),
        ("scene-0002", "val"),
        ("scene-0003", "val"),
    ]
    seeds = [seed for *_, seed in plan]
    assert seeds[:2] == [int(np.random.SeedSequence([0, i]).generate_state(1)[0]) for i in range(2)]
    assert len(set(seeds)) == 4
    for seed in seeds[2:]:
        assert scene_events(seed, cfg.frames_per_scene).turns > 0


def test_a_quickstart_length_val_scene_holds_a_turn_a_red_light_stop_and_a_lead():
    cfg = SynthConfig(train_scenes=1, val_scenes=1, frames_per_scene=40, seed=0)
    events = scene_events(scene_plan(cfg)[-1][2], cfg.frames_per_scene)
    assert events.turns > 0 and events.red_stops > 0 and events.leads > 0


def test_the_events_a_val_scene_is_chosen_by_are_those_of_the_scene_written():
    seed = scene_plan(SynthConfig(train_scenes=1, val_scenes=1, frames_per_scene=13, seed=0))[-1][2]
    scene = generate_scene("v", seed, 13)
    written = count_events([(f["command"], f["road"]) for f in scene.frames], scene.ego.speed)
    chosen = scene_events(seed, 13)
    assert (written.turns, written.red_stops) == (chosen.turns, chosen.red_stops) and written.turns > 0
    # The city's parked vehicles lie off the lanes: a lead is a vehicle of the traffic.
    assert written.leads == chosen.leads


def test_the_world_version_says_what_changed():
    assert FORMAT_VERSION == 6 and "road" in FORMAT_CHANGES[6] and "val scenes" in FORMAT_CHANGES[6]

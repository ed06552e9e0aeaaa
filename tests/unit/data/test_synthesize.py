"""Writing the synthetic world: the files do not depend on how many processes wrote them,
nor on where an interrupted write resumed."""

from __future__ import annotations

import hashlib
from pathlib import Path

from occtrain.config import SynthConfig
from occtrain.data.layout import ANNOTATIONS_FILE, FRAMES_DIR
from occtrain.data.synthesize import synthesis_workers, synthesize

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

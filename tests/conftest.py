"""Shared fixtures: tiny hand-built Occ3D datasets and a small synthesized world."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from occtrain.data.layout import DatasetWriter
from occtrain.occ3d import FRAME_DT, FREE, GRID_SHAPE

REPO = Path(__file__).resolve().parents[1]

if os.environ.get("PYTEST_XDIST_WORKER"):
    # The workers (one per core) share the cores: one thread each, for the worker and for
    # the CLI processes it starts, so that they do not oversubscribe them.
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


def hand_labels(seed: int) -> dict[str, np.ndarray]:
    """A plausible label volume: ground, a box of class 4, masks hiding one corner."""
    rng = np.random.default_rng(seed)
    sem = np.full(GRID_SHAPE, FREE, np.uint8)
    sem[:, :, 1] = 11
    x, y = rng.integers(20, 170, size=2)
    sem[x : x + 10, y : y + 5, 2:5] = 4
    cam = np.ones(GRID_SHAPE, np.uint8)
    cam[:50, :50] = 0
    return {"semantics": sem, "mask_lidar": cam.copy(), "mask_camera": cam}


def hand_frames(scene: str, n: int, seed: int) -> list[dict]:
    """Minimal FrameAnnotations of an ego driving straight along +x at 5 m/s."""
    frames = []
    for i in range(n):
        token = hashlib.md5(f"{scene}-{seed}-{i}".encode()).hexdigest()
        fut = [[5.0 * FRAME_DT * (k + 1), 0.0] for k in range(6)]
        mask = [1 if i + k + 1 < n else 0 for k in range(6)]
        frames.append(
            {
                "scene": scene, "token": token, "index": i, "timestamp": int(1e6 * (100 + i * FRAME_DT)),
                "ego_pose": {"translation": [5.0 * FRAME_DT * i, 0.0, 0.0], "yaw": 0.0},
                "ego_speed": 5.0, "ego_accel": 0.0, "ego_yaw_rate": 0.0,
                "command": "go straight", "meta_action": {"speed": "maintain", "direction": "straight"},
                "ego_future": fut, "ego_future_mask": mask,
                "ego_past": [[-5.0 * FRAME_DT * (4 - k), 0.0] for k in range(4)],
                "ego_past_mask": [1 if i - (4 - k) >= 0 else 0 for k in range(4)],
                "boxes": [], "agent_futures": [], "agent_future_mask": [],
                "caption": f"caption {i}", "narration": f"narration {i}",
            }
        )
    return frames


def write_hand_dataset(root: Path, train: int = 2, val: int = 1, frames: int = 12) -> Path:
    writer = DatasetWriter(root, {"generator": "tests", "train": train, "val": val, "frames": frames})
    qs = {"train": [], "val": []}
    for s in range(train + val):
        scene, split = f"scene-{s:04d}", "train" if s < train else "val"
        fr = hand_frames(scene, frames, s)
        for f in fr:
            # The token's own digits, not hash(): str hashes change with every process.
            writer.write_labels(scene, f["token"], hand_labels(int(f["token"][:8], 16) % 1000))
            qs[split].append({"question": "Are there any cars?", "answer": "yes", "sample_token": f["token"], "template_type": "exist", "num_hop": 0})
        writer.write_scene(scene, split, fr)
    writer.finalize(qs)
    return root


@pytest.fixture(scope="session")
def hand_dataset(tmp_path_factory) -> Path:
    return write_hand_dataset(tmp_path_factory.mktemp("hand") / "ds")


@pytest.fixture(scope="session")
def synth_dataset(tmp_path_factory) -> Path:
    """A small synthesized world (2 train + 1 val scenes of 12 frames), shared by the session."""
    from occtrain.config import SynthConfig
    from occtrain.data.synthesize import synthesize

    root = tmp_path_factory.mktemp("synth") / "world"
    synthesize(root, SynthConfig(train_scenes=2, val_scenes=1, frames_per_scene=12, seed=3), verbose=False)
    return root


def built_once(tmp_path_factory, name: str, build: Callable[[Path], Path]) -> Path:
    """``build(folder)`` run once per test session, whichever pytest-xdist worker asks first;
    the others wait for it and share the result, which they must only read. For end-to-end
    reference runs that several test files compare against."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # pytest-N/ holds every worker's
    folder, done = shared / f"built-{name}", shared / f"built-{name}.done"
    with open(shared / f"built-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # a build that failed part-way
            folder.mkdir()
            done.write_text(str(build(folder).relative_to(folder)))
    return folder / done.read_text()


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 300, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run the real ``occtrain`` CLI in a subprocess (``env``: variables to add)."""
    # tests/ on the path so recipes can load test-only plugins (tests/plugins/).
    path = os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]))
    env = dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=path, **(env or {}))
    return subprocess.run(
        [sys.executable, "-m", "occtrain", *args], cwd=cwd or REPO, env=env, capture_output=True, text=True, timeout=timeout
    )


def kill_at_checkpoint(args: list[str], checkpoint: Path, step: int, env: dict[str, str] | None = None, timeout: float = 600) -> int:
    """Start ``occtrain ARGS`` in its own process group, kill it (-9) once ``checkpoint``
    holds ``step`` or later, and return the step the checkpoint holds after the kill."""
    import signal
    import time

    import torch

    path = os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "occtrain", *args], cwd=REPO, env=dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=path, **(env or {})),
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )
    deadline = time.time() + timeout
    while proc.poll() is None and time.time() < deadline:
        if checkpoint.is_file():
            try:
                if torch.load(checkpoint, weights_only=True, map_location="cpu")["global_step"] >= step:
                    break
            except (RuntimeError, OSError, EOFError, KeyError):
                pass  # replaced while reading
        time.sleep(0.02)
    assert proc.poll() is None, f"the run finished (or timed out) before {checkpoint} reached step {step}"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    return torch.load(checkpoint, weights_only=True, map_location="cpu")["global_step"]

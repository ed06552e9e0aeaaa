"""Shared fixtures: tiny hand-built Occ3D datasets and a small synthesized world."""

from __future__ import annotations

import atexit
import fcntl
import hashlib
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from occtrain.data.dataset_writer import DatasetWriter
from occtrain.formats.occ3d import FRAME_DT, FREE, GRID_SHAPE

REPO = Path(__file__).resolve().parents[1]


def load_tool(name: str):
    """``tools/<name>.py`` as a module (the tools are scripts, not a package), registered in
    ``sys.modules`` under ``name``, where dataclasses look their module up."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


if os.environ.get("PYTEST_XDIST_WORKER"):
    # The workers (one per core) share the cores: one thread each, for the worker and for
    # the CLI processes it starts, so that they do not oversubscribe them.
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


#: The files that keep a worker busiest, longest first (seconds of one worker in a full run
#: on 2 cores, `pytest --junitxml`, 2026-11-29: 195, 182, 143, 143, 142, 114, 99, 67, 30,
#: 29, 28, 28, 24, 20, 19). pytest-xdist hands out whole files (``--dist loadfile``) in collection
#: order (``--no-loadscope-reorder``): these go first, so that the two workers finish
#: together. By default it starts with the files holding the most tests, which left these
#: few-test end-to-end files for last and one worker idle for minutes. Files not named here
#: follow in their usual order; a stale entry only costs balance, never a test.
HEAVIEST_FIRST = (
    "e2e/test_sharded.py",
    "e2e/test_pipeline.py",
    "e2e/test_sparseoccvla_recipe.py",
    "e2e/test_occllm_recipe.py",
    "e2e/test_pipeline_faults.py",  # after test_pipeline, whose run it waits for (built_once)
    "e2e/test_distributed.py",
    "e2e/test_occvla_recipe.py",
    "e2e/test_interruptions.py",
    "e2e/test_bad_inputs.py",
    "unit/data/synth/test_synth.py",
    "unit/run/test_runner.py",
    "unit/models/tokenizers/test_tokenizers.py",
    "unit/models/test_compiling.py",  # inductor compiles a decoder layer (about 25 s)
    "unit/stages/test_optim_ddp_step.py",
    "unit/families/occllm/test_msvae.py",
)


def pytest_collection_modifyitems(config, items) -> None:
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}

    def order(item) -> int:
        path = Path(str(item.path)).relative_to(REPO / "tests").as_posix()
        return rank.get(path, len(rank))

    items.sort(key=order)  # stable: each file's tests, and the other files, keep their order


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
                "scene": scene,
                "token": token,
                "index": i,
                "timestamp": int(1e6 * (100 + i * FRAME_DT)),
                "ego_pose": {"translation": [5.0 * FRAME_DT * i, 0.0, 0.0], "yaw": 0.0},
                "ego_speed": 5.0,
                "ego_accel": 0.0,
                "ego_yaw_rate": 0.0,
                "command": "go straight",
                "meta_action": {"speed": "maintain", "direction": "straight"},
                "ego_future": fut,
                "ego_future_mask": mask,
                "ego_past": [[-5.0 * FRAME_DT * (4 - k), 0.0] for k in range(4)],
                "ego_past_mask": [1 if i - (4 - k) >= 0 else 0 for k in range(4)],
                "boxes": [],
                "agent_futures": [],
                "agent_future_mask": [],
                "caption": f"caption {i}",
                "narration": f"narration {i}",
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
            qs[split].append(
                {
                    "question": "Are there any cars?",
                    "answer": "yes",
                    "sample_token": f["token"],
                    "template_type": "exist",
                    "num_hop": 0,
                }
            )
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


def free_port() -> int:
    """A TCP port free on this machine now, for a test's process group to rendezvous on."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _one_thread(rank: int, fn: Callable[..., None], *args) -> None:
    import torch

    torch.set_num_threads(1)
    fn(rank, *args)


def two_ranks(fn: Callable[..., None], *args, timeout: float = 120) -> None:
    """``fn(rank, *args)`` in two processes (for a gloo group of two), waited for; a test
    fails, rather than hangs, when one of them waits for ever in a collective the other
    skipped. Forked from this process, as DataLoader workers are: spawned ones would import
    this test's module, and with it torch, Lightning and occtrain, again (10-20 s of CPU a
    test). Like DataLoader workers, each runs torch on one thread: OpenMP's threads are not
    forked, and a child that reached for them would wait for ever."""
    import torch.multiprocessing as mp

    ctx = mp.start_processes(_one_thread, args=(fn, *args), nprocs=2, join=False, start_method="fork")
    deadline = time.monotonic() + timeout
    while not ctx.join(timeout=1):
        if time.monotonic() > deadline:
            for proc in ctx.processes:
                proc.kill()
            pytest.fail(f"the two processes of {fn.__name__} hung: one waited in a collective the other skipped")


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


def cli_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a test's ``occtrain`` process: tests/ on the path, so recipes can
    load test-only plugins (tests/plugins/), and ``extra`` added."""
    path = os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]))
    return dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=path, **(extra or {}))


#: Set to 1 to start every test's ``occtrain`` process from scratch instead of forking it
#: from the warm parent (tests/cli_zygote.py): slower, and the check that nothing depends on it.
FRESH_PROCESSES = os.environ.get("OCCTRAIN_TEST_FRESH_PROCESSES") == "1"


class CliProcess:
    """One ``occtrain`` process forked by the warm parent, with :class:`subprocess.Popen`'s
    ``pid``, ``poll``, ``wait`` and ``returncode``; its output is read once it has ended."""

    def __init__(self, parent: _WarmParent, pid: int, out: Path, err: Path) -> None:
        self.parent, self.pid, self._out, self._err = parent, pid, out, err
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.parent.exit_code(self.pid, timeout=0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            self.returncode = self.parent.exit_code(self.pid, timeout)
            if self.returncode is None:
                raise subprocess.TimeoutExpired(str(self.pid), timeout or 0)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def output(self) -> tuple[str, str]:
        texts = (self._out.read_text(errors="replace"), self._err.read_text(errors="replace"))
        self._out.unlink(missing_ok=True)
        self._err.unlink(missing_ok=True)
        return texts


class _WarmParent:
    """The client of tests/cli_zygote.py: one per pytest process, started on first use."""

    def __init__(self) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="occtrain-cli-"))
        self.proc = subprocess.Popen(
            [sys.executable, str(REPO / "tests" / "cli_zygote.py")],
            cwd=REPO,
            env=cli_env(),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        self.buffer, self.started, self.exited, self.count = b"", [], {}, 0
        self._read_until(lambda: self.started, timeout=300, what="the warm parent to import occtrain")
        self.started.clear()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def spawn(self, argv: list[str], cwd: Path, env: dict[str, str], session: bool) -> CliProcess:
        self.count += 1
        out, err = self.folder / f"{self.count}.out", self.folder / f"{self.count}.err"
        request = {
            "argv": list(argv),
            "cwd": str(cwd),
            "env": env,
            "stdout": str(out),
            "stderr": str(err),
            "session": session,
        }
        self.proc.stdin.write((json.dumps(request) + "\n").encode())
        self.proc.stdin.flush()
        self._read_until(lambda: self.started, timeout=60, what="a fork")
        return CliProcess(self, self.started.pop(0), out, err)

    def exit_code(self, pid: int, timeout: float | None) -> int | None:
        self._read_until(lambda: pid in self.exited, timeout=timeout, what=None)
        return self.exited.pop(pid, None)

    def _read_until(self, done: Callable[[], bool], timeout: float | None, what: str | None) -> None:
        deadline = None if timeout is None else time.monotonic() + timeout
        fd = self.proc.stdout.fileno()
        while not done():
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([fd], [], [], left)[0]:
                if what:
                    raise RuntimeError(f"timed out waiting for {what}")
                return
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                raise RuntimeError(f"the warm parent of the CLI processes ended (exit code {self.proc.wait()})")
            self.buffer += chunk
            while b"\n" in self.buffer:
                line, self.buffer = self.buffer.split(b"\n", 1)
                answer = json.loads(line)
                if "exited" in answer:
                    self.exited[answer["exited"]] = answer["rc"]
                else:
                    self.started.append(answer.get("started", answer.get("ready")))

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=30)
        shutil.rmtree(self.folder, ignore_errors=True)


class _FreshCliProcess(subprocess.Popen):
    """``occtrain`` started from scratch (FRESH_PROCESSES), with :class:`CliProcess`'s ``output``."""

    def __init__(self, args: list[str], cwd: Path, env: dict[str, str], session: bool, out: Path, err: Path) -> None:
        self._out, self._err = out, err
        with open(out, "w") as stdout, open(err, "w") as stderr:
            super().__init__([sys.executable, "-m", "occtrain", *args], cwd=cwd, env=env, stdout=stdout, stderr=stderr,
                             start_new_session=session)  # fmt: skip

    output = CliProcess.output


_warm_parent: _WarmParent | None = None


def start_cli(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None, session: bool = False, fresh: bool = False
):
    """Start ``occtrain ARGS`` without waiting, forked from the warm parent (a
    :class:`CliProcess`) or, with ``fresh`` or FRESH_PROCESSES, from scratch. ``session``:
    its own session and process group, for ``os.killpg``. ``output()`` reads its stdout
    and stderr once it has ended."""
    global _warm_parent
    if fresh or FRESH_PROCESSES:
        folder = Path(tempfile.mkdtemp(prefix="occtrain-cli-"))
        return _FreshCliProcess(list(args), cwd or REPO, cli_env(env), session, folder / "out", folder / "err")
    if _warm_parent is None or not _warm_parent.alive():
        _warm_parent = _WarmParent()
        atexit.register(_warm_parent.close)
    return _warm_parent.spawn(list(args), cwd or REPO, cli_env(env), session)


def run_cli_process(
    *args: str, cwd: Path | None = None, timeout: float = 300, env: dict[str, str] | None = None, fresh: bool = False
) -> subprocess.CompletedProcess:
    """Run the real ``occtrain`` CLI in another process and wait for it (``env``: variables
    to add); see :func:`start_cli`. Only for tests where the process is the point (DDP,
    torchrun, signals, a fresh clone): the others call :func:`run_cli`."""
    proc = start_cli(*args, cwd=cwd, env=env, session=True, fresh=fresh)
    try:
        code = proc.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise
    out, err = proc.output()
    return subprocess.CompletedProcess(["occtrain", *args], code, out, err)


def run_cli(*args: str, cwd: Path | None = None, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``occtrain ARGS`` in this process, through :func:`occtrain.cli.main`: its exit code,
    stdout and stderr as :func:`run_cli_process` returns them. The working directory (the
    repository unless ``cwd``), the environment (with ``env`` added), ``sys.argv``, torch's
    thread count and determinism flag are restored after it. An exception the CLI lets
    through is raised here, so a traceback fails the test rather than hiding in stderr."""
    import contextlib
    import io

    import torch

    from occtrain.cli import main

    saved_cwd, saved_env, saved_argv = os.getcwd(), dict(os.environ), sys.argv
    saved_threads, saved_deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    out, err = io.StringIO(), io.StringIO()
    try:
        os.chdir(cwd or REPO)
        os.environ.update({"PYTHONWARNINGS": "ignore", **(env or {})})
        sys.argv = ["occtrain", *args]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(args))
            except SystemExit as stop:  # argparse's usage errors
                code = stop.code if isinstance(stop.code, int) else 1
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        sys.argv = saved_argv
        torch.set_num_threads(saved_threads)
        torch.use_deterministic_algorithms(saved_deterministic)
    return subprocess.CompletedProcess(["occtrain", *args], code, out.getvalue(), err.getvalue())


def kill_at_checkpoint(
    args: list[str], checkpoint: Path, step: int, env: dict[str, str] | None = None, timeout: float = 600
) -> int:
    """Start ``occtrain ARGS`` in its own process group, kill it (-9) once ``checkpoint``
    holds ``step`` or later, and return the step the checkpoint holds after the kill."""
    import torch

    proc = start_cli(*args, env=env, session=True)
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

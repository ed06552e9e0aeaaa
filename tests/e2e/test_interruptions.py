"""The runner through the real CLI: kill -9 and resume, CPU DDP with two processes."""

from __future__ import annotations

import json
import os
import signal
import socket
import time

import pytest
import torch
from safetensors.torch import load_file

from conftest import run_cli, run_cli_process, start_cli, write_hand_dataset

pytestmark = pytest.mark.slow

RECIPE = """
name: probe
plugins: [plugins.probe_stage]
runs_root: {runs}
data:
  root: {data}
  batch_size: 2
  samples_per_shard: 4
  history: 1
  future: 1
trainer:
  max_steps: 16
  val_check_interval: 8
  limit_val_batches: 2
  ckpt_every_n_steps: 2
  log_every_n_steps: 1
stages:
  - name: only
    kind: probe
    model: {{width: 6}}
    optim: {{lr: 0.05}}
"""


@pytest.fixture
def recipe(tmp_path):
    data = write_hand_dataset(tmp_path / "ds", train=2, val=1, frames=8)
    path = tmp_path / "probe.yaml"
    path.write_text(RECIPE.format(runs=tmp_path / "runs", data=data))
    return path


#: A quarter of a second per step (tests/plugins/probe_stage.py), to kill a run mid-stage.
SLOW = {"OCCTRAIN_PROBE_STEP_DELAY": "0.25"}


@pytest.mark.parametrize("accumulate", [1, 2])
def test_kill_9_then_resume_gives_the_uninterrupted_weights(recipe, tmp_path, accumulate):
    # Reference: one uninterrupted run, at full speed (the delay changes timing only, not the maths).
    acc = f"trainer.accumulate_grad_batches={accumulate}"
    res = run_cli("run", str(recipe), acc, "--run-dir", str(tmp_path / "ref"))
    assert res.returncode == 0, res.stderr[-2000:]
    reference = load_file(tmp_path / "ref" / "only" / "export" / "model.safetensors")

    run_dir = tmp_path / "cut"
    proc = start_cli("run", str(recipe), acc, "--run-dir", str(run_dir), env=SLOW, session=True)
    last = run_dir / "only" / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if last.is_file() and torch.load(last, weights_only=True, map_location="cpu")["global_step"] >= 4:
            break
        time.sleep(0.1)
    assert proc.poll() is None, "the stage finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    saved_step = torch.load(last, weights_only=True, map_location="cpu")["global_step"]
    assert 4 <= saved_step < 16
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["stages"]["only"]["status"] == "running" and manifest["stages"]["only"]["attempts"] == 1

    # The killed process's lock file stays behind; the kernel dropped its lock with it.
    assert (run_dir / ".lock").read_text().startswith(f"pid {proc.pid} ")
    # And a damaged last.ckpt (a disk error after the fact): the one before it resumes.
    previous_step = torch.load(last.with_name("previous.ckpt"), weights_only=True, map_location="cpu")["global_step"]
    assert 2 <= previous_step < saved_step
    (run_dir / "only" / "checkpoints" / "last.ckpt").write_bytes(b"PK\x03\x04 damaged")
    res = run_cli("run", str(recipe), acc, "--run-dir", str(run_dir), env=SLOW)
    assert res.returncode == 0, res.stderr[-2000:]
    assert (
        "last.ckpt is unreadable" in res.stderr and "resuming only from" in res.stderr and "previous.ckpt" in res.stderr
    )
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["stages"]["only"]["status"] == "done" and manifest["stages"]["only"]["attempts"] == 2
    # The second attempt trained from the checkpoint's step, not from scratch (a restart
    # would give the same weights: training is deterministic).
    assert [h["start_step"] for h in manifest["stages"]["only"]["history"]] == [0, previous_step]
    # Wall time sums the attempts: 16 steps of at least 0.25 s, some before the kill.
    assert manifest["stages"]["only"]["wall_time_s"] >= 16 * 0.25
    assert torch.load(last, weights_only=True, map_location="cpu")["global_step"] == 16
    resumed = load_file(run_dir / "only" / "export" / "model.safetensors")
    assert resumed.keys() == reference.keys()
    for key in reference:
        assert torch.equal(resumed[key], reference[key]), key


def test_a_kill_after_the_last_checkpoint_resumes_to_the_export(recipe, tmp_path):
    """A kill -9 between the final checkpoint and the export (a race the killing tests hit
    at random) leaves a stage 'running' whose checkpoint has finished training: the rerun
    trains nothing, records the step it resumed at and exports the same weights."""
    import shutil

    run_dir = tmp_path / "run"
    res = run_cli("run", str(recipe), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-2000:]
    export = run_dir / "only" / "export"
    reference = load_file(export / "model.safetensors")
    # The state such a kill leaves: the stage still running, its export never written.
    manifest_path = run_dir / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["stages"]["only"]["status"] = "running"
    manifest_path.write_text(json.dumps(manifest))
    shutil.rmtree(export)

    res = run_cli("run", str(recipe), "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-2000:]
    entry = json.loads(manifest_path.read_text())["stages"]["only"]
    assert entry["status"] == "done" and entry["attempts"] == 2
    assert [h["start_step"] for h in entry["history"]] == [0, 16]
    resumed = load_file(export / "model.safetensors")
    assert resumed.keys() == reference.keys() and all(torch.equal(resumed[k], reference[k]) for k in reference)


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stop_signal_interrupts_in_one_line_and_a_rerun_resumes(recipe, tmp_path, sig, code):
    run_dir = tmp_path / "run"
    # 60 steps of 1 s: the stage must still be training after the second run below has
    # started Python and been refused, which takes tens of seconds on a loaded machine
    # (16 steps were too few beside two other pytest workers). The rerun that resumes it
    # goes at full speed.
    steps = 60
    args = [str(recipe), f"trainer.max_steps={steps}", "--run-dir", str(run_dir)]
    proc = start_cli("run", *args, env={"OCCTRAIN_PROBE_STEP_DELAY": "1.0"})
    last = run_dir / "only" / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while not last.is_file() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, "the stage finished before the signal"

    # A second run on the same directory is refused while the first holds it.
    second = run_cli("run", *args)
    assert second.returncode == 2
    assert second.stderr.strip() == (
        f"error: {run_dir} is in use by pid {proc.pid} on {socket.gethostname()}; wait for it to finish, stop it, or "
        "choose another --run-dir"
    )

    assert proc.poll() is None, "the stage finished before the signal"
    proc.send_signal(sig)
    proc.wait(timeout=120)
    _, err = proc.output()
    assert proc.returncode == code, err[-2000:]
    name = signal.Signals(sig).name
    saved_step = torch.load(last, weights_only=True, map_location="cpu")["global_step"]
    assert err.splitlines()[-1] == (
        f"interrupted: stage 'only' of {run_dir} interrupted by {name}; rerun the same command to resume it from "
        f"its checkpoint at step {saved_step} ({last})"
    )
    assert (
        sum(name in line for line in err.splitlines()) == 1
    )  # and nothing else about it (Lightning's "Received SIGTERM")
    assert "Traceback" not in err
    entry = json.loads((run_dir / "manifest.json").read_text())["stages"]["only"]
    assert entry["status"] == "interrupted" and entry["error"] == f"interrupted by {name}" and entry["wall_time_s"] > 0
    assert last.is_file()
    assert 0 < saved_step < steps

    res = run_cli("run", *args)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "resuming only" in res.stderr
    entry = json.loads((run_dir / "manifest.json").read_text())["stages"]["only"]
    assert entry["status"] == "done" and entry["attempts"] == 2
    assert [h["start_step"] for h in entry["history"]] == [0, saved_step]


def test_cpu_ddp_two_processes(recipe, tmp_path):
    res = run_cli_process(
        "run", str(recipe), "trainer.devices=2", "trainer.strategy=ddp", "--run-dir", str(tmp_path / "ddp"), timeout=600
    )
    assert res.returncode == 0, res.stderr[-3000:]
    manifest = json.loads((tmp_path / "ddp" / "manifest.json").read_text())
    assert manifest["stages"]["only"]["status"] == "done" and manifest["stages"]["only"]["attempts"] == 1
    # Two processes, each training on its half of every global batch of 2 (batch_size 2
    # per rank here: 16 steps x 2 samples each) and validating 2 batches of 2.
    (attempt,) = manifest["stages"]["only"]["history"]
    assert attempt["world_size"] == 2 and attempt["start_step"] == 0
    assert attempt["train_samples_per_rank"] == [32, 32]
    assert attempt["val_samples_per_rank"] == [4, 4]
    assert (tmp_path / "ddp" / "only" / "export" / "model.safetensors").is_file()
    assert res.stderr.count("done    only") == 1  # one summary line: only rank zero reports


def test_cli_errors_are_one_line(recipe, tmp_path):
    res = run_cli("run", str(recipe), "trainer.max_step=3")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "error: unknown key 'trainer.max_step' in override 'trainer.max_step=3'; did you mean 'max_steps'?"
    ]
    res = run_cli("run", str(recipe), "stages[0].model.fail=true", "--run-dir", str(tmp_path / "f"))
    assert res.returncode == 2
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("error: stage 'only' failed: RuntimeError: probe exploded (traceback in ")
    missing = tmp_path / "nothing.yaml"
    res = run_cli("run", str(missing))
    assert res.returncode == 2 and res.stderr.strip() == f"error: config file not found: {missing}"

"""The runner through the real CLI: kill -9 and resume, CPU DDP with two processes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from conftest import REPO, run_cli, write_hand_dataset

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


def _env() -> dict:
    path = os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]))
    return dict(os.environ, PYTHONPATH=path, PYTHONWARNINGS="ignore")


def test_kill_9_then_resume_gives_the_uninterrupted_weights(recipe, tmp_path):
    # Reference: one uninterrupted run (the delay changes timing only, not the maths).
    res = run_cli("run", str(recipe), "stages[0].model.step_delay=0.25", "--run-dir", str(tmp_path / "ref"))
    assert res.returncode == 0, res.stderr[-2000:]
    reference = load_file(tmp_path / "ref" / "only" / "export" / "model.safetensors")

    run_dir = tmp_path / "cut"
    cmd = [sys.executable, "-m", "occtrain", "run", str(recipe), "stages[0].model.step_delay=0.25", "--run-dir", str(run_dir)]
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
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

    res = run_cli("run", str(recipe), "stages[0].model.step_delay=0.25", "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr[-2000:]
    assert "resuming only" in res.stderr
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["stages"]["only"]["status"] == "done" and manifest["stages"]["only"]["attempts"] == 2
    assert torch.load(last, weights_only=True, map_location="cpu")["global_step"] == 16
    resumed = load_file(run_dir / "only" / "export" / "model.safetensors")
    assert resumed.keys() == reference.keys()
    for key in reference:
        assert torch.equal(resumed[key], reference[key]), key


def test_cpu_ddp_two_processes(recipe, tmp_path):
    res = run_cli("run", str(recipe), "trainer.devices=2", "trainer.strategy=ddp", "--run-dir", str(tmp_path / "ddp"), timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    manifest = json.loads((tmp_path / "ddp" / "manifest.json").read_text())
    assert manifest["stages"]["only"]["status"] == "done" and manifest["stages"]["only"]["attempts"] == 1
    assert (tmp_path / "ddp" / "only" / "export" / "model.safetensors").is_file()
    assert res.stderr.count("done    only") == 1  # one summary line: only rank zero reports


def test_cli_errors_are_one_line(recipe, tmp_path):
    res = run_cli("run", str(recipe), "trainer.max_step=3")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == ["error: unknown key 'trainer.max_step' in override 'trainer.max_step=3'; did you mean 'max_steps'?"]
    res = run_cli("run", str(recipe), "stages[0].model.fail=true", "--run-dir", str(tmp_path / "f"))
    assert res.returncode == 2
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("error: stage 'only' failed: RuntimeError: probe exploded (traceback in ")
    missing = tmp_path / "nothing.yaml"
    res = run_cli("run", str(missing))
    assert res.returncode == 2 and res.stderr.strip() == f"error: config file not found: {missing}"

"""Sharded training (``trainer.strategy: fsdp``, FSDP2 through Lightning) on 2 CPU processes.

One module-scoped run trains a tiny tokenizer in one process, then pretrain and a LoRA
instruct stage under DDP on two; a copy of it retrains both world-model stages sharded.
Against DDP with the same global batch: the same loss at every step and the same exports
(float tolerance), each rank holding half the world model. A sharded stage killed with
-9 mid-way resumes to the very weights of an uninterrupted sharded run. (The one-line
refusal of ``fsdp`` for a kind that does not shard is a case of ``test_bad_inputs.py``.)
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from conftest import REPO, kill_at_checkpoint, run_cli_process
from occtrain.config.recipe import OptimConfig

pytestmark = pytest.mark.slow

RECIPE = """
name: sharded
runs_root: {runs}
data:
  root: {data}
  synth: {{train_scenes: 2, val_scenes: 1, frames_per_scene: 12, seed: 3}}  # conftest.synth_dataset
  samples_per_shard: 8
  shuffle_buffer: 4
  batch_size: 1
trainer: {{ckpt_every_n_steps: 1, log_every_n_steps: 1, limit_val_batches: 1}}
stages:
  - name: tokenizer
    kind: tokenizer
    model: {tokenizer}
    optim: {{lr: 2.0e-3, weight_decay: 0.0}}
    trainer: {{max_steps: 2, val_check_interval: 2}}
  - name: pretrain
    kind: pretrain
    consumes: [tokenizer]
    model:
      llm: {{hidden_size: 64, num_layers: 2, num_heads: 4, intermediate_size: 128, text_vocab_size: 400}}
      tasks:
        weights: {{detection: 1, counting: 1, prediction: 1, planning: 2, forecasting: 2}}
        context_frames: 2
        forecast_frames: 2
      val_samples: 4
    optim: {{lr: 2.0e-3, weight_decay: 0.01}}
    # A small clip value: every step clips (by the norm over all shards, as DDP's over the whole model).
    trainer: {{max_steps: 4, val_check_interval: 4, gradient_clip_val: {clip}}}
  - name: instruct
    kind: instruct
    consumes: [pretrain]
    model:
      use_lora: true
      lora: {{r: 4, alpha: 8, dropout: 0.0}}
      tasks: {{weights: {{qa: 2, cot_planning: 1}}, context_frames: 2, questions_per_sample: 2}}
      val_samples: 4
      max_new_text_tokens: 8
    optim: {{lr: 2.0e-3}}
    trainer: {{max_steps: 3, val_check_interval: 3, gradient_clip_val: {clip}}}
"""

WORLD_STAGES = ("pretrain", "instruct")
CLIP = 0.05
#: Every run is one thread a process: DDP and FSDP then meet the same arithmetic per rank.
ONE_THREAD = {"OMP_NUM_THREADS": "1"}


def _on_two(strategy: str) -> list[str]:
    """The world-model stages on two CPU processes (2 x batch 1), the tokenizer on one."""
    return [f"stages.{s}.trainer.{k}" for s in WORLD_STAGES for k in ("devices=2", f"strategy={strategy}")]


@pytest.fixture(scope="module")
def ddp(tmp_path_factory, synth_dataset) -> Path:
    root = tmp_path_factory.mktemp("sharded")
    recipe = root / "sharded.yaml"
    recipe.write_text(
        RECIPE.format(
            runs=root / "runs",
            data=synth_dataset,
            tokenizer=REPO / "configs/model/occllama_tokenizer_tiny.yaml",
            clip=CLIP,
        )
    )
    res = run_cli_process(
        "run", str(recipe), *_on_two("ddp"), "--run-dir", str(root / "ddp"), timeout=900, env=ONE_THREAD
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return root / "ddp"


def _copy(run: Path, name: str) -> Path:
    """A copy of ``run`` (its done tokenizer and the scene cache with it) beside it."""
    target = run.parent / name
    shutil.copytree(run, target)
    return target


def _args(run: Path, *more: str) -> list[str]:
    return ["run", str(run.parent / "sharded.yaml"), *_on_two("fsdp"), *more, "--run-dir", str(run)]


@pytest.fixture(scope="module")
def fsdp(ddp) -> Path:
    run = _copy(ddp, "fsdp")
    res = run_cli_process(*_args(run, "--restart", "pretrain"), timeout=900, env=ONE_THREAD)
    assert res.returncode == 0, res.stderr[-3000:]
    return run


def _train_losses(stage_dir: Path) -> list[tuple[int, float]]:
    with open(stage_dir / "logs" / "csv" / "metrics.csv", newline="") as fh:
        return [(int(r["step"]), float(r["train/loss"])) for r in csv.DictReader(fh) if r.get("train/loss")]


def _export(stage_dir: Path) -> dict[str, Path]:
    root = stage_dir / "export"
    return {str(p.relative_to(root)): p for p in sorted(root.rglob("*")) if p.is_file()}


def _readable(path: Path, run: Path, as_run: Path) -> object:
    """A non-tensor file of an export, as written in ``as_run`` instead of ``run`` (the
    peft adapter names its base model by path) and with peft's ``target_modules``, a set
    it writes in the process's string-hash order, sorted."""
    text = path.read_text().replace(str(run), str(as_run))
    if path.suffix != ".json":
        return text
    data = json.loads(text)
    if isinstance(data.get("target_modules"), list):
        data["target_modules"] = sorted(data["target_modules"])
    return data


def _tensors(stage_dir: Path) -> dict[str, torch.Tensor]:
    return {
        f"{name}:{k}": v
        for name, path in _export(stage_dir).items()
        if name.endswith(".safetensors")
        for k, v in load_file(path).items()
    }


@pytest.mark.parametrize("stage", WORLD_STAGES)
def test_sharded_training_equals_ddp_with_the_same_global_batch(ddp, fsdp, stage):
    """Pretrain (the whole LLM) and instruct (a LoRA adapter over the frozen base), each
    sharded over two processes: every step's loss is DDP's, the exports hold the same files
    with the same tensors, and each rank held half the world model's parameters."""
    ours, theirs = _train_losses(fsdp / stage), _train_losses(ddp / stage)
    assert [s for s, _ in ours] == [s for s, _ in theirs] and len(ours) >= 3
    for (step, a), (_, b) in zip(ours, theirs):
        assert a == pytest.approx(b, rel=1e-4), f"{stage} step {step}"

    # The clip bound at the last step: its gradient, read back from AdamW's first moments in
    # the last two checkpoints (m_t = b1 m_t-1 + (1 - b1) g_t), has the clip's norm.
    b1 = OptimConfig().betas[0]
    prev, last = (
        torch.load(fsdp / stage / "checkpoints" / name, weights_only=True)["optimizer_states"][0]["state"]
        for name in ("previous.ckpt", "last.ckpt")
    )
    grads = [(last[k]["exp_avg"] - b1 * prev[k]["exp_avg"]) / (1 - b1) for k in last]
    assert float(torch.stack([g.double().norm() for g in grads]).norm()) == pytest.approx(CLIP, rel=1e-4)

    manifest = json.loads((fsdp / "manifest.json").read_text())["stages"][stage]
    assert manifest["config"]["trainer"]["strategy"] == "fsdp"
    (attempt,) = manifest["history"]
    assert attempt["world_size"] == 2
    metrics = manifest["metrics"]
    # Every tensor of the tiny world model has an even first dimension: exactly half each.
    assert metrics["params_per_rank"] == metrics["params"] / 2
    reference = json.loads((ddp / "manifest.json").read_text())["stages"][stage]["metrics"]
    assert "params_per_rank" not in reference  # DDP holds the whole model: nothing to report
    for key in ("val/loss", "val/token_acc", "params"):
        assert metrics[key] == pytest.approx(reference[key], rel=1e-5), key

    ours_files, theirs_files = _export(fsdp / stage), _export(ddp / stage)
    assert ours_files.keys() == theirs_files.keys()
    if stage == "instruct":
        assert "llm/adapter/adapter_model.safetensors" in ours_files  # LoRA exported as a peft adapter
    for name, path in ours_files.items():
        if not name.endswith(".safetensors"):  # configs, tokenizer, adapter config: alike
            assert _readable(path, fsdp, ddp) == _readable(theirs_files[name], ddp, ddp), name
    a, b = _tensors(fsdp / stage), _tensors(ddp / stage)
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5, msg=lambda m, key=key: f"{stage} {key}: {m}")


def test_a_sharded_stage_killed_mid_way_resumes_bit_exact(ddp, fsdp):
    """Killed (-9, both ranks) after its step-2 checkpoint, the sharded pretrain stage
    resumes from the full-state-dict checkpoint, weights and AdamW state re-sharded: its
    export equals the uninterrupted sharded run's bit for bit, and so does its loss log."""
    run = _copy(ddp, "cut")
    shutil.rmtree(run / "pretrain")  # DDP's checkpoints, which the watch below must not see
    last = run / "pretrain" / "checkpoints" / "last.ckpt"
    killed_at = kill_at_checkpoint(
        _args(run, "--restart", "pretrain", "--only", "pretrain"), last, step=2, env=ONE_THREAD
    )
    assert 2 <= killed_at < 4
    resumed = run_cli_process(*_args(run, "--only", "pretrain"), timeout=900, env=ONE_THREAD)
    assert resumed.returncode == 0, resumed.stderr[-3000:]

    entry = json.loads((run / "manifest.json").read_text())["stages"]["pretrain"]
    assert entry["status"] == "done" and [h["start_step"] for h in entry["history"]] == [0, killed_at]
    ref, got = _tensors(fsdp / "pretrain"), _tensors(run / "pretrain")
    assert ref.keys() == got.keys()
    for key in ref:
        assert torch.equal(ref[key], got[key]), f"killed at step {killed_at}: {key} differs"
    assert _train_losses(run / "pretrain") == _train_losses(fsdp / "pretrain")

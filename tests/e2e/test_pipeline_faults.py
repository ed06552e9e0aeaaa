"""The tiny quickstart killed and resumed in every stage, and trained at bf16-mixed, each
against the reference run ``test_pipeline_e2e`` reads too (made once for the session,
by whichever pytest worker asks first); a file of its own so both workers share the
end-to-end time."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from conftest import kill_at_checkpoint, run_cli
from occtrain.stages.callbacks import MEASURED
from quickstart_run import PIPELINE_STEPS, STAGES, export_tensors, shared_quickstart_run, tiny_overrides, train_rows

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory) -> Path:
    return shared_quickstart_run(tmp_path_factory)


def test_kill_9_at_a_random_step_of_every_stage_resumes_bit_exact(pipeline, tmp_path):
    """Each stage kind is killed (-9) once, at a random optimizer step, and resumed: every
    export equals the uninterrupted run's bit for bit, the CSV log holds each step once,
    and the manifest counts two attempts per stage with their wall times summed."""
    import random

    import torch

    rng = random.Random(int(os.environ.get("OCCTRAIN_TEST_SEED", time.time_ns() % 10_000)))
    run_dir = tmp_path / "run"
    args = [
        "run",
        "recipes/quickstart.yaml",
        *tiny_overrides(pipeline.parent / "data", steps=PIPELINE_STEPS),
        "--run-dir",
        str(run_dir),
    ]
    killed_at = {
        name: kill_at_checkpoint(args, run_dir / name / "checkpoints" / "last.ckpt", rng.randint(1, PIPELINE_STEPS - 1))
        for name in STAGES
    }
    res = run_cli(*args)
    assert res.returncode == 0, res.stderr[-3000:]

    stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
    reference = json.loads((pipeline / "manifest.json").read_text())["stages"]
    for name in STAGES:
        entry = stages[name]
        assert entry["status"] == "done" and entry["attempts"] == 2, (name, entry["attempts"])
        assert entry["wall_time_s"] > 0
        # The second attempt continued from the checkpoint, not from step 0 (a restart would
        # give the same weights, training being deterministic).
        assert [h["start_step"] for h in entry["history"]] == [0, killed_at[name]], name
        ref, got = export_tensors(pipeline / name), export_tensors(run_dir / name)
        assert ref.keys() == got.keys(), name
        for key in ref:
            assert torch.equal(ref[key], got[key]), f"{name} (killed at step {killed_at[name]}): {key} differs"
        rows = train_rows(run_dir / name)
        assert [s for s, _ in rows] == [s for s, _ in train_rows(pipeline / name)], name  # each step logged once
        assert rows == train_rows(pipeline / name), name
        timing = ("speedup", *MEASURED)  # measurements of the machine, not results
        ours = {k: v for k, v in entry["metrics"].items() if not k.endswith(timing)}
        theirs = {k: v for k, v in reference[name]["metrics"].items() if not k.endswith(timing)}
        assert ours == theirs, name


def test_bf16_mixed_trains_every_stage_on_cpu(pipeline, tmp_path):
    """The quickstart's five stage kinds at bf16-mixed on the CPU (the GPU default), the
    world-model stages with gradient checkpointing on, logging to MLflow and W&B (offline)
    where installed: every stage trains and exports, its losses are finite, the tokenizer's
    first loss (same weights, same batch) is fp32's to bf16's precision, and each stage has
    its tracker run."""
    import importlib.util
    import math

    run_dir = tmp_path / "bf16"
    checkpointing = [f"stages[{i}].model.gradient_checkpointing=true" for i in (1, 2)]
    trackers = [name for name in ("mlflow", "wandb") if importlib.util.find_spec(name)]
    res = run_cli(
        "run",
        "recipes/quickstart.yaml",
        *tiny_overrides(pipeline.parent / "data", steps=2),
        "trainer.precision=bf16-mixed",
        *checkpointing,
        f"trainer.loggers=[csv,{','.join(trackers or ['tensorboard'])}]",
        "--run-dir",
        str(run_dir),
        env={"WANDB_MODE": "offline"},
    )
    assert res.returncode == 0, res.stderr[-3000:]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert {s["config"]["trainer"]["precision"] for s in manifest["stages"].values()} == {"bf16-mixed"}
    for name in STAGES:
        rows = train_rows(run_dir / name)
        assert len(rows) == 2 and all(math.isfinite(float(loss)) for _, loss in rows), (name, rows)
        assert (run_dir / name / "export").is_dir()
    fp32, bf16 = float(train_rows(pipeline / "tokenizer")[0][1]), float(train_rows(run_dir / "tokenizer")[0][1])
    assert bf16 == pytest.approx(fp32, rel=0.02)
    for name in STAGES:
        logs = run_dir / name / "logs"
        if "mlflow" in trackers:
            assert list((run_dir / "mlruns").glob(f"*/{(logs / 'mlflow_run_id').read_text()}/metrics/train/loss"))
        if "wandb" in trackers:
            assert len(list((logs / "wandb").glob("offline-run-*"))) == 1  # its own run, not the stage before's

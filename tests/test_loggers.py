"""`trainer.loggers`: CSV always, TensorBoard, MLflow (local file store) and W&B (offline)
through Lightning's logger classes; a resumed stage logs on into the same tracker runs."""

from __future__ import annotations

import json

import pytest

from conftest import run_cli
from occtrain.errors import ConfigError
from occtrain.stages.loggers import build_loggers, check_loggers

pytest.importorskip("mlflow")
pytest.importorskip("wandb")


def _log_and_close(loggers, step: int) -> None:
    for logger in loggers:
        logger.log_metrics({"train/loss": 1.5 - 0.1 * step}, step=step)
        logger.finalize("success")


def test_every_logger_writes_and_a_resume_reuses_the_tracker_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    stage = tmp_path / "run" / "tokenizer"
    first = build_loggers(["csv", "tensorboard", "mlflow", "wandb"], stage, resume_step=None)
    assert [type(lg).__name__ for lg in first] == ["AppendingCSVLogger", "TensorBoardLogger", "TrackedMLFlowLogger", "TrackedWandbLogger"]
    _log_and_close(first, 0)
    mlflow_id, wandb_id = (stage / "logs" / "mlflow_run_id").read_text(), (stage / "logs" / "wandb_run_id").read_text()
    # The file store holds the metric under the run's id, in the run directory's mlruns/.
    assert list((tmp_path / "run" / "mlruns").glob(f"*/{mlflow_id}/metrics/train/loss"))
    assert list((stage / "logs" / "wandb").glob(f"offline-run-*-{wandb_id}"))
    again = build_loggers(["csv", "mlflow", "wandb"], stage, resume_step=1)
    assert again[1].run_id == mlflow_id and again[2].experiment.id == wandb_id
    _log_and_close(again, 1)
    lines = next((tmp_path / "run" / "mlruns").glob(f"*/{mlflow_id}/metrics/train/loss")).read_text().split()
    assert lines[1::3] == ["1.5", "1.4"]  # "timestamp value step", both attempts in one run


def test_unknown_loggers_are_refused_by_key():
    check_loggers(["csv", "wandb"])
    with pytest.raises(ConfigError, match=r"stages.x.trainer.loggers: 'neptune' is not a logger occtrain writes; choose from csv, tensorboard, mlflow, wandb"):
        check_loggers(["csv", "neptune"], "stages.x.trainer.loggers")


@pytest.mark.slow
def test_a_recipe_logs_to_mlflow_and_wandb_offline(tmp_path):
    run_dir = tmp_path / "run"
    res = run_cli(
        "run", "stages/tokenizer.yaml", f"data.root={tmp_path / 'data'}", "data.synth.train_scenes=1", "data.synth.val_scenes=1",
        "data.synth.frames_per_scene=12", "stages.tokenizer.trainer.max_steps=2", "stages.tokenizer.trainer.val_check_interval=2",
        "stages.tokenizer.trainer.limit_val_batches=1", "trainer.log_every_n_steps=1",
        "trainer.loggers=[csv,mlflow,wandb]", "--run-dir", str(run_dir), timeout=600, env={"WANDB_MODE": "offline"},
    )
    assert res.returncode == 0, res.stderr[-2000:]
    stage = next(p for p in run_dir.iterdir() if (p / "logs").is_dir())
    run_id = (stage / "logs" / "mlflow_run_id").read_text()
    assert list((run_dir / "mlruns").glob(f"*/{run_id}/metrics/train/loss"))
    assert list((stage / "logs" / "wandb").glob("offline-run-*"))
    assert not (stage / "logs" / "tensorboard").exists()  # only what the recipe named, and csv
    assert json.loads((run_dir / "manifest.json").read_text())["stages"][stage.name]["status"] == "done"

"""`trainer.loggers`: CSV always, TensorBoard, MLflow (local file store) and W&B (offline)
through Lightning's logger classes; a resumed stage logs on into the same tracker runs.
A whole recipe logging to both trackers: ``test_pipeline_faults``'s bf16 run."""

from __future__ import annotations

import pytest

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

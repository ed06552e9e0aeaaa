"""`trainer.loggers`: CSV always, TensorBoard, MLflow (local file store) and W&B (offline)
through Lightning's logger classes; a resumed stage logs on into the same tracker runs, and
a tracker writes inside the run directory only. A whole recipe logging to both trackers:
``test_pipeline_faults``'s bf16 run."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

import occtrain.stages.loggers
from occtrain.errors import ConfigError
from occtrain.stages.loggers import build_loggers, check_loggers

trackers = pytest.mark.skipif(
    importlib.util.find_spec("mlflow") is None or importlib.util.find_spec("wandb") is None,
    reason="needs the mlflow and wandb extras",
)
WANDB_DIRS = ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR", "WANDB_ARTIFACT_DIR")


def _log_and_close(loggers, step: int) -> None:
    for logger in loggers:
        logger.log_metrics({"train/loss": 1.5 - 0.1 * step}, step=step)
        logger.finalize("success")


@trackers
def test_every_logger_writes_and_a_resume_reuses_the_tracker_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    stage = tmp_path / "run" / "tokenizer"
    first = build_loggers(["csv", "tensorboard", "mlflow", "wandb"], stage, resume_step=None)
    assert [type(lg).__name__ for lg in first] == [
        "AppendingCSVLogger",
        "TensorBoardLogger",
        "TrackedMLFlowLogger",
        "TrackedWandbLogger",
    ]
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
    with pytest.raises(
        ConfigError,
        match=r"stages.x.trainer.loggers: 'neptune' is not a logger occtrain writes; "
        r"choose from csv, tensorboard, mlflow, wandb",
    ):
        check_loggers(["csv", "neptune"], "stages.x.trainer.loggers")


class _Recorded:
    """Stands in for a tracker's logger class: keeps the arguments, and the W&B directories
    of the environment, that the real one would have started with."""

    def __init__(self, **kwargs):
        self.kwargs = kwargs
        self.env = {key: os.environ.get(key) for key in WANDB_DIRS}


@pytest.fixture
def recorded(monkeypatch):
    """Tracker classes that record, a clean W&B environment (restored afterwards) and no
    variable set by an earlier test's stage."""
    for key in (*WANDB_DIRS, "WANDB_SILENT", "MLFLOW_ALLOW_FILE_STORE"):
        monkeypatch.setenv(key, "")  # records the caller's value (or its absence) for teardown
        monkeypatch.delenv(key)
    monkeypatch.setattr(occtrain.stages.loggers, "_SET_FOR_A_STAGE", {})
    monkeypatch.setattr(
        occtrain.stages.loggers, "check_loggers", lambda names: None
    )  # the extras need not be installed
    monkeypatch.setattr(occtrain.stages.loggers, "TrackedWandbLogger", _Recorded)
    monkeypatch.setattr(occtrain.stages.loggers, "TrackedMLFlowLogger", _Recorded)


def _inside(path: str, root: Path) -> bool:
    return Path(path).resolve().is_relative_to(root.resolve())


def test_wandb_writes_inside_the_stage_logs_and_each_stage_in_its_own(tmp_path, recorded):
    for stage in ("tokenizer", "pretrain"):  # one process runs the stages in turn
        logs = tmp_path / "run" / stage / "logs"
        wandb = build_loggers(["wandb"], logs.parent, resume_step=None)[1]
        assert Path(wandb.kwargs["save_dir"]) == logs and wandb.kwargs["offline"] is True
        assert wandb.env["WANDB_DIR"] == str(logs.resolve())  # wandb adds its own wandb/ below it
        assert all(_inside(wandb.env[key], logs / "wandb") for key in WANDB_DIRS[1:]), wandb.env


def test_a_wandb_directory_the_user_set_is_kept(tmp_path, recorded, monkeypatch):
    monkeypatch.setenv("WANDB_CACHE_DIR", str(tmp_path / "my-cache"))
    for stage in ("tokenizer", "pretrain"):
        wandb = build_loggers(["wandb"], tmp_path / "run" / stage, resume_step=None)[1]
        assert wandb.env["WANDB_CACHE_DIR"] == str(tmp_path / "my-cache")
        assert _inside(wandb.env["WANDB_DATA_DIR"], tmp_path / "run" / stage / "logs")


def test_mlflow_keeps_its_store_and_artifacts_in_the_run(tmp_path, recorded):
    mlflow = build_loggers(["mlflow"], tmp_path / "run" / "tokenizer", resume_step=None)[1]
    assert mlflow.kwargs["tracking_uri"] == (tmp_path / "run" / "mlruns").resolve().as_uri()
    # No artifact location of its own: a file store keeps each run's artifacts inside itself.
    assert mlflow.kwargs.get("artifact_location") is None
    assert not any(os.environ.get(key) for key in WANDB_DIRS)  # a W&B-less recipe leaves W&B's environment alone

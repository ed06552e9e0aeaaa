"""What a stage logs to: the CSV file the dashboard and a resume read (always), and the
trackers a recipe's ``trainer.loggers`` adds through Lightning's own logger classes:
TensorBoard, MLflow (a local file store, ``<run>/mlruns``, its artifacts in it too) and Weights
& Biases (offline, ``<stage>/logs/wandb``, its caches and settings too; ``wandb sync`` uploads
it later): nothing goes outside the run directory but where a user's own environment
variable (a ``WANDB_CACHE_DIR``, say) sends it. MLflow and W&B are optional
extras (``pip install -e '.[mlflow]'`` / ``'.[wandb]'``). A resumed stage logs on into the
same MLflow run and W&B run: their ids are kept in ``<stage>/logs/``."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lightning.fabric.loggers.csv_logs import _ExperimentWriter
from lightning.fabric.loggers.logger import rank_zero_experiment
from lightning.pytorch.loggers import CSVLogger, Logger, MLFlowLogger, TensorBoardLogger, WandbLogger

from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_open, atomic_write_text, remove_inside

#: The loggers a recipe can name; csv is always written.
LOGGERS = ("csv", "tensorboard", "mlflow", "wandb")
#: Loggers that need their own package (an optional extra of the same name).
_TRACKERS = ("mlflow", "wandb")


class _AppendingWriter(_ExperimentWriter):
    """Lightning's CSV writer deletes ``metrics.csv`` when it starts; a resumed stage keeps
    the rows logged before the checkpoint it resumes from instead (later rows are logged
    again by the resumed run)."""

    def __init__(self, log_dir: str, keep_before_step: int | None) -> None:
        path = Path(log_dir) / self.NAME_METRICS_FILE
        kept: list[dict] = []
        keys: list[str] = []
        if keep_before_step is not None and path.is_file():
            with open(path, newline="") as fh:
                reader = csv.DictReader(fh)
                keys = list(reader.fieldnames or [])
                kept = [row for row in reader if _row_step(row) < keep_before_step]
        remove_inside(path, log_dir)
        super().__init__(log_dir)
        if kept:
            with atomic_open(path) as fh:
                text = _csv_text(keys, kept)
                fh.write(text.encode())
            self.metrics_keys = sorted(keys)

    def _check_log_dir_exists(self) -> None:
        """The base class deletes earlier logs here (and warns that it will)."""


def _row_step(row: dict) -> float:
    try:
        return float(row.get("step") or 0)
    except ValueError:
        return 0.0


def _csv_text(keys: list[str], rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=sorted(keys))
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


class AppendingCSVLogger(CSVLogger):
    """A CSVLogger whose ``metrics.csv`` survives a resume (see :class:`_AppendingWriter`)."""

    def __init__(self, *args: Any, resume_step: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._resume_step = resume_step

    @property
    @rank_zero_experiment
    def experiment(self) -> _ExperimentWriter:
        # Rank zero's alone, as Lightning's own: Lightning creates every logger's experiment
        # on every rank before fitting, and a second rank rewriting metrics.csv beside rank
        # zero lost the rows a resumed multi-process stage keeps.
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(self.log_dir, self._resume_step)
        return self._experiment


def check_loggers(names: list[str], key: str = "trainer.loggers") -> None:
    """One line for an unknown logger, or a tracker whose package is not installed."""
    import importlib.util

    for name in names:
        if name not in LOGGERS:
            raise ConfigError(f"{key}: '{name}' is not a logger occtrain writes; choose from {', '.join(LOGGERS)}")
        if name in _TRACKERS and importlib.util.find_spec(name) is None:
            raise ConfigError(f"{key}: '{name}' needs its package; install it with pip install -e '.[{name}]'")


def _kept_id(path: Path) -> str | None:
    return (path.read_text().strip() or None) if path.is_file() else None


if TYPE_CHECKING:

    class _TrackerLogger(Logger):
        """What the mixin sits in front of: a tracker's logger, which has an experiment."""

        @property
        def experiment(self) -> Any: ...

else:
    _TrackerLogger = object


class _KeepsRunId(_TrackerLogger):
    """A tracker's logger that writes its run id to ``id_file`` once the run exists (the
    ``experiment`` property is read at every log call: the file is checked once)."""

    def __init__(self, *args: Any, id_file: Path, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._id_file = id_file
        self._id_kept = False

    def _run_id_of(self, experiment: Any) -> Any:
        raise NotImplementedError

    @property
    def experiment(self) -> Any:
        experiment = super().experiment
        if not self._id_kept:
            run_id = self._run_id_of(experiment)
            if isinstance(run_id, str) and run_id:  # other ranks hold a dummy without one
                if _kept_id(self._id_file) != run_id:
                    atomic_write_text(self._id_file, run_id)
                self._id_kept = True
        return experiment


class TrackedMLFlowLogger(_KeepsRunId, MLFlowLogger):
    """Lightning's MLflow logger, its run id kept for a resume."""

    def _run_id_of(self, experiment: Any) -> Any:
        return self._run_id


class TrackedWandbLogger(_KeepsRunId, WandbLogger):
    """Lightning's W&B logger, its run id kept for a resume; each stage's run finished."""

    def _run_id_of(self, experiment: Any) -> Any:
        return getattr(experiment, "id", None)

    def finalize(self, status: str) -> None:
        # Stages run one after another in one process; an unfinished run would swallow the next stage's.
        super().finalize(status)
        if self._experiment is not None and hasattr(self._experiment, "finish"):
            self._experiment.finish(exit_code=0 if status == "success" else 1)
            self._experiment = None
            self._id_kept = False


#: Where W&B writes, by the variable that moves it, relative to the stage's ``logs/``: the run
#: files (``<WANDB_DIR>/wandb``, as ``save_dir``), settings, the artifact cache, artifact
#: staging and downloads. Unset, the last four are ~/.config/wandb, ~/.cache/wandb,
#: ~/.local/share/wandb and ./artifacts.
_WANDB_DIRS = {
    "WANDB_DIR": ".",
    "WANDB_CONFIG_DIR": "wandb/config",
    "WANDB_CACHE_DIR": "wandb/cache",
    "WANDB_DATA_DIR": "wandb/data",
    "WANDB_ARTIFACT_DIR": "wandb/artifacts",
}
#: The values occtrain set (not the user), so a later stage in the process moves them to its own logs.
_SET_FOR_A_STAGE: dict[str, str] = {}


def _point_wandb_at(logs: Path) -> None:
    """Keep everything W&B writes inside the stage's ``logs/`` (under ``logs/wandb``).

    W&B reads these directories from the environment wherever it writes, not from
    ``wandb.init``, so the process environment is the only place to set them. A variable the
    user set is theirs and kept (they chose that place); the others are set for this stage.
    """
    for key, sub in _WANDB_DIRS.items():
        where = str((logs / sub).resolve())
        if key not in os.environ or os.environ[key] == _SET_FOR_A_STAGE.get(key):
            os.environ[key] = _SET_FOR_A_STAGE[key] = where


def build_loggers(names: list[str], stage_dir: Path, resume_step: int | None) -> list[Logger]:
    """The stage's loggers: CSV always, then each tracker ``names`` adds, in that order."""
    check_loggers(names)
    logs = stage_dir / "logs"
    out: list[Logger] = [AppendingCSVLogger(logs, name="", version="csv", resume_step=resume_step)]
    run, stage = stage_dir.parent.name, stage_dir.name
    for name in dict.fromkeys(names):
        if name == "tensorboard":
            out.append(TensorBoardLogger(logs, name="", version="tensorboard"))
        elif name == "mlflow":
            # MLflow 3 keeps its file store (no database to set up) behind an opt-in.
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
            # Given the store's URI, MLflow writes nothing elsewhere: a file store keeps each
            # run's artifacts inside itself. One store per run, so its stages compare in one UI.
            out.append(
                TrackedMLFlowLogger(
                    experiment_name=run,
                    run_name=stage,
                    tracking_uri=(stage_dir.parent / "mlruns").resolve().as_uri(),
                    run_id=_kept_id(logs / "mlflow_run_id"),
                    id_file=logs / "mlflow_run_id",
                )
            )
        elif name == "wandb":
            os.environ.setdefault("WANDB_SILENT", "true")
            (logs / "wandb").mkdir(parents=True, exist_ok=True)
            _point_wandb_at(logs)
            kept = _kept_id(logs / "wandb_run_id")
            out.append(
                TrackedWandbLogger(
                    project=run,
                    name=stage,
                    save_dir=str(logs),
                    offline=True,
                    id=kept,
                    resume="allow" if kept else None,
                    id_file=logs / "wandb_run_id",
                )
            )
    return out

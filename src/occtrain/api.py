"""The Python API: a trained world model from its export directory, no recipe or run needed.

    import occtrain

    model = occtrain.load("runs/quickstart/instruct/export")
    clip = model.clip("data/quickstart", split="val")
    model.answer(clip, "Are there any cars?")

``load`` rebuilds the model exactly as a later stage would (the engine's
``load_world_model``); its operations are the ones its family declares
(``WorldSpec.operations``: answer a question, plan, forecast, reason to a meta action, or
a family's own), each taking a clip of a dataset in the Occ3D layout.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occtrain.data.clips import Clip, frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError, OcctrainError
from occtrain.formats.occ3d import FUTURE_STEPS

if TYPE_CHECKING:  # the engine imports torch and transformers: only when a model is loaded
    from occtrain.engine import WorldModelEngine

#: Operations a planner stage reads, not meant for a user.
_INTERNAL = ("reference_meta_action", "generated_meta_actions", "visual_summary")


class TrainedModel:
    """A world model loaded from an export, with its family's operations as methods."""

    def __init__(self, engine: WorldModelEngine):
        self.engine = engine.eval()
        self._data: str | None = None

    @property
    def family(self) -> str:
        return self.engine.family

    @property
    def operations(self) -> list[str]:
        """What this model can do (each is a method: ``model.<operation>(clip, ...)``)."""
        return [name for name in self.engine.spec.operations if name not in _INTERNAL]

    def clip(self, data_root: str | Path, token: str | None = None, split: str = "val") -> Clip:
        """The clip around sample ``token`` of a dataset (default: the first frame of
        ``split`` with the history the model's prompts read and a whole 3 s future)."""
        root = str(data_root)
        if self._data != root:
            self.engine.prepare_inputs(root)  # the frozen encoders' inputs, in memory
            self._data = root
        index = DatasetIndex.open(root)
        clips = frame_clips(index, split, self.engine.tasks.context_frames, FUTURE_STEPS, partial_history=False)
        for clip in clips:
            if token is None or clip.anchor["token"] == token:
                return clip
        which = f"sample {token}" if token is not None else "sample"
        raise ConfigError(
            f"{root}: no {split} {which} with {self.engine.tasks.context_frames} history frames and a 3 s future"
        )

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_") or name in _INTERNAL or name not in self.engine.spec.operations:
            raise AttributeError(
                f"the '{self.engine.family}' world model has no operation '{name}'; it has {', '.join(self.operations)}"
            )
        return partial(self.engine.spec.operations[name], self.engine)

    def __dir__(self) -> list[str]:
        return sorted({*super().__dir__(), *self.operations})


def load(export_dir: str | Path) -> TrainedModel:
    """A trained world model from a world-model stage's ``export/`` directory (or the stage's
    own directory, whose ``export/`` it loads)."""
    from occtrain.engine import load_world_model

    return TrainedModel(load_world_model(_export_dir(Path(export_dir))))


def _export_dir(path: Path) -> Path:
    """The export ``path`` means: itself, or the ``export/`` of a stage directory; a stage
    without one or a whole run is refused in one line saying what to pass instead."""
    from occtrain.formats.exports import EXPORT_CONFIG
    from occtrain.formats.manifest import MANIFEST_FILE

    if (path / EXPORT_CONFIG).is_file():
        return path
    if (path / "export").is_dir():
        return path / "export"
    if (path / MANIFEST_FILE).is_file():
        raise ConfigError(_run_dir_message(path))
    if (path.parent / MANIFEST_FILE).is_file() and path.is_dir():
        raise ConfigError(
            f"{path} is a stage directory without an export; its stage is not done — run it, or pass {path}/export"
        )
    return path  # not occtrain's layout: the loader says what is missing


def _run_dir_message(run: Path) -> str:
    """What a run directory holds, for a user who passed it to ``load``."""
    from occtrain.formats.manifest import Manifest

    stages = Manifest.load(run, writable=False).stages
    if not stages:
        return (
            f"{run} is a run directory with no stages run yet; run its recipe, "
            "then pass RUN/STAGE/export of a world-model stage"
        )
    listed = ", ".join(f"{name} ({entry.status})" for name, entry in stages.items())
    loadable = [name for name in stages if _holds_world_model(run / name / "export")]
    example = f"e.g. {run / loadable[-1] / 'export'}" if loadable else "none has one yet"
    return (
        f"{run} is a run directory, not an export; its stages are {listed}; "
        f"pass a world-model stage's export ({example})"
    )


def _holds_world_model(export: Path) -> bool:
    """Whether ``export`` is a world model's, by its config (a plugin's stage kinds may write
    one too); a broken one is not offered, its own error comes when it is loaded."""
    from occtrain.formats.exports import EXPORT_CONFIG, export_kind

    try:
        return (export / EXPORT_CONFIG).is_file() and export_kind(export) == "world_model"
    except OcctrainError:
        return False

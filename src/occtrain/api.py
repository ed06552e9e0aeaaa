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

from functools import partial
from pathlib import Path
from typing import Any, Callable

from occtrain.data.clips import Clip, frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.errors import ConfigError
from occtrain.occ3d import FUTURE_STEPS

#: Operations a planner stage reads, not meant for a user.
_INTERNAL = ("reference_meta_action", "generated_meta_actions", "visual_summary")


class TrainedModel:
    """A world model loaded from an export, with its family's operations as methods."""

    def __init__(self, engine: Any):
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
        raise ConfigError(f"{root}: no {split} {which} with {self.engine.tasks.context_frames} history frames and a 3 s future")

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_") or name in _INTERNAL or name not in self.engine.spec.operations:
            raise AttributeError(f"the '{self.engine.family}' world model has no operation '{name}'; it has {', '.join(self.operations)}")
        return partial(self.engine.spec.operations[name], self.engine)

    def __dir__(self) -> list[str]:
        return sorted({*super().__dir__(), *self.operations})


def load(export_dir: str | Path) -> TrainedModel:
    """A trained world model from a world-model stage's ``export/`` directory."""
    from occtrain.engine import load_world_model

    return TrainedModel(load_world_model(Path(export_dir)))

"""The per-sample inputs a family's prompt parts read besides their own values: what a
family registers with its spec (``WorldSpec.sample_inputs``) and the engine serves by name.

A part that names a sample (OccVLA's camera views, the voxels its occupancy queries are
trained on) holds only the sample's token; the sequence builder's ``lay`` reads the
values through ``PromptInputs.read(name, token)``. An input is either *encoded*: made
through a frozen encoder (the vision stage's), so the engine encodes every frame of a
dataset once and keeps the rows on disk; or read from the dataset when a part is laid
out (nothing worth caching). The engine knows no input by name: a family that needs a
new one (lidar points, a map) registers it here and edits neither core nor engine.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from occtrain.data.layout import DatasetIndex

#: A chunk of a dataset's samples, ``(scene, token)`` each.
Samples = list[tuple[str, str]]


class InputSource(Protocol):
    """What an input's rows may read through besides the dataset: the engine's frozen
    camera encoder, pooled as the world model reads it."""

    def encode_images(self, images: torch.Tensor) -> torch.Tensor: ...


@dataclass(frozen=True)
class SampleInput:
    """One per-sample input: ``rows(source, index, samples)`` gives one row per sample."""

    name: str
    rows: Callable[[InputSource, DatasetIndex, Samples], torch.Tensor]
    #: Made through a frozen encoder: encoded once per dataset (``<name>.safetensors`` in
    #: the stage's cache directory). Otherwise read from the dataset per laid-out part.
    encoded: bool = False
    #: Its rows read the camera images (a dataset without them is refused in one line).
    reads_cameras: bool = False
    #: What the progress bar says while a dataset is encoded.
    what: str = ""

    @property
    def cache_file(self) -> str:
        return f"{self.name}.safetensors"


def _voxels(source: InputSource, index: DatasetIndex, samples: Samples) -> torch.Tensor:
    return torch.from_numpy(np.stack([index.labels(s, t)["semantics"] for s, t in samples]))


def _image_tokens(source: InputSource, index: DatasetIndex, samples: Samples) -> torch.Tensor:
    return source.encode_images(torch.from_numpy(np.stack([index.images(s, t) for s, t in samples])))


#: A frame's occupancy labels, uint8 (X, Y, Z): what occupancy-query parts are trained on.
VOXELS = SampleInput("voxels", _voxels)
#: A frame's camera views through the frozen vision encoder, pooled as the world model
#: reads them, float (T, D).
IMAGE_TOKENS = SampleInput(
    "image_tokens",
    _image_tokens,
    encoded=True,
    reads_cameras=True,
    what="encoding the cameras with the frozen vision encoder",
)

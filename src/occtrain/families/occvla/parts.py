"""OccVLA's own prompt parts: a frame's camera views as image tokens, and the occupancy
queries trained on its voxels. Each holds only the sample's token; the sequence builder
reads their values through the inputs the family registers (``core.sample_inputs``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from occtrain.data.clips import PromptPart


@dataclass(frozen=True)
class Images(PromptPart):
    """The camera views of sample ``token`` as image tokens (read as ``image_tokens``)."""

    token: str
    supervise: bool = False  # never: an input


@dataclass(frozen=True)
class Occupancy(PromptPart):
    """Occupancy queries that read the images before them and are trained, with loss
    weight ``weight``, to give the voxels of sample ``token`` (read as ``voxels``); nothing
    after them sees them, so a prompt leaves them out at inference."""

    read_after: ClassVar[bool] = False
    token: str
    weight: float = 1.0
    supervise: bool = False  # their loss is their own, not the answer's

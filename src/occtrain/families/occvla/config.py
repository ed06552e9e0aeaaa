"""OccVLA's world-model settings (``model.occvla`` of a pretrain stage)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from occtrain.errors import ConfigError

if TYPE_CHECKING:
    from occtrain.core.lm_world_model import WorldInputs


@dataclass
class OccVLAWorldConfig:
    """The image tokens, the occupancy queries and their projections (Sec. 3.2)."""

    #: One occupancy query per p x p patch of the OccWorld latent grid (p = 1: a query per
    #: latent cell; the paper does not give its count).
    query_patch: int = 1
    #: Image tokens per camera: the vision tower's patch grid average-pooled to (rows,
    #: cols). The paper feeds 256 per view (SigLIP at 224 px); six views of 3 x 4 keep the
    #: tiny LLM's sequences short on a CPU.
    image_tokens: list[int] = field(default_factory=lambda: [3, 4])
    #: Hidden width of the two-layer image projector (vision width -> LLM width).
    projector_hidden: int = 256

    def validate(self, where: str, inputs: WorldInputs) -> None:
        """One line naming the key when a setting cannot work over ``inputs`` (a ``WorldInputs``)."""
        latent = tuple(inputs.scene.latent_hw)
        p = self.query_patch
        if p < 1 or latent[0] % p or latent[1] % p:
            raise ConfigError(
                f"{where}.query_patch: {p} must divide the tokenizer's latent grid {latent[0]} x {latent[1]}"
            )
        if len(self.image_tokens) != 2 or min(self.image_tokens) < 1:
            raise ConfigError(f"{where}.image_tokens: {list(self.image_tokens)} must be [rows, cols], each >= 1")
        if self.projector_hidden < 1:
            raise ConfigError(f"{where}.projector_hidden: must be >= 1, got {self.projector_hidden}")

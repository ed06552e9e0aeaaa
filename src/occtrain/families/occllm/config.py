"""Config of Occ-LLM's Motion-Separation VAE (seeds/003, Sec. III-A, Table III)."""

from __future__ import annotations

from dataclasses import dataclass, field

from occtrain.errors import ConfigError
from occtrain.families.occworld.config import OccWorldVQVAEConfig
from occtrain.occ3d import CLASS_INDEX, FREE, NUM_CLASSES

#: The paper does not list its movable classes; these are Occ3D's vehicles, cyclists and
#: pedestrians (barriers and cones stand still).
MOVABLE_CLASSES: tuple[str, ...] = (
    "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian", "trailer", "truck",
)


@dataclass
class MSVAEConfig(OccWorldVQVAEConfig):
    """OccWorld's 2D VAE (height folded into channels) with Occ-LLM's two additions, each
    switchable for Table III's ablation: a light 3D convolution before the encoder and after
    the decoder, and motion separation (movable and static voxels encoded apart by the shared
    encoder, quantized by two codebooks, decoded by the shared decoder and merged).

    ``num_codes`` is the static codebook's size, ``num_codes_motion`` the movable one's.
    """

    conv3d: bool = True
    motion_separation: bool = True
    num_codes_motion: int = 512
    movable_classes: list[str] = field(default_factory=lambda: list(MOVABLE_CLASSES))

    def validate(self, where: str) -> None:
        super().validate(where)
        unknown = [c for c in self.movable_classes if c not in CLASS_INDEX or CLASS_INDEX[c] == FREE]
        if unknown:
            raise ConfigError(f"{where}.movable_classes: '{unknown[0]}' is not an Occ3D class (0..{NUM_CLASSES - 2} by name)")
        if self.num_codes_motion < 1:
            raise ConfigError(f"{where}.num_codes_motion: must be >= 1, got {self.num_codes_motion}")

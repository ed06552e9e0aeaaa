"""What the synthetic world's boxed things are: class, size range, and their tracks over time."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from occtrain.data.schema import STOP_SPEED, Status
from occtrain.formats.occ3d import CLASS_INDEX


@dataclass(frozen=True)
class Kind:
    """A kind of boxed object: its Occ3D class and the range of its [length, width, height]."""

    category: str
    size_lo: tuple[float, float, float]
    size_hi: tuple[float, float, float]

    @property
    def cls(self) -> int:
        return CLASS_INDEX[self.category]

    def sample_size(self, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(self.size_lo, self.size_hi)


#: Roughly nuScenes-sized objects. Cycles "with rider" include the rider in their box, as
#: nuScenes does, so they are taller.
KINDS: dict[str, Kind] = {
    "car": Kind("car", (3.9, 1.75, 1.45), (5.0, 2.0, 1.9)),
    "truck": Kind("truck", (6.0, 2.3, 2.7), (9.5, 2.6, 3.6)),
    "tractor": Kind("truck", (5.5, 2.4, 3.2), (6.5, 2.6, 3.6)),
    "bus": Kind("bus", (10.5, 2.8, 3.1), (12.5, 3.0, 3.5)),
    "trailer": Kind("trailer", (7.5, 2.45, 3.2), (12.0, 2.6, 3.8)),
    "construction_vehicle": Kind("construction_vehicle", (5.5, 2.5, 2.8), (7.5, 3.0, 3.6)),
    "bicycle": Kind("bicycle", (1.6, 0.5, 1.0), (1.85, 0.7, 1.2)),
    "cyclist": Kind("bicycle", (1.6, 0.55, 1.6), (1.85, 0.7, 1.85)),
    "motorcycle": Kind("motorcycle", (1.9, 0.7, 1.1), (2.3, 0.9, 1.3)),
    "motorcyclist": Kind("motorcycle", (1.9, 0.75, 1.45), (2.3, 0.9, 1.7)),
    "pedestrian": Kind("pedestrian", (0.5, 0.5, 1.55), (0.85, 0.75, 1.9)),
    "traffic_cone": Kind("traffic_cone", (0.35, 0.35, 0.6), (0.5, 0.5, 0.9)),
    "barrier": Kind("barrier", (1.8, 0.4, 0.8), (2.6, 0.6, 1.1)),
}


def pick(rng: np.random.Generator, table: tuple[tuple[str, float], ...]) -> str:
    """A kind name drawn from (name, weight) pairs."""
    names, weights = zip(*table)
    return names[int(rng.choice(len(names), p=np.array(weights) / sum(weights)))]


VEHICLE_CLASSES = frozenset(CLASS_INDEX[c] for c in ("car", "truck", "bus", "trailer", "construction_vehicle"))
CYCLE_CLASSES = frozenset(CLASS_INDEX[c] for c in ("bicycle", "motorcycle"))
PEDESTRIAN = CLASS_INDEX["pedestrian"]


@dataclass
class TrackSet:
    """Every boxed object of a scene, sampled at the frame times (struct of arrays).

    ``xy``/``yaw``/``speed`` are global and cover the scene's frames plus the future
    horizon after its end. ``parked`` marks vehicles that are parked rather than stopped
    in traffic; ``rider`` is 1/0 for cycles with/without a rider and -1 otherwise.
    """

    cls: np.ndarray  # (N,) int
    size: np.ndarray  # (N, 3) length, width, height
    xy: np.ndarray  # (N, T, 2)
    yaw: np.ndarray  # (N, T)
    speed: np.ndarray  # (N, T)
    parked: np.ndarray  # (N,) bool
    rider: np.ndarray  # (N,) int

    def __len__(self) -> int:
        return len(self.cls)

    @property
    def velocity(self) -> np.ndarray:
        """(N, T, 2) global velocity: speed along the heading."""
        return self.speed[..., None] * np.stack([np.cos(self.yaw), np.sin(self.yaw)], axis=-1)

    def attribute(self, n: int, t: int) -> Status | Literal[""]:
        """nuScenes-style status of object ``n`` at frame ``t`` (schema.STATUS_VALUES, or "")."""
        c = int(self.cls[n])
        if c in CYCLE_CLASSES:
            return "with rider" if self.rider[n] == 1 else "without rider"
        moving = self.speed[n, t] > STOP_SPEED
        if c == PEDESTRIAN:
            return "moving" if moving else "standing"
        if c in VEHICLE_CLASSES:
            return "parked" if self.parked[n] else ("moving" if moving else "stopped")
        return ""

    @staticmethod
    def concat(parts: list[TrackSet]) -> TrackSet:
        return TrackSet(*(np.concatenate([getattr(p, f) for p in parts]) for f in TrackSet.__dataclass_fields__))

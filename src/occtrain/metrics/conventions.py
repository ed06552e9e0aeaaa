"""The names every metric result carries for its convention, and the horizon labels.

Kept apart from the metrics themselves (which import torch and torchmetrics) so that the
CLI, the dashboard and the paper figures can name conventions without loading them.
"""

from __future__ import annotations

from occtrain.formats.occ3d import FRAME_DT

#: Occupancy: Occ3D's (camera-visible voxels, classes absent from both sides left out) and
#: OccWorld's (every voxel; an absent class scores 100), by name.
OCC3D, OCCWORLD = "occ3d", "occworld"
CONVENTIONS = (OCC3D, OCCWORLD)
#: Planning: ST-P3's (L2 and collision averaged up to each horizon) and UniAD's (at it).
STP3, UNIAD = "stp3", "uniad"


def horizon_label(index: int) -> str:
    """Future frame index -> seconds label: 1 -> '1s', 0 -> '0.5s' (frames at 2 Hz)."""
    return f"{(index + 1) * FRAME_DT:g}s"


#: The future frames a forecast is scored at (1, 2 and 3 s at 2 Hz), and the file of one
#: sample's forecast that ``occtrain score forecast`` reads and ``occtrain eval
#: --save-predictions`` writes (``<scene>/<token>/forecast.npz``, 'semantics' (T, X, Y, Z)).
FORECAST_HORIZONS = (1, 3, 5)
FORECAST_FILE = "forecast.npz"

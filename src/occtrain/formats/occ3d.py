"""The Occ3D-nuScenes grid, class list and time step: the one place these facts live.

Everything that touches voxels, classes, colours or frame timing imports from here.
"""

from __future__ import annotations

import numpy as np

#: Occ3D-nuScenes class names, in label order. Index 17 is free space.
CLASS_NAMES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
NUM_CLASSES = len(CLASS_NAMES)  # 18
FREE = 17
#: Classes that count in mIoU (all but free).
SEMANTIC_CLASSES = tuple(range(FREE))
CLASS_INDEX = {name: i for i, name in enumerate(CLASS_NAMES)}
#: The classes that move: vehicles, cyclists and pedestrians (barriers and cones stand
#: still). Occ-LLM's motion separation and the movable-class mIoU read this grouping.
MOVABLE_CLASSES: tuple[str, ...] = (
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "trailer",
    "truck",
)

#: Occ3D-nuScenes training-set voxel counts per class, in class order (free last): the
#: counts public Occ3D training code weights its class-balanced losses with (the BEVDet-occ
#: lineage's ``nusc_class_frequencies``). Facts for ``occtrain data stats`` to compare with.
OCC3D_TRAIN_VOXELS: tuple[int, ...] = (
    1163161,
    2309034,
    188743,
    2997643,
    20317180,
    852476,
    243808,
    2457947,
    497017,
    2731022,
    7224789,
    214411435,
    5565043,
    63191967,
    76098082,
    128860031,
    141625221,
    2307405309,
)
#: What one real Occ3D-nuScenes frame (``labels.npz``) shows, as shares in [0, 1] but for
#: the voxels per column: its mask_camera lies wholly inside its mask_lidar.
OCC3D_FRAME: dict[str, float] = {
    "occupied": 0.061,
    "occupied_columns": 0.39,
    "voxels_per_column": 2.5,
    "low_layers": 0.40,
    "mask_lidar": 0.088,
    "mask_camera": 0.068,
    "camera_inside_lidar": 1.0,
    "occupied_in_camera": 0.527,
}

#: Voxel grid: (X, Y, Z) cells, ego frame with x forward, y left, z up.
GRID_SHAPE: tuple[int, int, int] = (200, 200, 16)
VOXEL_SIZE = 0.4  # metres, isotropic
#: Lower and upper bounds (x, y, z) in metres of the grid, ego at the x-y centre.
RANGE_MIN = np.array([-40.0, -40.0, -1.0])
RANGE_MAX = np.array([40.0, 40.0, 5.4])

#: nuScenes keyframes come at 2 Hz.
FRAME_DT = 0.5
#: Future / past horizons used throughout (3 s of future, 2 s of past).
FUTURE_STEPS = 6
PAST_STEPS = 4

#: Ego vehicle footprint used by the planning collision metric (ST-P3 / UniAD).
EGO_LENGTH = 4.084
EGO_WIDTH = 1.85

#: Usual Occ3D visualisation colours (RGB), one per class; free is white.
CLASS_COLORS = np.array(
    [
        (0, 0, 0),  # others
        (255, 120, 50),  # barrier
        (255, 192, 203),  # bicycle
        (255, 255, 0),  # bus
        (0, 150, 245),  # car
        (0, 255, 255),  # construction_vehicle
        (200, 180, 0),  # motorcycle
        (255, 0, 0),  # pedestrian
        (255, 240, 150),  # traffic_cone
        (135, 60, 0),  # trailer
        (160, 32, 240),  # truck
        (255, 0, 255),  # driveable_surface
        (139, 137, 137),  # other_flat
        (75, 0, 75),  # sidewalk
        (150, 240, 80),  # terrain
        (230, 230, 250),  # manmade
        (0, 175, 0),  # vegetation
        (255, 255, 255),  # free
    ],
    dtype=np.uint8,
)


def voxel_centers_1d(axis: int) -> np.ndarray:
    """Centres (metres) of the grid cells along one axis (0 = x, 1 = y, 2 = z)."""
    n = GRID_SHAPE[axis]
    return RANGE_MIN[axis] + VOXEL_SIZE * (np.arange(n) + 0.5)


def metres_to_index(xyz: np.ndarray) -> np.ndarray:
    """Map metric ego-frame coordinates (..., k<=3) to integer voxel indices (unclipped)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    k = xyz.shape[-1]
    return np.floor((xyz - RANGE_MIN[:k]) / VOXEL_SIZE).astype(np.int64)

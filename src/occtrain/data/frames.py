"""Frame batches read straight from a dataset index, with the keys the shard loader's
``collate_frames`` gives: what evaluation and the encoders of other frames read without shards."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from occtrain.data.layout import DatasetIndex


def frames_batch(index: DatasetIndex, samples: list[tuple[str, str]], cameras: bool = False) -> dict[str, Any]:
    """``semantics`` uint8 (B, X, Y, Z), ``mask_camera`` bool, ``token`` and ``meta`` lists
    of the ``(scene, token)`` samples; with ``cameras`` also ``images`` uint8 (B, 6, H, W, 3),
    ``intrinsics`` (B, 6, 3, 3) and ``cam_to_ego`` (B, 6, 4, 4)."""
    labels = [index.labels(scene, token) for scene, token in samples]
    batch: dict[str, Any] = {
        "semantics": torch.from_numpy(np.stack([x["semantics"] for x in labels])),
        "mask_camera": torch.from_numpy(np.stack([x["mask_camera"] for x in labels]).astype(bool)),
        "token": [token for _, token in samples],
        "meta": [
            {"scene": scene, "token": token, "index": index.scenes[scene].index(token)} for scene, token in samples
        ],
    }
    if cameras:
        batch.update(camera_batch(index, samples))
    return batch


def camera_batch(index: DatasetIndex, samples: list[tuple[str, str]]) -> dict[str, torch.Tensor]:
    """The six views and their calibration of each sample, stacked in CAMERA_NAMES order."""
    records = [index.cameras(scene, token) for scene, token in samples]
    return {
        "images": torch.from_numpy(np.stack([index.images(scene, token) for scene, token in samples])),
        "intrinsics": torch.tensor(np.stack([[r.intrinsic for r in rs] for rs in records]), dtype=torch.float32),
        "cam_to_ego": torch.tensor(np.stack([[r.cam_to_ego for r in rs] for rs in records]), dtype=torch.float32),
    }

"""Frame batches read straight from a dataset index, with the keys the shard loader's
``collate_frames`` gives: what evaluation and the encoders of other frames read without shards."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from occtrain.data.layout import DatasetIndex


def frames_batch(
    index: DatasetIndex, samples: list[tuple[str, str]], cameras: bool = False, pixel_truth: bool = False
) -> dict[str, Any]:
    """``semantics`` uint8 (B, X, Y, Z), ``mask_camera`` bool, ``token`` and ``meta`` lists
    of the ``(scene, token)`` samples; with ``cameras`` also ``images`` uint8 (B, 6, H, W, 3),
    ``intrinsics`` (B, 6, 3, 3) and ``cam_to_ego`` (B, 6, 4, 4); with ``pixel_truth`` too,
    where the dataset has them (synthetic frames), each pixel's class ``cam_class`` uint8 and
    depth ``cam_depth`` metres (B, 6, H, W)."""
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
        batch.update(camera_batch(index, samples, pixel_truth))
    return batch


def camera_batch(
    index: DatasetIndex, samples: list[tuple[str, str]], pixel_truth: bool = False
) -> dict[str, torch.Tensor]:
    """The six views and their calibration of each sample, stacked in CAMERA_NAMES order;
    with ``pixel_truth`` their class and depth maps where every sample has them."""
    records = [index.cameras(scene, token) for scene, token in samples]
    out = {
        "images": torch.from_numpy(np.stack([index.images(scene, token) for scene, token in samples])),
        "intrinsics": torch.tensor(np.stack([[r.intrinsic for r in rs] for rs in records]), dtype=torch.float32),
        "cam_to_ego": torch.tensor(np.stack([[r.cam_to_ego for r in rs] for rs in records]), dtype=torch.float32),
    }
    if not pixel_truth:
        return out
    targets = [index.camera_targets(scene, token) for scene, token in samples]
    maps = [t for t in targets if t is not None]
    if len(maps) == len(targets):  # synthetic frames: what each pixel truly shows
        out["cam_class"] = torch.from_numpy(np.stack([classes for classes, _ in maps]))
        out["cam_depth"] = torch.from_numpy(np.stack([depth for _, depth in maps]))
    return out

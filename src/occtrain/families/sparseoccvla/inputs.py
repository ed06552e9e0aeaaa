"""What the sparse occupancy encoder reads besides a frames batch: the camera views of the
frames before it (Table 8's multi-frame input) and the ground truth of the frames after it
moved into its ego frame (App. A's extended-range supervision), from the dataset index."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from occtrain.data.clips import clip_rng
from occtrain.data.frames import camera_batch
from occtrain.data.layout import DatasetIndex
from occtrain.models.point_sets import occupied_points


def ego_to_global(x: float, y: float, yaw: float) -> np.ndarray:
    """The 4 x 4 transform of a planar ego pose (global x, y, yaw)."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = [x, y]
    return out


def frame_transform(index: DatasetIndex, scene: str, source: str, target: str) -> np.ndarray:
    """The 4 x 4 transform from sample ``source``'s ego frame to sample ``target``'s."""
    return np.linalg.inv(ego_to_global(*index.ego_pose(scene, target))) @ ego_to_global(*index.ego_pose(scene, source))


@dataclass
class CameraFrames:
    """The camera input of a batch over F frames (0 = the current one, then earlier ones):
    ``images`` uint8 (B, F, V, H, W, 3), ``intrinsics`` (B, F, V, 3, 3), ``cam_to_ego``
    (B, F, V, 4, 4) to that frame's ego frame, and ``current_to_frame`` (B, F, 4, 4) from
    the current ego frame to frame f's."""

    images: torch.Tensor
    intrinsics: torch.Tensor
    cam_to_ego: torch.Tensor
    current_to_frame: torch.Tensor


def camera_frames(batch: dict[str, Any], index: DatasetIndex | None, frames: int) -> CameraFrames:
    """The batch's cameras, and with ``frames`` > 1 those of the frames before each sample
    (a scene's first frames repeat its first)."""
    views = [[batch["images"]], [batch["intrinsics"]], [batch["cam_to_ego"]]]
    dev = batch["images"].device  # earlier frames are read from disk, onto the batch's device
    moves = [torch.eye(4, device=dev).expand(len(batch["meta"]), 4, 4)]
    for back in range(1, frames):
        if index is None:
            raise ValueError("earlier frames are read from the dataset: pass its index")
        samples, transforms = [], []
        for meta in batch["meta"]:
            tokens = index.scenes[meta["scene"]]
            earlier = tokens[max(0, int(meta["index"]) - back)]
            samples.append((meta["scene"], earlier))
            transforms.append(frame_transform(index, meta["scene"], meta["token"], earlier))
        cams = camera_batch(index, samples)
        for slot, key in zip(views, ("images", "intrinsics", "cam_to_ego")):
            slot.append(cams[key].to(dev))
        moves.append(torch.tensor(np.stack(transforms), dtype=torch.float32, device=dev))
    images, intrinsics, cam_to_ego = (torch.stack(v, 1) for v in views)
    return CameraFrames(images, intrinsics, cam_to_ego, torch.stack(moves, 1))


def ground_truth(
    batch: dict[str, Any],
    index: DatasetIndex | None,
    count: int,
    extended: int,
    seed: int,
    keep: tuple[int, ...] = (),
    keep_share: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each sample's sparsified ground-truth point set: ``count`` occupied voxel centres of
    its frame and, with ``extended`` > 0, of the next ``extended`` frames of its scene moved
    into its ego frame by the poses (the draw seeded by ``seed`` and the sample token),
    voxels of the ``keep`` classes taken first, up to ``keep_share`` of the points
    (``occupied_points``).
    Returns points (B, K, 3), classes (B, K) and which are real (B, K)."""
    out = []
    for b, meta in enumerate(batch["meta"]):
        rng = clip_rng(seed, meta["token"])
        points, classes, n = occupied_points(batch["semantics"][b].cpu().numpy(), count, rng, keep, keep_share)
        if extended and index is not None:
            more = _later_points(index, meta, count, extended, rng, keep, keep_share)
            if more is not None:
                # One draw over the union: the current frame keeps its share of the points,
                # the kept classes first.
                all_points = torch.cat([points[:n], more[0]])
                all_classes = torch.cat([classes[:n], more[1]])
                order = torch.from_numpy(rng.permutation(len(all_points)))
                kept = torch.isin(all_classes[order], torch.tensor(keep, dtype=torch.long))
                kept &= kept.cumsum(0) <= int(count * keep_share)
                pick = torch.cat([order[kept], order[~kept]])[:count]
                points, classes, n = _padded(all_points[pick], all_classes[pick], count)
        out.append((points, classes, torch.arange(count) < n))
    points, classes, real = (torch.stack(t) for t in zip(*out))
    return points, classes, real


def _later_points(
    index: DatasetIndex,
    meta: dict,
    count: int,
    extended: int,
    rng: np.random.Generator,
    keep: tuple[int, ...] = (),
    keep_share: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    tokens = index.scenes[meta["scene"]]
    later = tokens[int(meta["index"]) + 1 : int(meta["index"]) + 1 + extended]
    points, classes = [], []
    for token in later:
        p, c, n = occupied_points(index.labels(meta["scene"], token)["semantics"], count, rng, keep, keep_share)
        move = torch.tensor(frame_transform(index, meta["scene"], token, meta["token"]), dtype=torch.float32)
        points.append(p[:n] @ move[:3, :3].T + move[:3, 3])
        classes.append(c[:n])
    return (torch.cat(points), torch.cat(classes)) if points else None


def _padded(points: torch.Tensor, classes: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    n = len(points)
    if n == 0:
        return torch.zeros(count, 3), torch.zeros(count, dtype=torch.long), 0
    if n >= count:
        return points[:count], classes[:count], count
    return torch.cat([points, points[:1].expand(count - n, 3)]), torch.cat([classes, classes[:1].expand(count - n)]), n

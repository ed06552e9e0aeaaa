"""Occupancy as sets of 3D points: the ground-truth points of a label volume, the Chamfer
distance and focal loss a point-set encoder trains with, and voxelization back to labels.

SparseOccVLA (like OPUS and SparseWorld before it) predicts occupancy as points with
classes rather than as a dense grid. Its encoder's points are supervised with the
Chamfer distance to the scene's occupied voxel centres (Eq. 1) and each point's class with
a focal loss against the label of the ground-truth point it is matched to (the nearest);
the points are voxelized into the 200 x 200 x 16 grid to be scored like any other
occupancy. Points are in metres in the ego frame (``occtrain.formats.occ3d``'s grid).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from occtrain.formats.occ3d import FREE, GRID_SHAPE, RANGE_MAX, RANGE_MIN, VOXEL_SIZE
from occtrain.models.projection import lift

#: The classes a point can take: every Occ3D class but free (a point is occupied space).
POINT_CLASSES = FREE

#: How far past a depth map's surface a lifted pixel is placed (metres). Depth maps hold
#: centimetres: 2 cm lands inside the voxel the pixel shows but for rays that clip a
#: corner (1.7 % of a frame's lifted voxels; a quarter voxel, 10 cm, missed 5.6 %).
LIFT_BEYOND_M = 0.02

_LOW = torch.tensor(RANGE_MIN, dtype=torch.float32)
_HIGH = torch.tensor(RANGE_MAX, dtype=torch.float32)


def voxel_centres(indices: torch.Tensor) -> torch.Tensor:
    """Integer voxel indices (..., 3) -> their centres in metres (..., 3)."""
    return _LOW.to(indices.device) + VOXEL_SIZE * (indices.float() + 0.5)


def occupied_points(
    semantics: np.ndarray | torch.Tensor,
    count: int,
    rng: np.random.Generator,
    keep: tuple[int, ...] = (),
    keep_share: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """A sparsified ground-truth point set of one label volume (X, Y, Z): the centres of
    ``count`` occupied voxels drawn without replacement (every one when there are fewer),
    their classes, and how many are real (the rest repeat the first, to stack batches).
    Voxels of the ``keep`` classes are taken before any other is drawn, up to
    ``keep_share`` of ``count`` (a uniform draw leaves a car a handful of points among a
    scene's 10^5 voxels; all of them can crowd the rest of the scene out). Returns
    Float[count, 3], Long[count], n."""
    sem = torch.as_tensor(np.asarray(semantics)).long()
    occupied = (sem != FREE).nonzero()
    n = min(count, occupied.shape[0])
    if n == 0:
        return torch.zeros(count, 3), torch.zeros(count, dtype=torch.long), 0
    if occupied.shape[0] <= count:
        pick = torch.arange(n)
    else:
        classes = sem[occupied[:, 0], occupied[:, 1], occupied[:, 2]]
        is_kept = torch.isin(classes, torch.tensor(keep, dtype=torch.long))
        kept = is_kept.nonzero().squeeze(1)
        cap = min(len(kept), int(count * keep_share))
        if cap < len(kept):
            kept = kept[torch.from_numpy(rng.choice(len(kept), size=cap, replace=False))]
        if cap == count:
            pick = kept
        else:
            others = torch.ones(len(classes), dtype=torch.bool)
            others[kept] = False
            rest = others.nonzero().squeeze(1)
            drawn = rest[torch.from_numpy(rng.choice(len(rest), size=count - cap, replace=False))]
            pick = torch.cat([kept, drawn]) if cap else drawn
    chosen = occupied[pick]
    chosen = torch.cat([chosen, chosen[:1].expand(count - n, 3)]) if n < count else chosen
    return voxel_centres(chosen), sem[chosen[:, 0], chosen[:, 1], chosen[:, 2]], n


@torch.no_grad()
def nearest(
    src: torch.Tensor, dst: torch.Tensor, dst_valid: torch.Tensor | None = None, chunk: int = 4096
) -> torch.Tensor:
    """For each point of ``src`` (B, M, 3) the index of its nearest point of ``dst`` (B, K, 3)
    (Euclidean, over the ``dst_valid`` ones; 0 where a sample has none).

    On the CPU through a k-d tree (scikit-learn's): the dense M x K distances of a
    forecaster frame's 4 x 4096 points against 2048 took 0.4 s, the tree 57-91 ms (both exact;
    `tools/bench/sparseoccvla.py chamfer`). On an accelerator by dense distances, in chunks
    so that M x K never sits in memory."""
    if src.device.type == "cpu":
        return _nearest_by_tree(src, dst, dst_valid)
    return _nearest_dense(src, dst, dst_valid, chunk)


def _nearest_dense(
    src: torch.Tensor, dst: torch.Tensor, dst_valid: torch.Tensor | None = None, chunk: int = 4096
) -> torch.Tensor:
    out = torch.empty(src.shape[:2], dtype=torch.long, device=src.device)
    for i in range(0, src.shape[1], chunk):
        d = torch.cdist(src[:, i : i + chunk].detach().float(), dst.detach().float())
        if dst_valid is not None:
            d = d.masked_fill(~dst_valid[:, None, :], float("inf"))
        out[:, i : i + chunk] = d.argmin(-1)
    return out


def _nearest_by_tree(src: torch.Tensor, dst: torch.Tensor, dst_valid: torch.Tensor | None = None) -> torch.Tensor:
    from sklearn.neighbors import KDTree  # here: importing scikit-learn takes seconds, and few commands need it

    out = torch.zeros(src.shape[:2], dtype=torch.long)
    for b in range(src.shape[0]):
        keep = torch.arange(dst.shape[1]) if dst_valid is None else dst_valid[b].nonzero().squeeze(1).cpu()
        if len(keep):
            tree = KDTree(dst[b, keep].detach().double().numpy())
            out[b] = keep[torch.from_numpy(tree.query(src[b].detach().double().numpy(), return_distance=False)[:, 0])]
    return out


def chamfer_distance(
    pred: torch.Tensor,
    gt: torch.Tensor,
    gt_valid: torch.Tensor | None = None,
    reduction: str = "mean",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Chamfer distance of Eq. 1 between point sets ``pred`` (B, M, 3) and ``gt`` (B, K, 3):
    the squared distance from each predicted point to its nearest ground-truth point plus
    from each (valid) ground-truth point to its nearest predicted point.

    ``reduction="sum"`` adds the two sums as Eq. 1 writes them; ``"mean"`` adds the two
    means (the scale a loss weight can be set for whatever the point counts). Returns the
    distance per sample (B,) and, for each predicted point, the index of its nearest
    ground-truth point (what its class is matched to). Exact: the nearest pairs are found
    without gradient and the distance is taken on them with it.
    """
    if reduction not in ("sum", "mean"):
        raise ValueError(f"reduction must be sum or mean, got {reduction!r}")
    valid = torch.ones(gt.shape[:2], dtype=torch.bool, device=gt.device) if gt_valid is None else gt_valid.bool()
    to_gt = nearest(pred, gt, valid)
    to_pred = nearest(gt, pred)
    forward = (pred - torch.gather(gt, 1, to_gt[..., None].expand_as(pred))).pow(2).sum(-1)  # (B, M)
    backward = (gt - torch.gather(pred, 1, to_pred[..., None].expand_as(gt))).pow(2).sum(-1) * valid  # (B, K)
    if reduction == "sum":
        return forward.sum(1) + backward.sum(1), to_gt
    return forward.mean(1) + backward.sum(1) / valid.sum(1).clamp(min=1), to_gt


def sigmoid_focal_loss(
    logits: torch.Tensor, labels: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0
) -> torch.Tensor:
    """The focal loss (Lin et al.) of class logits (..., C) against integer labels (...),
    one sigmoid per class as OPUS and the mmdetection focal loss compute it:
    ``-alpha_t (1 - p_t)^gamma log p_t`` summed over the C classes; mean over the points."""
    target = F.one_hot(labels.long(), logits.shape[-1]).to(logits.dtype)
    p = logits.sigmoid()
    ce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    p_t = p * target + (1 - p) * (1 - target)
    alpha_t = alpha * target + (1 - alpha) * (1 - target)
    return (alpha_t * (1 - p_t).pow(gamma) * ce).sum(-1).mean()


def voxelize(
    points: torch.Tensor,
    classes: torch.Tensor,
    extent: tuple[int, int, int] = (1, 1, 1),
    background: torch.Tensor | None = None,
) -> torch.Tensor:
    """Points (M, 3) in metres with their classes (M,) -> a label volume (X, Y, Z), free
    where no point falls, or ``background`` (X, Y, Z) there (the per-voxel prior: a point
    set says nothing of the voxels it leaves uncovered). Each point votes for its class in
    the voxel it lies in, or with ``extent`` (ex, ey, ez) in a box of that many voxels
    around it (a coarse point set covering its neighbourhood); a voxel takes its most voted
    class (the lowest on a tie). Points outside the grid are dropped."""
    grid = torch.tensor(GRID_SHAPE, device=points.device)
    base = torch.floor((points.float() - _LOW.to(points.device)) / VOXEL_SIZE).long()  # (M, 3)
    ex, ey, ez = (int(e) for e in extent)
    offsets = (
        torch.stack(
            torch.meshgrid(
                torch.arange(ex) - (ex - 1) // 2,
                torch.arange(ey) - (ey - 1) // 2,
                torch.arange(ez) - (ez - 1) // 2,
                indexing="ij",
            ),
            -1,
        )
        .reshape(-1, 3)
        .to(points.device)
    )
    cells = (base[:, None] + offsets[None]).reshape(-1, 3)
    labels = classes.long().repeat_interleave(offsets.shape[0])
    inside = ((cells >= 0) & (cells < grid)).all(-1)
    cells, labels = cells[inside], labels[inside]
    flat = (cells[:, 0] * GRID_SHAPE[1] + cells[:, 1]) * GRID_SHAPE[2] + cells[:, 2]
    # Votes per (voxel, class) pair, then per voxel the pair with the most votes (ties to the lowest class).
    pairs, votes = torch.unique(flat * POINT_CLASSES + labels, return_counts=True)
    voxel, label = pairs // POINT_CLASSES, pairs % POINT_CLASSES
    rank = votes * POINT_CLASSES + (POINT_CLASSES - 1 - label)
    size = int(np.prod(GRID_SHAPE))
    best = torch.full((size,), -1, dtype=torch.long, device=points.device).scatter_reduce(0, voxel, rank, "amax")
    win = rank == best[voxel]
    if background is None:
        out = torch.full((size,), FREE, dtype=torch.long, device=points.device)
    else:
        out = background.to(points.device).long().reshape(-1).clone()
    out[voxel[win]] = label[win]
    return out.view(GRID_SHAPE)


def lifted_pixels(
    classes: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_to_ego: torch.Tensor,
    background: torch.Tensor | None = None,
    extent: tuple[int, int, int] = (1, 1, 1),
) -> torch.Tensor:
    """Per-pixel classes and camera-z depths (B, V, H, W) of V calibrated cameras -> label
    volumes (B, X, Y, Z): each pixel with a surface votes its class in the voxel just past
    the surface along its ray (``LIFT_BEYOND_M``: inside the voxel it shows), ``background``
    (or free) where none lands."""
    points = lift(depth.to(intrinsics.device), intrinsics, cam_to_ego, beyond=LIFT_BEYOND_M)
    seen = (depth > 0) & (classes.long() != FREE)
    return torch.stack(
        [
            voxelize(p[s], c.to(p.device).long()[s], extent, background)
            for p, c, s in zip(points, classes, seen.to(points.device))
        ]
    )


__all__ = [
    "lifted_pixels",
    "POINT_CLASSES",
    "chamfer_distance",
    "nearest",
    "occupied_points",
    "sigmoid_focal_loss",
    "voxel_centres",
    "voxelize",
]

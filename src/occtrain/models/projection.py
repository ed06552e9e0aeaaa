"""Ego-frame 3D points into the surround cameras, and image features read where they land.

Batched torch counterparts of ``data.cameras.Camera.project``: a query-based encoder
samples its image features at its points' projections (SparseBEV's feature sampling), and a
distillation branch reads a frozen teacher's features there. Conventions are
``data.cameras``': ego (x forward, y left, z up), camera (x right, y down, z forward),
pixels (u right, v down, pixel centres at +0.5).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: Closer to the camera plane than this (metres), a point counts as behind it.
MIN_DEPTH = 1e-3


def in_cameras(points: torch.Tensor, cam_to_ego: torch.Tensor) -> torch.Tensor:
    """Points (B, N, 3) in the ego frame -> in each of V cameras' frames (B, V, N, 3); the
    last coordinate is the point's depth along that camera's axis."""
    ego_to_cam = torch.linalg.inv(cam_to_ego.float())
    rot, shift = ego_to_cam[..., :3, :3], ego_to_cam[..., :3, 3]
    return torch.einsum("bvij,bnj->bvni", rot, points.float()) + shift[:, :, None]


def project(
    points: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor, image_hw: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (B, N, 3) in the ego frame -> pixel coordinates (B, V, N, 2) in each of V
    cameras (``intrinsics`` (B, V, 3, 3), ``cam_to_ego`` (B, V, 4, 4)) and whether each
    lands inside the ``image_hw`` image in front of the camera (B, V, N)."""
    cam = in_cameras(points, cam_to_ego)
    depth = cam[..., 2]
    pix = torch.einsum("bvij,bvnj->bvni", intrinsics.float(), cam)
    uv = pix[..., :2] / depth.clamp(min=MIN_DEPTH)[..., None]
    h, w = image_hw
    inside = (depth > MIN_DEPTH) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    return uv, inside


def lift(depth: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor, beyond: float = 0.0) -> torch.Tensor:
    """Every pixel centre of V cameras at its camera-z ``depth`` (B, V, H, W) -> ego-frame
    points (B, V, H, W, 3): the inverse of :func:`project`. ``beyond`` (metres) moves each
    point that far further along its ray: a depth map's surface is a voxel's face, and a
    point just past it lies inside the voxel it shows."""
    b, v, h, w = depth.shape
    dev = depth.device
    vv, uu = torch.meshgrid(torch.arange(h, device=dev) + 0.5, torch.arange(w, device=dev) + 0.5, indexing="ij")
    pixels = torch.stack([uu, vv, torch.ones_like(uu)], -1)  # (H, W, 3)
    rays = torch.einsum("bvij,hwj->bvhwi", torch.linalg.inv(intrinsics.float()), pixels)  # camera z = 1
    length = rays.norm(dim=-1)  # metres along the ray per metre of camera z
    z = depth.float() + beyond / length
    cam = rays * z[..., None]
    rot, shift = cam_to_ego[..., :3, :3].float(), cam_to_ego[..., :3, 3].float()
    return torch.einsum("bvij,bvhwj->bvhwi", rot, cam) + shift[:, :, None, None]


def read_views(features: torch.Tensor, uv: torch.Tensor, image_hw: tuple[int, int]) -> torch.Tensor:
    """Bilinear samples (B, V, N, C) of per-camera feature maps ``features`` (B, V, C, h, w),
    which cover the ``image_hw`` image, at pixels ``uv`` (B, V, N, 2) of each camera."""
    b, v, c, fh, fw = features.shape
    h, w = image_hw
    grid = torch.stack([uv[..., 0] / w * 2 - 1, uv[..., 1] / h * 2 - 1], -1).reshape(b * v, 1, -1, 2)
    sampled = F.grid_sample(
        features.reshape(b * v, c, fh, fw), grid.to(features.dtype), mode="bilinear", align_corners=False
    )
    return sampled.reshape(b, v, c, -1).permute(0, 1, 3, 2)


def average_views(sampled: torch.Tensor, inside: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera samples (B, V, N, C) averaged over the cameras each point is ``inside``
    (B, V, N): (B, N, C) and whether any camera sees the point (B, N); a point no camera
    sees reads zeros."""
    weight = inside.to(sampled.dtype)[..., None]
    seen = weight.sum(1)  # (B, N, 1)
    return (sampled * weight).sum(1) / seen.clamp(min=1), seen[..., 0] > 0


def sample_views(
    features: torch.Tensor, uv: torch.Tensor, inside: torch.Tensor, image_hw: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear samples of per-camera feature maps ``features`` (B, V, C, h, w), which cover
    the ``image_hw`` image, at pixels ``uv`` (B, V, N, 2), averaged over the cameras each
    point is ``inside`` (B, V, N). Returns (B, N, C) and whether any camera sees the point
    (B, N); a point no camera sees reads zeros."""
    return average_views(read_views(features, uv, image_hw), inside)


__all__ = ["average_views", "in_cameras", "lift", "project", "read_views", "sample_views"]

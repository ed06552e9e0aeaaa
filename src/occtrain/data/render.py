"""Bird's-eye pictures of occupancy in the usual Occ3D colours, with the ego and its plan."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from occtrain.formats.occ3d import CLASS_COLORS, CLASS_NAMES, EGO_LENGTH, EGO_WIDTH, FREE, GRID_SHAPE, VOXEL_SIZE

UNSEEN_TINT = 0.55  # how dark camera-invisible columns are drawn when a mask is given


def top_down_classes(semantics: np.ndarray) -> np.ndarray:
    """(X, Y) class of the highest non-free voxel in each column; free where the column is empty."""
    occupied = semantics != FREE
    z = semantics.shape[-1]
    highest = z - 1 - np.argmax(occupied[..., ::-1], axis=-1)
    top = np.take_along_axis(semantics, highest[..., None], axis=-1)[..., 0]
    return np.where(occupied.any(-1), top, FREE).astype(np.uint8)


def _ego_to_pixel(xy: np.ndarray, scale: int) -> np.ndarray:
    """Ego-frame metres -> image pixels (x forward is up, y left is left)."""
    x_idx = (np.asarray(xy)[..., 0] + GRID_SHAPE[0] * VOXEL_SIZE / 2) / VOXEL_SIZE
    y_idx = (np.asarray(xy)[..., 1] + GRID_SHAPE[1] * VOXEL_SIZE / 2) / VOXEL_SIZE
    return np.stack([(GRID_SHAPE[1] - y_idx) * scale, (GRID_SHAPE[0] - x_idx) * scale], axis=-1)


def render_bev(
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    trajectory: Sequence[Sequence[float]] | None = None,
    trajectory_mask: Sequence[int] | None = None,
    scale: int = 3,
    title: str | None = None,
    plan: Sequence[Sequence[float]] | None = None,
) -> Image.Image:
    """One frame as a top-down RGB picture; ``mask`` (X,Y,Z) darkens columns the camera never
    sees; ``trajectory`` (the true future, green) and ``plan`` (a model's, red) are drawn on it."""
    rgb = CLASS_COLORS[top_down_classes(semantics)].astype(np.float32)
    if mask is not None:
        seen = mask.astype(bool).any(-1)
        rgb[~seen] *= UNSEEN_TINT
    # Rows: x forward goes up; columns: y left goes left.
    img = Image.fromarray(rgb[::-1, ::-1].astype(np.uint8)).resize(
        (GRID_SHAPE[1] * scale, GRID_SHAPE[0] * scale), Image.Resampling.NEAREST
    )
    draw = ImageDraw.Draw(img)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [EGO_LENGTH / 2, EGO_WIDTH / 2]
    draw.polygon([tuple(p) for p in _ego_to_pixel(corners, scale)], fill=(30, 30, 30), outline=(255, 255, 255))
    for points, mask_, (line, dot) in (
        (trajectory, trajectory_mask, ((0, 200, 80), (0, 110, 40))),
        (plan, None, ((230, 40, 40), (150, 0, 0))),
    ):
        if points is None:
            continue
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        keep = np.ones(len(pts), bool) if mask_ is None else np.asarray(mask_, bool)
        px = _ego_to_pixel(np.vstack([[0.0, 0.0], pts[keep]]), scale)
        if len(px) > 1:  # a white casing keeps the line visible on any class colour
            draw.line([tuple(p) for p in px], fill=(255, 255, 255), width=max(2, scale) + 2)
            draw.line([tuple(p) for p in px], fill=line, width=max(2, scale))
        for p in px[1:]:
            r = 1.5 * scale + 1
            draw.ellipse([p[0] - r, p[1] - r, p[0] + r, p[1] + r], fill=dot, outline=(255, 255, 255))
    if title:
        draw.rectangle([0, 0, img.width, 14 + scale], fill=(0, 0, 0))
        draw.text((4, 2), title, fill=(255, 255, 255))
    return img


def legend(classes: Sequence[int], width: int) -> Image.Image:
    """A strip naming the colours of ``classes``."""
    per_row = max(1, width // 150)
    rows = (len(classes) + per_row - 1) // per_row
    img = Image.new("RGB", (width, 6 + 18 * rows), (250, 250, 250))
    draw = ImageDraw.Draw(img)
    for i, c in enumerate(classes):
        x, y = 6 + (i % per_row) * 150, 4 + (i // per_row) * 18
        draw.rectangle([x, y, x + 12, y + 12], fill=tuple(int(v) for v in CLASS_COLORS[c]), outline=(60, 60, 60))
        draw.text((x + 17, y), CLASS_NAMES[c], fill=(0, 0, 0))
    return img


#: Where each camera sits around the bird's-eye view: the front three above, the back three
#: below, each row as a driver would turn to see it (left to right).
SURROUND_ROWS = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))


def surround(views: dict[str, np.ndarray], bev: Image.Image, gap: int = 4) -> Image.Image:
    """The six camera images (name -> (H, W, 3) uint8) around a bird's-eye picture; the
    views are scaled so each row spans at least the picture's width."""
    h, w = next(iter(views.values())).shape[:2]
    scale = max(1, int(np.ceil((bev.width - 2 * gap) / (3 * w))))
    tiles = {
        name: Image.fromarray(img).resize((w * scale, h * scale), Image.Resampling.NEAREST)
        for name, img in views.items()
    }
    row_w = 3 * w * scale + 2 * gap
    width = max(row_w, bev.width)
    out = Image.new("RGB", (width, 2 * h * scale + bev.height + 2 * gap), (255, 255, 255))
    draw = ImageDraw.Draw(out)
    for names, top in zip(SURROUND_ROWS, (0, h * scale + bev.height + 2 * gap)):
        x = (width - row_w) // 2
        for name in names:
            out.paste(tiles[name], (x, top))
            draw.text((x + 3, top + 2), name, fill=(255, 255, 255))
            x += w * scale + gap
    out.paste(bev, ((width - bev.width) // 2, h * scale + gap))
    return out


def strip(images: Sequence[Image.Image], classes: Sequence[int] | None = None, gap: int = 4) -> Image.Image:
    """Pictures side by side, with an optional colour legend underneath."""
    w = sum(i.width for i in images) + gap * (len(images) - 1)
    h = max(i.height for i in images)
    key = legend(classes, w) if classes else None
    out = Image.new("RGB", (w, h + (key.height if key else 0)), (255, 255, 255))
    x = 0
    for im in images:
        out.paste(im, (x, 0))
        x += im.width + gap
    if key:
        out.paste(key, (0, h))
    return out

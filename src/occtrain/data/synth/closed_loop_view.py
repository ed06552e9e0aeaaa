"""A bird's-eye view of a closed-loop episode: one picture per planning frame, saved as a GIF.

The view is the ego's (its heading up, ``SPAN`` metres across): the city raster in the
camera palette, the other agents as boxes (vehicles, cyclists, pedestrians, placed
objects), the stop lines of the route in their light's colour, the ego in white with its
plan in cyan and the route ahead in yellow, and each infraction written over the frame it
happened in, the ego ringed in red. Pillow draws the frames and writes the GIF.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from occtrain.data.geometry import ego_to_global, global_to_ego
from occtrain.data.synth.camera_render import CAMERA_COLOURS, LIGHT_COLOURS
from occtrain.formats.occ3d import EGO_LENGTH, EGO_WIDTH, FREE
from occtrain.metrics.closed_loop_scores import Infraction

#: Pixels across the picture and metres they span; the ego sits a quarter up from the bottom.
PIXELS = 320
SPAN = 64.0
EGO_AT = 0.75
PLAN_COLOUR = (40, 220, 240)
ROUTE_COLOUR = (240, 220, 60)
EGO_COLOUR = (250, 250, 250)
ALERT_COLOUR = (235, 40, 30)


@dataclass
class ViewFrame:
    """What one picture shows: the ego, its plan and the route ahead (global), everyone else, what went wrong."""

    time: float
    ego_xy: np.ndarray
    ego_yaw: float
    speed: float
    command: str
    plan: np.ndarray  # (K, 2) global
    route: np.ndarray  # (M, 2) global
    agents_xy: np.ndarray
    agents_yaw: np.ndarray
    agents_size: np.ndarray
    agents_cls: np.ndarray
    infractions: list[Infraction]
    #: The route's stop lines ahead: (global xy, heading, "red" / "amber" / "green").
    lights: list[tuple[np.ndarray, float, str]] = field(default_factory=list)


def _to_pixels(points: np.ndarray, frame: ViewFrame) -> np.ndarray:
    """Global points -> picture pixels (x right, y down), the ego's heading up."""
    local = global_to_ego(points, frame.ego_xy, frame.ego_yaw)
    scale = PIXELS / SPAN
    return np.stack([PIXELS / 2 - local[..., 1] * scale, PIXELS * EGO_AT - local[..., 0] * scale], axis=-1)


def _background(static, frame: ViewFrame) -> np.ndarray:
    """(PIXELS, PIXELS, 3) uint8: the static raster under the view, in the camera palette."""
    scale = SPAN / PIXELS
    col, row = np.meshgrid(np.arange(PIXELS) + 0.5, np.arange(PIXELS) + 0.5)
    local = np.stack([(PIXELS * EGO_AT - row) * scale, (PIXELS / 2 - col) * scale], axis=-1)
    ix, iy = static.cells(ego_to_global(local, frame.ego_xy, frame.ego_yaw))
    cls = np.where(static.cls[ix, iy] != FREE, static.cls[ix, iy], static.ground[ix, iy])
    return CAMERA_COLOURS[np.minimum(cls, len(CAMERA_COLOURS) - 1)].astype(np.uint8)


def _box(xy: np.ndarray, yaw: float, length: float, width: float) -> np.ndarray:
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    return ego_to_global(corners, xy, yaw)


def render_view(static, frame: ViewFrame) -> Image.Image:
    """The picture of one planning frame."""
    image = Image.fromarray(_background(static, frame))
    draw = ImageDraw.Draw(image)
    for xy, yaw, size, cls in zip(frame.agents_xy, frame.agents_yaw, frame.agents_size, frame.agents_cls):
        if np.max(np.abs(global_to_ego(xy, frame.ego_xy, frame.ego_yaw))) > SPAN:
            continue
        poly = _to_pixels(_box(xy, float(yaw), size[0], size[1]), frame)
        colour = tuple(int(c) for c in CAMERA_COLOURS[int(cls)])
        draw.polygon([tuple(p) for p in poly], fill=colour, outline=(20, 20, 20))
    for xy, heading, state in frame.lights:
        bar = _to_pixels(_box(xy, heading, 1.0, 3.5), frame)
        draw.polygon([tuple(p) for p in bar], fill=LIGHT_COLOURS[state])
    for line, colour in ((frame.route, ROUTE_COLOUR), (frame.plan, PLAN_COLOUR)):
        if len(line):
            pts = _to_pixels(np.concatenate([frame.ego_xy[None], line]), frame)
            draw.line([tuple(p) for p in pts], fill=colour, width=2)
    ego = _to_pixels(_box(frame.ego_xy, frame.ego_yaw, EGO_LENGTH, EGO_WIDTH), frame)
    draw.polygon([tuple(p) for p in ego], fill=EGO_COLOUR, outline=(0, 0, 0))
    draw.text((6, 4), f"t {frame.time:4.1f} s  {frame.speed:4.1f} m/s  {frame.command}", fill=(255, 255, 255))
    if frame.infractions:
        cx, cy = PIXELS / 2, PIXELS * EGO_AT
        r = 0.6 * EGO_LENGTH * PIXELS / SPAN + 6
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), outline=ALERT_COLOUR, width=3)
        for i, inf in enumerate(frame.infractions):
            text = inf.kind.replace("_", " ") + (f": {inf.other}" if inf.other else "")
            draw.text((6, PIXELS - 16 - 12 * i), text, fill=ALERT_COLOUR)
    return image


def save_gif(static, frames: list[ViewFrame], path: Path, seconds_per_frame: float) -> Path:
    """The episode's pictures as a looping GIF at ``path`` (written whole, then moved into place)."""
    if not frames:
        raise ValueError("an episode animation needs at least one frame")
    pictures = [render_view(static, f) for f in frames]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    pictures[0].save(
        tmp, format="GIF", save_all=True, append_images=pictures[1:], duration=int(seconds_per_frame * 1000), loop=0
    )
    tmp.replace(path)
    return path

"""A clip sample as stages see it, the parts a prompt is made of, and the planning targets.

A clip is history frames, the anchor frame and future frames with the anchor's annotation,
its NuScenes-QA questions and its narration. A family's tasks turn a clip into parts
(text, an occupancy scene by clip frame, waypoints), each marked as the answer or not; the
parts know nothing of token ids. The planning target (the ego's future with its validity
mask and the agents' future boxes for the collision check) is built here, once, for every
stage and evaluator that scores a plan.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from occtrain.data.geometry import global_to_ego
from occtrain.data.layout import DatasetIndex
from occtrain.data.schema import QAQuestion
from occtrain.formats.occ3d import FUTURE_STEPS, PAST_STEPS


class PromptPart:
    """One piece of a prompt: a frozen dataclass with a ``supervise`` field (whether it is
    the answer, trained and generated). A family adds a kind of its own by subclassing this
    and laying it out in its sequence builder's ``lay``; core and engine need no edit."""

    supervise: bool
    #: Whether the parts after it read it. One that only trains (OccVLA's occupancy
    #: queries, seen by nothing after them) is left out of a prompt at inference.
    read_after: ClassVar[bool] = True


#: Any part of a prompt (the name the builders and the engine type their parts with).
Part = PromptPart


@dataclass(frozen=True)
class Text(PromptPart):
    text: str
    supervise: bool = False


def text_of(part: PromptPart) -> str:
    """The text of a part a task laid out as text (a question, a reference answer)."""
    if not isinstance(part, Text):
        raise TypeError(f"expected a Text part, got {type(part).__name__}")
    return part.text


@dataclass(frozen=True)
class Scene(PromptPart):
    """The occupancy scene of clip frame ``frame`` (0 = oldest history frame)."""

    frame: int
    supervise: bool = False


@dataclass(frozen=True)
class Actions(PromptPart):
    """Waypoints in metres, ego frame of the anchor, shape (N, 2). With ``base`` (N, 2),
    e.g. the constant-velocity plan, the tokens hold each waypoint's offset from it, and a
    generated block is read back as base + offset."""

    xy: tuple[tuple[float, float], ...]
    supervise: bool = False
    base: tuple[tuple[float, float], ...] | None = None


@dataclass(frozen=True)
class Branch(PromptPart):
    """The parts after it, up to the next Branch, form one branch: they see the parts before
    the first Branch (the shared context) and themselves only. Several answers about one
    context then train in one sequence exactly as each would in its own."""

    supervise: bool = False  # never: a marker, not an answer


@dataclass
class Clip:
    """One clip sample as the stages receive it (see ``collate_clips``)."""

    ann: dict
    qa: list[QAQuestion]
    narration: str

    @property
    def anchor(self) -> dict:
        return self.ann["anchor"]

    @property
    def anchor_index(self) -> int:
        return int(self.ann["history"])

    def ego_steps(self) -> np.ndarray:
        """(T-1, 2): the ego's move from each clip frame to the next, in that frame's ego axes."""
        poses = np.asarray(self.ann["ego_poses"], dtype=np.float64)  # (T, 3): x, y, yaw (global)
        steps = [global_to_ego(poses[i + 1, :2], poses[i, :2], poses[i, 2]) for i in range(len(poses) - 1)]
        return np.asarray(steps).reshape(-1, 2)

    def ego_positions(self) -> np.ndarray:
        """(T, 2): the ego's position at each clip frame, in the anchor's ego axes."""
        poses = np.asarray(self.ann["ego_poses"], dtype=np.float64)
        a = self.anchor_index
        return np.asarray(global_to_ego(poses[:, :2], poses[a, :2], poses[a, 2])).reshape(-1, 2)


def clip_rng(seed: int, token: str) -> np.random.Generator:
    """The random draws of one clip (which task, which question, ...): fixed by the seed and
    the clip's sample token, so they do not depend on batch size, order or DDP rank."""
    return np.random.default_rng([seed, zlib.crc32(token.encode())])


def clips_from_batch(batch: dict) -> list[Clip]:
    """The per-sample clip records of a collated clip batch."""
    return [Clip(ann, qa, narr) for ann, qa, narr in zip(batch["ann"], batch["qa"], batch["narration"])]


def clip_annotation(
    index: DatasetIndex, scene: str, anchor: int, history: int, future: int, split: str, frames: list | None
) -> dict:
    """The ``ann.json`` of the clip of ``scene`` anchored at sample ``anchor`` with ``history``
    frames before it and ``future`` after (the caller keeps both inside the scene)."""
    tokens = index.scenes[scene]
    window = tokens[anchor - history : anchor + future + 1]
    return {
        "anchor": frames[anchor] if frames else pose_anchor(index, scene, anchor),
        "tokens": window,
        "ego_poses": [list(index.ego_pose(scene, t)) for t in window],
        "history": history,
        "future": future,
        "split": split,
    }


def pose_anchor(index: DatasetIndex, scene: str, anchor: int) -> dict:
    """The anchor record of a scene without occtrain's sidecar: what the ego poses give
    (past and future waypoints in the anchor's ego frame, masked where the scene ends), so
    planning and its metrics work on a plain Occ3D release. Boxes, text and the driving
    command need the sidecar and stay absent."""
    tokens = index.scenes[scene]
    x, y, yaw = index.ego_pose(scene, tokens[anchor])

    def waypoints(positions: range, steps: int) -> tuple[list[list[float]], list[int]]:
        xy = [list(index.ego_pose(scene, tokens[i]))[:2] for i in positions if 0 <= i < len(tokens)]
        local = global_to_ego(np.asarray(xy).reshape(-1, 2), np.array([x, y]), yaw).tolist()
        mask = [1] * len(local) + [0] * (steps - len(local))
        return local + [[0.0, 0.0]] * (steps - len(local)), mask

    future, future_mask = waypoints(range(anchor + 1, anchor + FUTURE_STEPS + 1), FUTURE_STEPS)
    past_positions = range(anchor - PAST_STEPS, anchor)
    past_xy = [i for i in past_positions if i >= 0]
    past, _ = waypoints(range(past_xy[0], anchor) if past_xy else range(0), PAST_STEPS)
    missing = PAST_STEPS - len(past_xy)  # oldest first: the missing ones lead
    past = [[0.0, 0.0]] * missing + past[: len(past_xy)]
    return {
        "scene": scene,
        "token": tokens[anchor],
        "index": anchor,
        "ego_future": future,
        "ego_future_mask": future_mask,
        "ego_past": past,
        "ego_past_mask": [0] * missing + [1] * len(past_xy),
    }


def frame_clips(
    index: DatasetIndex, split: str, history: int, future: int = 0, partial_history: bool = True
) -> Iterator[Clip]:
    """A clip anchored at every frame of ``split`` that has ``future`` frames after it, with
    ``history`` frames before it; with ``partial_history`` also the frames at a scene's
    start, with fewer (what a question about the frame needs). The clips carry no
    occupancy; their scenes come from a code cache by sample token."""
    questions = index.questions_by_sample(split)
    for scene in index.splits.get(split, []):
        frames = index.frames(scene) if index.has_frame_annotations(scene) else None
        tokens = index.scenes[scene]
        for a in range(0 if partial_history else history, len(tokens) - future):
            ann = clip_annotation(index, scene, a, min(history, a), future, split, frames)
            yield Clip(ann, questions.get(tokens[a], []), ann["anchor"].get("narration", ""))


def ego_future(anchor: dict) -> tuple[np.ndarray, np.ndarray]:
    """The anchor's ego future (FUTURE_STEPS, 2) and its validity mask (zeros where unknown)."""
    future = np.zeros((FUTURE_STEPS, 2))
    mask = np.zeros(FUTURE_STEPS, dtype=bool)
    given = np.asarray(anchor.get("ego_future", []), dtype=np.float64).reshape(-1, 2)[:FUTURE_STEPS]
    future[: len(given)] = given
    mask[: len(given)] = np.asarray(anchor.get("ego_future_mask", [1] * len(given)), dtype=bool)[: len(given)]
    return future, mask


def future_agent_boxes(anchor: dict) -> list[np.ndarray]:
    """Per future step, the agents' boxes (N, 5: x, y, length, width, yaw) for the collision metric.

    Positions come from the annotated agent futures; the yaw stays the anchor's (the
    annotation carries no future headings). Static objects keep their place.
    """
    boxes = anchor.get("boxes", [])
    futures = anchor.get("agent_futures", [])
    masks = anchor.get("agent_future_mask", [])
    steps: list[np.ndarray] = []
    for t in range(FUTURE_STEPS):
        rows = []
        for i, b in enumerate(boxes):
            if i < len(futures) and masks[i][t]:
                x, y = futures[i][t]
            elif b.get("attribute", "") in ("", "parked"):
                x, y = b["center"][:2]
            else:
                continue  # a mover whose future is unknown at this step
            rows.append((x, y, b["size"][0], b["size"][1], b["yaw"]))
        steps.append(np.asarray(rows, dtype=np.float32).reshape(-1, 5))
    return steps


@dataclass
class PlanTarget:
    """What a plan is scored against, for a batch of anchors: ``traj`` Float[B, 6, 2],
    ``mask`` Bool[B, 6] and per anchor the agents' future boxes (``future_agent_boxes``)."""

    traj: torch.Tensor
    mask: torch.Tensor
    agents: list[list[np.ndarray]]

    def rows(self, rows: list[int]) -> PlanTarget:
        return PlanTarget(self.traj[rows], self.mask[rows], [self.agents[i] for i in rows])


def plan_target(anchors: list[dict], device: torch.device | str = "cpu") -> PlanTarget:
    """The planning ground truth of ``anchors``, on ``device``."""
    futures, masks = zip(*(ego_future(a) for a in anchors))
    return PlanTarget(
        torch.from_numpy(np.stack(futures)).float().to(device),
        torch.from_numpy(np.stack(masks)).to(device),
        [future_agent_boxes(a) for a in anchors],
    )

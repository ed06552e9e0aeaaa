"""What a predicted scene's query block may read besides its position in the sequence: the
scene before it, the last observed scene, and how far the ego has moved since each.

Training and generation track these by one rule (:class:`SceneTrack`): training from the
scenes and true waypoints a forecast lays out, generation from the prompt's scenes and the
scenes and waypoints it generated, so a model sees in generation the queries it was
trained on. ``moved_last_scene`` queries move the scene before by the ego's step;
``moved_observed_scene`` queries move the last observed scene by the ego's whole move
since it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

#: A move of the ego: metres, (x, y) in the axes of the prompt's anchor frame.
EgoStep = tuple[float, float]

#: What a scene's query block is made of ("next_scene" mode): learnable ``<scene_q_j>``
#: tokens (OccLLaMA's and Occ-LLM's), the scene before it, the scene before it moved by the
#: ego's step, or the observed present moved by the ego's move since it (see ``query_scene``).
SCENE_QUERIES = ("learned", "last_scene", "moved_last_scene", "moved_observed_scene")

#: Moves a scene (as the world model tracks it) by an ego step: ``core.protocols.SceneMover``'s.
Move = Callable[[torch.Tensor, EgoStep], torch.Tensor]


@dataclass(frozen=True)
class SceneContext:
    """What a predicted scene's query block may read (``LMWorldModel.scene_query_ids``).

    ``last_scene``: the scene before it as the world model tracks it (``tracked_scene``: its
    code ids in the codes layout, its raw codes in the patches layout, where an id names
    only a position; None: none); ``observed``: the same of the last prompt scene, the
    present the forecast starts from (None: none); ``step``: the ego's move from the scene
    before to this one, ``offset``: from the observed scene to this one (each None when no
    waypoint came before this scene)."""

    last_scene: torch.Tensor | None = None
    observed: torch.Tensor | None = None
    step: EgoStep | None = None
    offset: EgoStep | None = None


class SceneTrack:
    """The scenes of a sequence so far and where the ego stands, as they are laid out or
    generated. A prompt's scene is observed and is the frame the waypoints are written in
    (the ego at its origin); a predicted scene is where the waypoint before it put the ego."""

    def __init__(self) -> None:
        self.last: torch.Tensor | None = None
        self.observed: torch.Tensor | None = None
        self.at: EgoStep = (0.0, 0.0)
        self.next: EgoStep | None = None
        #: The last waypoint of the action block laid out or generated since the last scene
        #: (a position, any plan prior added back): what the next scene is fused with.
        self.waypoint: torch.Tensor | None = None

    def planned(self, xy: torch.Tensor) -> None:
        """Waypoints (N, 2) were laid out (or generated): the first is where the ego goes next."""
        if xy.numel():
            first = xy.reshape(-1, 2)[0]
            self.next = (float(first[0]), float(first[1]))
            self.waypoint = xy.reshape(-1, 2)[-1].detach().float().cpu()

    def context(self) -> SceneContext:
        """What the next predicted scene's query block reads."""
        step = None if self.next is None else (self.next[0] - self.at[0], self.next[1] - self.at[1])
        return SceneContext(self.last, self.observed, step, self.next)

    def scene(self, code_ids: torch.Tensor | None, predicted: bool) -> None:
        """A scene (as the world model tracks it: see ``SceneContext``) was laid out or generated."""
        self.last = code_ids
        if not predicted:
            self.observed, self.at = code_ids, (0.0, 0.0)
        elif self.next is not None:
            self.at = self.next
        self.next = self.waypoint = None


def query_source(mode: str, context: SceneContext) -> tuple[torch.Tensor, EgoStep | None] | None:
    """What a query block of ``SCENE_QUERIES`` mode ``mode`` is made from: the scene (as the
    world model tracks it) and the ego's move it is moved by (None: unmoved); None for the
    learnable queries, also when there is no such scene."""
    source = context.observed if mode == "moved_observed_scene" else context.last_scene
    if mode == "learned" or source is None:
        return None
    step = context.offset if mode == "moved_observed_scene" else context.step
    return source, None if mode == "last_scene" else step


def query_scene(mode: str, context: SceneContext, move: Move | None) -> torch.Tensor | None:
    """The scene a query block of ``SCENE_QUERIES`` mode ``mode`` holds, as the world model
    tracks scenes, or None: the learnable queries, also when there is no such scene; a scene
    unmoved when no waypoint came before this one. ``moved_*`` modes move through ``move``
    (the frozen tokenizer's: shifted and re-encoded)."""
    made = query_source(mode, context)
    if made is None:
        return None
    source, step = made
    if step is None:
        return source
    if move is None:
        raise ValueError(
            f"{mode} queries move scenes through the frozen tokenizer: build the world model through the engine"
        )
    return move(source, step).to(source.device)

"""The ego's step between scenes, as a sequence lays it out: what a predicted scene's
query block may read (``moved_last_scene`` queries move the scene before by it).

Training and generation track it by one rule (:class:`EgoTrack`): training from the true
waypoints a forecast lays out before each scene, generation from the waypoints it
generated, so a model sees in generation the queries it was trained on.
"""

from __future__ import annotations

import torch

#: The ego's move from the scene before a predicted scene to that scene: metres, (x, y) in
#: the axes of the prompt's anchor frame (the planned waypoint minus where the ego stood).
EgoStep = tuple[float, float]


class EgoTrack:
    """Where the ego stands at the last scene of a sequence and where the waypoints laid
    out since plan it next, so a predicted scene's query block can read the ego's step
    (training lays the true waypoints out, generation its own: the same rule reads both).

    A prompt's scene is the frame the waypoints are written in (the ego at the origin); a
    predicted scene is where its planned waypoint put the ego."""

    def __init__(self) -> None:
        self.at: EgoStep = (0.0, 0.0)
        self.next: EgoStep | None = None

    def planned(self, xy: torch.Tensor) -> None:
        """Waypoints (N, 2) were laid out (or generated): the first is where the ego goes next."""
        if xy.numel():
            self.next = (float(xy.reshape(-1, 2)[0, 0]), float(xy.reshape(-1, 2)[0, 1]))

    def step(self) -> EgoStep | None:
        """The ego's step from the last scene to the next (None: no waypoint since)."""
        if self.next is None:
            return None
        return (self.next[0] - self.at[0], self.next[1] - self.at[1])

    def scene(self, predicted: bool) -> None:
        """A scene was laid out: a predicted one where the plan put the ego, a prompt's one
        at the origin of the waypoints' frame."""
        if not predicted:
            self.at = (0.0, 0.0)
        elif self.next is not None:
            self.at = self.next
        self.next = None

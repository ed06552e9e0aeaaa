"""Waypoint quantisation into action-token bins: the one place of the action-bin quantizer."""

from __future__ import annotations

import torch

#: Where the bins lie: "range" puts the first bin's lower edge at ``low``; "zero" shifts
#: the bins by less than half a width so that 0 m is a bin centre (no move, no offset from
#: a prior, is then exact: with "range", 256 bins over [-40, 40] m put 0 on an edge and
#: "no offset" decodes to 0.16 m either side).
ACTION_GRIDS = ("zero", "range")


class ActionQuantizer:
    """Uniform bins per axis of width ``(high - low) / bins`` (OccLLaMA / DriveLM: 256
    bins), laid out by ``grid`` (``ACTION_GRIDS``).

    ``encode`` maps metres to bin indices, ``decode`` maps indices to bin centres, so a
    value inside the bins comes back within half a bin width. Values outside them are
    clamped into the first or last bin (they decode to that bin's centre).
    """

    def __init__(self, bins: int, low: tuple[float, float], high: tuple[float, float], grid: str = "zero"):
        if grid not in ACTION_GRIDS:
            raise ValueError(f"grid must be one of {ACTION_GRIDS}, got {grid!r}")
        self.bins, self.grid = int(bins), grid
        self.low = torch.tensor(low, dtype=torch.float64)
        self.high = torch.tensor(high, dtype=torch.float64)
        self.width = (self.high - self.low) / self.bins
        #: The first bin's lower edge per axis.
        self.edge = (torch.round(self.low / self.width) - 0.5) * self.width if grid == "zero" else self.low.clone()

    def encode(self, xy: torch.Tensor) -> torch.Tensor:
        """Float[..., 2] metres -> Long[..., 2] bin indices in [0, bins)."""
        idx = torch.floor((xy.double() - self.edge.to(xy.device)) / self.width.to(xy.device))
        return idx.clamp(0, self.bins - 1).long()

    def decode(self, ids: torch.Tensor) -> torch.Tensor:
        """Long[..., 2] bin indices -> Float[..., 2] bin centres in metres."""
        centre = self.edge.to(ids.device) + (ids.double() + 0.5) * self.width.to(ids.device)
        return centre.float()

    def to_json(self) -> dict:
        return {"bins": self.bins, "low": self.low.tolist(), "high": self.high.tolist(), "grid": self.grid}

    def expected_bin(self, logits: torch.Tensor, axis: int) -> int:
        """The bin holding the expected bin centre under ``softmax(logits)`` (one axis's bins)."""
        centres = self.edge[axis] + (torch.arange(self.bins, dtype=torch.float64) + 0.5) * self.width[axis]
        value = (logits.double().cpu().softmax(-1) * centres).sum()
        return int(torch.floor((value - self.edge[axis]) / self.width[axis]).clamp(0, self.bins - 1))

    def encode_moves(self, xy: torch.Tensor) -> torch.Tensor:
        """Float[N, 2] positions -> Long[N, 2] bins of each one's move from the decoded
        position before it (the first's from the origin): error feedback keeps every
        decoded position within half a bin of its own, however long the block."""
        bins, reached = [], torch.zeros(2, dtype=torch.float64, device=xy.device)
        for point in xy.double():
            bins.append(self.encode(point - reached))
            reached = reached + self.decode(bins[-1]).double()
        return torch.stack(bins) if bins else torch.zeros(0, 2, dtype=torch.long, device=xy.device)

    def decode_moves(self, ids: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`encode_moves`: Long[N, 2] move bins -> Float[N, 2] positions."""
        return self.decode(ids).double().cumsum(0).float()

"""What a forecast scene is trained to give, cell by cell of the tokenizer's latent grid.

A query block that carries the present moved by the ego (``moved_observed_scene``) starts
the model off from where the static world will be; what is left to learn is what moves.
Two rules make the targets say so, for every family whose tokens forecast a scene:

- No code synonyms (:func:`canonical_codes`). A tokenizer often encodes the same geometry
  with different codes depending on what lies around it, so the future's code at a cell
  can differ from the query's while the voxels under the cell are the same (on the
  quickstart's tokenizer 84 % of the changed static cells decoded to at least 98 % the
  same voxels). Where the scene under a cell is at least ``CANONICAL_AGREEMENT`` the same
  in the moved present and the future, the target is the query's code: a target that
  differs from its query then means the scene changed there.
- Weight on what moves (:func:`mover_cells`). The cells where a movable-class voxel (a car,
  a cyclist, a pedestrian, ...) differs between the moved present and the future: where an
  agent came from or went to (a parked car, moved with everything else, differs nowhere).
  A family weighs them above the rest in its loss, in place of "changed from the query".

Both read the label volumes of the present (moved by the ego) and the future: known in
training, where every scene is a dataset frame; a scene without labels keeps its codes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from occtrain.formats.occ3d import CLASS_INDEX, MOVABLE_CLASSES

#: A cell's target is the query's code when at least this share of the voxels under it
#: holds the same class in the moved present and in the future (at most 20 of a 8x8x16 cell).
CANONICAL_AGREEMENT = 0.98


@dataclass(frozen=True)
class ForecastTarget:
    """A predicted scene's target: its raw codes (flat, codebook-major), canonicalised
    against its query, and Bool (h, w) the cells where an agent moved (None: not known)."""

    codes: torch.Tensor
    movers: torch.Tensor | None


def _per_cell(volume: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """(X, Y, Z) -> (h, w, X/h * Y/w * Z): each latent cell's voxels."""
    x, y, z = volume.shape
    h, w = hw
    return volume.reshape(h, x // h, w, y // w, z).permute(0, 2, 1, 3, 4).reshape(h, w, -1)


def canonical_codes(
    query: torch.Tensor,
    target: torch.Tensor,
    query_labels: torch.Tensor,
    target_labels: torch.Tensor,
    books: int,
    hw: tuple[int, int],
) -> torch.Tensor:
    """``target`` (flat codes, codebook-major, ``books`` x ``hw``) with the query's codes
    wherever the voxels under the cell are at least ``CANONICAL_AGREEMENT`` the same in
    ``query_labels`` (the moved present, X x Y x Z) and ``target_labels`` (the future)."""
    same = (_per_cell(query_labels, hw) == _per_cell(target_labels, hw)).float().mean(-1) >= CANONICAL_AGREEMENT
    keep = same.reshape(1, -1).expand(books, -1).reshape(-1).to(target.device)
    return torch.where(keep, query.to(target.device).long(), target.long())


def mover_cells(query_labels: torch.Tensor, target_labels: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """Bool (h, w): the cells where a movable-class voxel differs between the moved present
    and the future (an agent came or went)."""
    movable = torch.tensor(sorted(CLASS_INDEX[c] for c in MOVABLE_CLASSES), device=query_labels.device)
    q, t = _per_cell(query_labels, hw), _per_cell(target_labels, hw)
    return ((q != t) & (torch.isin(q, movable) | torch.isin(t, movable))).any(-1)


__all__ = ["CANONICAL_AGREEMENT", "ForecastTarget", "canonical_codes", "mover_cells"]

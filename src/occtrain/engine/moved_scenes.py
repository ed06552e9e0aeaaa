"""A scene moved by the ego through the frozen scene tokenizer: what ``moved_last_scene``
and ``moved_observed_scene`` query blocks hold (``core.protocols.SceneMover``).

A scene's labels are shifted by the step in whole voxels (``data.geometry.moved_scene``:
free where the new view reaches past the old grid, the heading kept) and encoded again.
The labels are the observed ones when the codes are those of a dataset frame (``observed``:
a prompt's scenes, and in training every scene before a predicted one), else the scene's
codes decoded (a generated scene). Decoding costs a dozen encodings, so training, which
moves only observed scenes, never decodes, and generation decodes only what it generated.
Both layouts move raw codes (``codes``; the codes layout's ids go through it by
``__call__``). The results are kept (keyed by the codes and the whole-voxel shift, all they
depend on): training asks for the same scenes moved by the same true steps every epoch; up
to ``capacity`` entries, the oldest dropped first.
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from collections.abc import Callable

import torch

from occtrain.core.ego_steps import EgoStep
from occtrain.core.protocols import SceneEncoder
from occtrain.core.vocab import JointVocab
from occtrain.data.geometry import moved_scene, voxel_shift


class MovedScenes:
    """A :class:`~occtrain.core.protocols.SceneMover` over a frozen discrete scene encoder."""

    def __init__(
        self,
        vocab: JointVocab,
        encoder: SceneEncoder,
        observed: Callable[[torch.Tensor], torch.Tensor | None] | None = None,
        capacity: int = 20_000,
    ):
        if not encoder.discrete:
            raise ValueError("moved scenes re-encode codes: the scene encoder must be a discrete tokenizer")
        self.vocab = vocab
        self.encoder = encoder
        #: Codes (flat) -> the observed labels (X, Y, Z) of the dataset frame they encode, or None.
        self.observed = observed or (lambda codes: None)
        self.capacity = capacity
        self._kept: OrderedDict[tuple[bytes, int, int], torch.Tensor] = OrderedDict()
        self.computed = 0  # scenes moved through the encoder (the rest came from what is kept)
        self.decoded = 0  # of which had no observed labels and were decoded first

    @torch.no_grad()
    def __call__(self, code_ids: torch.Tensor, step: EgoStep) -> torch.Tensor:
        """The codes layout: a scene's code ids moved by ``step``."""
        moved = self.codes(self.vocab.codes_from_ids(code_ids.detach().cpu()), step)
        return self.vocab.occ_ids(moved).to(code_ids.device)

    @torch.no_grad()
    def codes(self, codes: torch.Tensor, step: EgoStep) -> torch.Tensor:
        """A scene's raw codes (flat, codebook-major) moved by ``step``: any layout."""
        flat = codes.detach().reshape(-1).long().cpu()
        shift = voxel_shift(step)
        key = (flat.numpy().tobytes(), *shift)
        moved = self._kept.get(key)
        if moved is None:
            device = self._device()
            labels = self.observed(flat)
            if labels is None:
                labels = self.encoder.decode(flat[None].to(device))[0].cpu()
                self.decoded += 1
            moved = self.encoder.encode(moved_scene(labels, step)[None].to(device))[0].cpu().long()
            self.computed += 1
            self._kept[key] = moved
            if len(self._kept) > self.capacity:
                self._kept.popitem(last=False)
        else:
            self._kept.move_to_end(key)
        return moved.to(codes.device)

    @torch.no_grad()
    def labels(self, codes: torch.Tensor, step: EgoStep | None) -> torch.Tensor | None:
        """The observed labels of the dataset frame these raw codes encode, moved by ``step``
        (None: as they are); None for codes of no dataset frame (nothing is decoded)."""
        labels = self.observed(codes.detach().reshape(-1).long().cpu())
        if labels is None or step is None:
            return labels
        return moved_scene(labels, step)

    def _device(self) -> torch.device:
        module = self.encoder
        assert isinstance(module, torch.nn.Module)
        first = next(itertools.chain(module.parameters(), module.buffers()), None)
        return torch.device("cpu") if first is None else first.device

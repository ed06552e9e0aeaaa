"""What a world model's sequences are made of, shared by training and decoding: the
laid-out token sequence, the per-token payload beside the ids, one generation step."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import torch

if TYPE_CHECKING:
    from transformers import Cache

IGNORE = -100

#: What a world model carries beside the ids, per token: name -> (shape, dtype, fill).
#: A model whose scene tokens are codes carries nothing (a code token's id is its code);
#: one whose scene tokens are slots carries what each slot holds (its cells' codes, a
#: continuous feature, an image feature).
PayloadSpec = dict[str, tuple[tuple[int, ...], torch.dtype, float]]


def empty_payload(spec: PayloadSpec, n: int, device: torch.device | str | None = None) -> dict[str, torch.Tensor]:
    """The payload of ``n`` tokens that carry none (every field at its fill value)."""
    return {k: torch.full((n, *shape), fill, dtype=dtype, device=device) for k, (shape, dtype, fill) in spec.items()}


def cat_payload(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Payloads of consecutive token runs, joined along the token axis."""
    if not parts or not parts[0]:
        return {}
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


@dataclass
class TokenSequence:
    """One laid-out sequence (all Long[L] except ``scene_target`` Bool[L]; ``payload``
    holds the world model's per-token extras, each with L rows)."""

    input_ids: torch.Tensor
    labels: torch.Tensor
    segment_ids: torch.Tensor
    position_ids: torch.Tensor
    scene_target: torch.Tensor
    #: Long[L]: 0 on the shared trunk, k on branch k (see ``SequenceBuilder.branch``).
    branch_ids: torch.Tensor
    payload: dict[str, torch.Tensor] = field(default_factory=dict)
    #: Per-sequence targets a world model adds to its loss beside the token targets
    #: (e.g. voxel labels for occupancy queries and their loss weight), by name; collate
    #: stacks each, zeros for a sequence without it.
    targets: dict[str, torch.Tensor] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.input_ids.shape[0])


class Step(NamedTuple):
    """One forward of the LLM during generation: logits, the KV cache and the last hidden
    states (what a patch head reads; None for a model that does not read them)."""

    logits: torch.Tensor
    cache: Cache | None
    hidden: torch.Tensor | None


def head(seq: TokenSequence, n: int) -> TokenSequence:
    """The first ``n`` tokens of a laid-out sequence (a prompt's prefix)."""
    return TokenSequence(
        seq.input_ids[:n],
        seq.labels[:n],
        seq.segment_ids[:n],
        seq.position_ids[:n],
        seq.scene_target[:n],
        seq.branch_ids[:n],
        {k: v[:n] for k, v in seq.payload.items()},
    )


def tail(seq: TokenSequence, n: int) -> TokenSequence:
    """A laid-out sequence from token ``n`` on (what follows a prompt's prefix)."""
    return TokenSequence(
        seq.input_ids[n:],
        seq.labels[n:],
        seq.segment_ids[n:],
        seq.position_ids[n:],
        seq.scene_target[n:],
        seq.branch_ids[n:],
        {k: v[n:] for k, v in seq.payload.items()},
    )


def rows(hidden: torch.Tensor | None, *index: int | slice) -> torch.Tensor | None:
    """``hidden[index]``, or None when there are no hidden states."""
    return None if hidden is None else hidden[index]


def prompt_of(spec: PayloadSpec, prefix: torch.Tensor | TokenSequence) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """A prompt's ids Long[L] and payload: a laid-out sequence carries its own, bare ids
    carry none (enough for a world model without payload)."""
    if isinstance(prefix, TokenSequence):
        return prefix.input_ids.reshape(-1).long(), prefix.payload
    ids = torch.as_tensor(prefix).reshape(-1).long()
    return ids, empty_payload(spec, ids.numel())

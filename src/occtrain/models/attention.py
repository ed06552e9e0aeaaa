"""Spatial-temporal attention (OccLLaMA Sec. III-B) as a 4D additive attention mask.

A sequence carries one segment id per token:

- ``0``: a text, action or marker token: causal (sees every visible earlier token);
- ``s > 0``: a token of occupancy scene ``s``: causal towards other tokens, and
  bidirectional among the tokens of the same scene;
- ``s < 0``: a scene-query token standing for scene ``-s`` (next-scene prediction):
  bidirectional among its own block, sees the earlier visible tokens, and is hidden from
  every token outside its block, so the rest of the sequence attends to the scene's real
  codes only (exactly what generation sees after the queries are replaced by codes).

Optionally a branch id per token (packing answers): ``0`` is the shared trunk, ``k > 0``
branch k. A branch sees the trunk and itself, never another branch, so several answers
about one context train in one sequence exactly as each would alone.

Optionally a sample id per token (packing sequences, ``core.packing``): several laid-out
sequences share one row, and a token sees only the tokens of its own sequence, so each
trains exactly as it would in a row of its own.

Transformers 5.x passes a 4D mask ``[B, 1, Lq, Lk]`` to the attention kernel unchanged.
"sdpa" takes it boolean (True = attend) or additive float; "eager" adds it to the scores,
so it must be the additive float (``build_4d_mask``). ``tests/unit/models/test_attention.py``
checks that the Llama honours it in these three forms. The world model keeps the boolean
form and converts it per implementation (boolean suits SDPA in any compute dtype).
"""

from __future__ import annotations

import torch


def allowed_pairs(
    segment_ids: torch.Tensor,
    pad_mask: torch.Tensor,
    branch_ids: torch.Tensor | None = None,
    sample_ids: torch.Tensor | None = None,
) -> torch.Tensor:
    """Bool[B, L, L]: may query i attend to key j? ``pad_mask`` is True on real tokens;
    ``branch_ids`` and ``sample_ids`` Long[B, L] (optional) keep branches and packed
    sequences apart (see the module docstring).

    Every token may attend to itself, so a padding row is never empty (no NaN).
    """
    L = segment_ids.shape[1]
    idx = torch.arange(L, device=segment_ids.device)
    causal = idx[None, :] <= idx[:, None]  # [Lq, Lk]
    seg_q, seg_k = segment_ids[:, :, None], segment_ids[:, None, :]
    same_block = (seg_q == seg_k) & (seg_k != 0)
    visible_key = (seg_k >= 0) & pad_mask[:, None, :]
    allowed = (causal[None] & visible_key) | (same_block & pad_mask[:, None, :])
    if branch_ids is not None:
        br_q, br_k = branch_ids[:, :, None], branch_ids[:, None, :]
        allowed = allowed & ((br_k == 0) | (br_k == br_q))
    if sample_ids is not None:
        allowed = allowed & (sample_ids[:, :, None] == sample_ids[:, None, :])
    return allowed | torch.eye(L, dtype=torch.bool, device=segment_ids.device)[None]


def additive(allowed: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Bool[B, Lq, Lk] -> Float[B, 1, Lq, Lk]: 0 where allowed, the dtype's minimum elsewhere."""
    mask = torch.zeros(allowed.shape, dtype=dtype, device=allowed.device)
    return mask.masked_fill(~allowed, torch.finfo(dtype).min)[:, None]


def build_4d_mask(
    segment_ids: torch.Tensor, pad_mask: torch.Tensor, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Segment ids Long[B, L] and real-token mask Bool[B, L] -> additive mask Float[B, 1, L, L]."""
    return additive(allowed_pairs(segment_ids, pad_mask), dtype)


def chunk_allowed(segment_ids: torch.Tensor, past_len: int) -> torch.Tensor:
    """Bool[1, n, past_len + n] for feeding ``n`` new tokens (segments Long[n]) after
    ``past_len`` cached ones. The cache never holds query tokens, so the new tokens see all
    of it; among themselves the usual rules apply."""
    seg = segment_ids[None]
    inner = allowed_pairs(seg, torch.ones_like(seg, dtype=torch.bool))
    past = torch.ones(1, seg.shape[1], past_len, dtype=torch.bool, device=seg.device)
    return torch.cat([past, inner], dim=2)


def scene_segments(is_code: torch.Tensor) -> torch.Tensor:
    """Segment ids Long[..., L] of a sequence whose scenes are runs of occupancy-code tokens
    (``is_code`` Bool[..., L]): 1, 2, ... per run, 0 elsewhere. Scenes are always separated
    by their ``<occ>``/``</occ>`` markers, so each run is one scene."""
    prev = torch.nn.functional.pad(is_code[..., :-1], (1, 0), value=False)
    starts = is_code & ~prev
    return torch.cumsum(starts.long(), dim=-1) * is_code.long()

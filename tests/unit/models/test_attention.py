"""Spatial-temporal attention: the mask's semantics, and that the HF Llama honours it."""

from __future__ import annotations

import pytest
import torch
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.models.attention import additive, allowed_pairs, build_4d_mask, chunk_allowed, scene_segments

# text, scene 1 (2 tokens), text, query block of scene 2, scene 2's codes, text, padding
SEGMENTS = torch.tensor([[0, 1, 1, 0, -2, -2, 2, 2, 0, 0]])
PAD = torch.tensor([[True] * 9 + [False]])
# Row = query token, column = key token; written out by hand from the rules.
EXPECTED = torch.tensor(
    [
        [1, 0, 0, 0, 0, 0, 0, 0, 0, 0],  # text: causal
        [1, 1, 1, 0, 0, 0, 0, 0, 0, 0],  # scene 1: its whole scene, the past
        [1, 1, 1, 0, 0, 0, 0, 0, 0, 0],
        [1, 1, 1, 1, 0, 0, 0, 0, 0, 0],  # text after a scene sees all of it
        [1, 1, 1, 1, 1, 1, 0, 0, 0, 0],  # queries: the past and their own block
        [1, 1, 1, 1, 1, 1, 0, 0, 0, 0],
        [1, 1, 1, 1, 0, 0, 1, 1, 0, 0],  # scene 2's codes: not the queries
        [1, 1, 1, 1, 0, 0, 1, 1, 0, 0],
        [1, 1, 1, 1, 0, 0, 1, 1, 1, 0],  # text after: never the queries, never padding
        [1, 1, 1, 1, 0, 0, 1, 1, 1, 1],  # padding row: itself, so never empty
    ],
    dtype=torch.bool,
)


def test_mask_semantics_by_hand():
    assert torch.equal(allowed_pairs(SEGMENTS, PAD)[0], EXPECTED)
    mask = build_4d_mask(SEGMENTS, PAD)
    assert mask.shape == (1, 1, 10, 10) and mask.dtype == torch.float32
    assert torch.equal(mask[0, 0] == 0, EXPECTED)
    assert float(mask.min()) == torch.finfo(torch.float32).min
    assert build_4d_mask(SEGMENTS, PAD, torch.bfloat16).dtype == torch.bfloat16


def test_chunk_mask_after_cache():
    got = chunk_allowed(torch.tensor([0, -1, -1]), past_len=3)
    want = torch.tensor([[1, 1, 1, 1, 0, 0], [1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    assert torch.equal(got[0], want)


def test_scene_segments_from_code_runs():
    is_code = torch.tensor([False, True, True, False, False, True, False, True, True, True])
    assert scene_segments(is_code).tolist() == [0, 1, 1, 0, 0, 2, 0, 3, 3, 3]


def _llama(impl: str) -> LlamaForCausalLM:
    torch.manual_seed(0)
    cfg = LlamaConfig(
        vocab_size=40,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=4,
        attn_implementation=impl,
    )
    return LlamaForCausalLM(cfg).eval()


@pytest.mark.parametrize("impl,as_bool", [("sdpa", True), ("sdpa", False), ("eager", False)])
def test_hf_llama_honours_the_mask(impl, as_bool):
    model = _llama(impl)
    seg = torch.tensor([[0, 0, 1, 1, 1, 0, 0, 0]])
    ones = torch.ones_like(seg, dtype=torch.bool)

    def logits(ids, segments):
        allowed = allowed_pairs(segments, ones)
        mask = allowed[:, None] if as_bool else additive(allowed)
        with torch.no_grad():
            return model(input_ids=ids, attention_mask=mask).logits[0]

    ids = torch.tensor([[5, 6, 7, 8, 9, 10, 11, 12]])
    later_in_scene = ids.clone()
    later_in_scene[0, 4] = 20
    later_text = ids.clone()
    later_text[0, 6] = 21
    base = logits(ids, seg)
    # A later token of the same scene reaches an earlier one...
    assert not torch.allclose(base[2], logits(later_in_scene, seg)[2], atol=1e-5)
    # ...but not a token before the scene.
    assert torch.allclose(base[:2], logits(later_in_scene, seg)[:2], atol=1e-6)
    # A later text token changes nothing before it.
    assert torch.allclose(base[:6], logits(later_text, seg)[:6], atol=1e-6)
    # Control: under a plain causal mask the same change leaves position 2 alone.
    causal = torch.zeros_like(seg)
    assert torch.allclose(logits(ids, causal)[2], logits(later_in_scene, causal)[2], atol=1e-6)

"""Model FLOPs per token: a hand count on a tiny Llama, and torch's FLOP counter agreeing."""

from __future__ import annotations

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.models.flops import TransformerFlops


def _tiny(tied: bool = False) -> LlamaForCausalLM:
    torch.manual_seed(0)
    config = LlamaConfig(
        vocab_size=10,
        hidden_size=8,
        intermediate_size=16,
        num_hidden_layers=2,
        num_attention_heads=2,
        num_key_value_heads=1,
        tie_word_embeddings=tied,
        attn_implementation="eager",  # torch counts its matmuls; not CPU sdpa
    )
    return LlamaForCausalLM(config)


def test_the_count_by_hand_on_a_tiny_llama():
    flops = TransformerFlops.of(_tiny())
    # Per layer: q 8x8, k and v 8x4 (one KV head of 4), o 8x8; gate and up 8x16, down 16x8.
    per_layer = 64 + 32 + 32 + 64 + 3 * 128
    assert flops.weights == 2 * per_layer + 8 * 10  # and the LM head; the embedding is a lookup
    assert flops.trainable == flops.weights and flops.layers == 2 and flops.attention_width == 8
    # S = 5: forward 2 x 1,232 + 4 x 2 x 5 x 8; training 6 x 1,232 + 12 x 2 x 5 x 8.
    assert flops.forward_per_token(5) == 2464 + 320
    assert flops.train_per_token(5) == 7392 + 960


def test_a_tied_head_counts_once_and_frozen_weights_skip_their_gradient():
    tied = TransformerFlops.of(_tiny(tied=True))
    assert tied.weights == TransformerFlops.of(_tiny()).weights  # the head is a matmul either way
    model = _tiny()
    for layer in model.model.layers:
        layer.requires_grad_(False)
    frozen = TransformerFlops.of(model)
    assert frozen.trainable == 80  # the LM head alone
    assert frozen.train_per_token(5) == 4 * frozen.weights + 2 * 80 + 12 * 2 * 5 * 8


@pytest.mark.parametrize("seq_len", [1, 7])
@pytest.mark.parametrize("frozen_layers", [False, True])
def test_torchs_flop_counter_counts_the_same_forward_and_training_step(seq_len, frozen_layers):
    model = _tiny()
    if frozen_layers:  # their inputs' gradients still flow to the trained embedding
        for layer in model.model.layers:
            layer.requires_grad_(False)
    flops = TransformerFlops.of(model)
    ids = torch.randint(0, 10, (3, seq_len))
    with FlopCounterMode(display=False) as counter:
        model(input_ids=ids)
    assert counter.get_total_flops() == 3 * seq_len * flops.forward_per_token(seq_len)
    with FlopCounterMode(display=False) as counter:
        model(input_ids=ids, labels=ids).loss.backward()
    assert counter.get_total_flops() == 3 * seq_len * flops.train_per_token(seq_len)

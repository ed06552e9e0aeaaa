"""Model FLOPs of a decoder-only transformer, the count model FLOPs utilization divides.

PaLM's convention (Chowdhery et al. 2022, App. B), which torchtitan and litgpt report MFU
by: per token, 2 FLOPs per matmul weight forward (every decoder layer's projections and the
LM head; the input embedding is a lookup, not a matmul) and 4 x layers x sequence length x
attention width for the attention scores and their weighted sum; a training step does twice
the forward again backward. Where weights are frozen (LoRA, adapters, a frozen projector)
backward computes their inputs' gradients but not theirs, so a frozen weight costs 4 FLOPs
a token where a trained one costs 6: all trainable, the count is PaLM's 6N + 12 L S d.
Elementwise work (norms, activations, RoPE, softmax) is not counted, as in PaLM.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from transformers import PreTrainedModel


@dataclass(frozen=True)
class TransformerFlops:
    """What a decoder-only transformer's FLOPs per token follow from."""

    #: Matmul weights every token goes through (decoder layers and LM head).
    weights: int
    #: Of those, the trained ones.
    trainable: int
    layers: int
    #: Heads x head dim: the width of the attention scores' dot products.
    attention_width: int

    def forward_per_token(self, seq_len: int) -> float:
        return 2.0 * self.weights + 4.0 * self.layers * seq_len * self.attention_width

    def train_per_token(self, seq_len: int) -> float:
        """Forward and backward: activation gradients through every weight, weight gradients
        for the trained ones, attention backward twice its forward."""
        return 4.0 * self.weights + 2.0 * self.trainable + 12.0 * self.layers * seq_len * self.attention_width

    @classmethod
    def of(cls, llm: PreTrainedModel) -> TransformerFlops:
        """Counted from a Hugging Face causal LM (a peft-wrapped one included): its 2-D
        parameters but the input embedding, and the LM head even where it is tied to it."""
        get_input = getattr(llm, "get_input_embeddings", None)
        embed = get_input().weight if get_input is not None else None
        weights = {id(p): p for p in llm.parameters() if p.dim() == 2 and p is not embed}
        head = llm.get_output_embeddings() if hasattr(llm, "get_output_embeddings") else None
        if head is not None:  # tied to the embedding or not, the head is a matmul per token
            weights[id(head.weight)] = head.weight
        config = llm.config
        heads = int(config.num_attention_heads)
        head_dim = int(getattr(config, "head_dim", None) or config.hidden_size // heads)
        return cls(
            weights=sum(p.numel() for p in weights.values()),
            trainable=sum(p.numel() for p in weights.values() if p.requires_grad),
            layers=int(config.num_hidden_layers),
            attention_width=heads * head_dim,
        )

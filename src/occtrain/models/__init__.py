"""nn.Modules of the papers (no Lightning here): scene tokenizers, and the pieces of later stages."""

from __future__ import annotations

from torch import nn

from occtrain.models.tokenizers import SceneTokenizer, TokenizerOutput, build_tokenizer


def count_parameters(module: nn.Module) -> int:
    """Number of parameters of ``module``, trainable and frozen alike (buffers excluded)."""
    return sum(p.numel() for p in module.parameters())


__all__ = ["SceneTokenizer", "TokenizerOutput", "build_tokenizer", "count_parameters"]

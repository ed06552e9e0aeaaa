"""Blocks every scene tokenizer shares: the output record and base class, the VQ codebook,
conv encoder/decoder blocks, swin blocks and the reconstruction losses. The architectures
themselves live in their families (``occtrain.families``) and register there."""

from __future__ import annotations

from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerOutput
from occtrain.models.tokenizers.quantizer import QuantizerOutput, VectorQuantizer

__all__ = ["QuantizerOutput", "SceneTokenizer", "TokenizerOutput", "VectorQuantizer"]

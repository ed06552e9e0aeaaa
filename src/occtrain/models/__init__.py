"""Blocks the families share (no Lightning here): LLM loading and LoRA, the joint vocabulary,
the action quantizer, attention masks, the VQ codebook and tokenizer blocks, planning heads."""

from __future__ import annotations

from torch import nn


def count_parameters(module: nn.Module, trainable: bool = False) -> int:
    """Number of parameters of ``module`` (buffers excluded); only trainable ones with ``trainable``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable)


def without_peft(model: nn.Module) -> nn.Module:
    """The model inside a peft wrapper (LoRA), or ``model`` itself when it has none."""
    return model.get_base_model() if hasattr(model, "get_base_model") else model


__all__ = ["count_parameters", "without_peft"]

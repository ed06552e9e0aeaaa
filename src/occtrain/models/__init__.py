"""Blocks the families share (no Lightning here): LLM loading and LoRA, the joint vocabulary,
the action quantizer, attention masks, the VQ codebook and tokenizer blocks, planning heads."""

from __future__ import annotations

from typing import TYPE_CHECKING

from torch import nn

if TYPE_CHECKING:
    from transformers import PreTrainedModel


def count_parameters(module: nn.Module, trainable: bool = False) -> int:
    """Number of parameters of ``module`` (buffers excluded); only trainable ones with ``trainable``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable)


def without_peft(model: nn.Module) -> PreTrainedModel:
    """The Hugging Face model inside a peft wrapper (LoRA), or ``model`` itself when it has none."""
    get_base_model = getattr(model, "get_base_model", None)
    return model if get_base_model is None else get_base_model()


__all__ = ["count_parameters", "without_peft"]

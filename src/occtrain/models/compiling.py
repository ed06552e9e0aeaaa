"""``torch.compile`` for training steps (``trainer.compile: true``).

What compiles is each repeated block on its own (a transformer's decoder layers, as
torchtitan does): the blocks are alike, so they share one compiled graph, and compiling
takes seconds rather than the minutes a whole model's graph does. Only training forwards
go through it; evaluation and generation stay eager, because decoding feeds one token at
a time against a growing KV cache (a new shape each step, and a cache object the compiler
breaks the graph at) and ends sequences at data-dependent points, where compiling would
only add recompilations.

The module's weights, names and state dict are untouched: checkpoints, exports and a
resume are the same with compiling on or off.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from torch import nn

from occtrain.models import without_peft

_COMPILED = "_occtrain_compiled_forward"


def compile_for_training(module: nn.Module, **options: Any) -> bool:
    """Route ``module``'s training forwards (training mode, gradients on) through
    ``torch.compile(module.forward, **options)``; the rest stay eager. False when it was
    compiled already (a resumed fit, a second call)."""
    if hasattr(module, _COMPILED):
        return False
    eager = module.forward
    compiled = torch.compile(eager, **options)

    def forward(*args: Any, **kwargs: Any) -> Any:
        if module.training and torch.is_grad_enabled():
            return compiled(*args, **kwargs)
        return eager(*args, **kwargs)

    object.__setattr__(module, _COMPILED, compiled)
    object.__setattr__(module, "forward", forward)
    return True


def is_compiled(module: nn.Module) -> bool:
    return hasattr(module, _COMPILED)


def decoder_layers(llm: nn.Module) -> list[nn.Module]:
    """A Hugging Face causal LM's decoder layers (inside a peft wrapper too): the blocks
    :func:`compile_for_training` compiles one by one."""
    base = without_peft(llm)
    decoder = base.get_decoder() if hasattr(base, "get_decoder") else None
    layers = getattr(decoder, "layers", None)
    if not isinstance(layers, nn.ModuleList):
        raise ValueError(f"{type(base).__name__} has no decoder layers to compile (get_decoder().layers)")
    return list(layers)


def compile_all(modules: Iterable[nn.Module], **options: Any) -> int:
    """Compile each of ``modules`` for training; how many were newly compiled."""
    return sum(compile_for_training(m, **options) for m in modules)

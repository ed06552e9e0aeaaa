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

Inductor keeps what it compiled (kernels and graphs, over 100 MB) in
``TORCHINDUCTOR_CACHE_DIR``, by default a folder in the system's temp dir where nobody
looks; :func:`use_cache_dir` points it into the run instead, unless the user chose one.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from occtrain.models import without_peft

_COMPILED = "_occtrain_compiled_forward"
CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"


def use_cache_dir(folder: Path) -> tuple[Path, Callable[[], None]]:
    """Have inductor cache what it compiles in ``folder`` unless the user set
    ``TORCHINDUCTOR_CACHE_DIR``; the folder in use, and what puts the variable back.

    Torch writes its default into the variable the first time it looks (``torch.compile``
    does), so that value is torch's, not a user's choice."""
    before = os.environ.get(CACHE_ENV)
    if before and before != _torch_default():
        return Path(before), lambda: None
    os.environ[CACHE_ENV] = str(Path(folder).absolute())

    def restore() -> None:
        if before is None:
            os.environ.pop(CACHE_ENV, None)
        else:
            os.environ[CACHE_ENV] = before

    return Path(os.environ[CACHE_ENV]), restore


def _torch_default() -> str | None:
    try:
        from torch._inductor.runtime.cache_dir_utils import default_cache_dir
    except ImportError:  # a torch that keeps it elsewhere: any value set counts as the user's
        return None
    return os.path.abspath(default_cache_dir())


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

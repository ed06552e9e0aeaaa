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
looks, and its precompiled C++ headers (about 150 MB) in that default folder whatever the
variable says. :func:`use_cache_dir` points all of it, and the compiler's temporary files,
into the run instead (or into the folder the user chose with the variable).

Inductor reads its cache back with pickle, so a cache is only used where it was made: one
that came with a run copied from elsewhere is emptied first (:func:`trust_cache`).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from occtrain.formats.io import atomic_write_json, remove_inside
from occtrain.models import without_peft

_COMPILED = "_occtrain_compiled_forward"
CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"


@dataclass(frozen=True)
class CompileCache:
    """Where inductor caches during a fit (``use_cache_dir``): the folder, whether a cache
    that came from elsewhere was emptied first, and what puts everything back."""

    folder: Path
    emptied: bool
    restore: Callable[[], None]


def use_cache_dir(folder: Path, vet: bool = True) -> CompileCache:
    """Have inductor cache what it compiles in ``folder`` unless the user set
    ``TORCHINDUCTOR_CACHE_DIR`` (then in theirs, left as it is), its precompiled headers and
    the compiler's temporary files there too. With ``vet``, ``folder`` is emptied first when
    it was not made where it lies (:func:`trust_cache`; under DDP rank zero vets it alone,
    before the others use it).

    Torch writes its default into the variable the first time it looks (``torch.compile``
    does), so that value is torch's, not a user's choice."""
    before = os.environ.get(CACHE_ENV)
    users = bool(before) and before != _torch_default()
    chosen = Path(str(before)) if users else Path(folder).absolute()
    emptied = False if users or not vet else not trust_cache(chosen)
    os.environ[CACHE_ENV] = str(chosen)
    temp_before = tempfile.tempdir
    scratch = chosen / "tmp"
    scratch.mkdir(parents=True, exist_ok=True)
    tempfile.tempdir = str(scratch)
    headers_back = _headers_into(chosen / "precompiled_headers")

    def restore() -> None:
        if before is None:
            os.environ.pop(CACHE_ENV, None)
        else:
            os.environ[CACHE_ENV] = before
        tempfile.tempdir = temp_before
        headers_back()

    return CompileCache(chosen, emptied, restore)


def _headers_into(folder: Path) -> Callable[[], None]:
    """Inductor's precompiled C++ headers in ``folder``: torch fixes their folder when it
    loads its code cache (the default cache folder, whatever ``TORCHINDUCTOR_CACHE_DIR``
    says); where that name has moved in another torch, headers are not precompiled at all
    (slower compiles, nothing written outside). What puts it back."""
    from torch._inductor import codecache
    from torch._inductor import config as inductor_config

    if not hasattr(codecache, "_HEADER_DIR"):
        with_headers = inductor_config.cpp_cache_precompile_headers
        inductor_config.cpp_cache_precompile_headers = False
        return lambda: setattr(inductor_config, "cpp_cache_precompile_headers", with_headers)
    old = codecache._HEADER_DIR, codecache._HEADER_LOCK_DIR
    codecache._HEADER_DIR, codecache._HEADER_LOCK_DIR = str(folder), str(folder / "locks")
    codecache._precompile_header.cache_clear()  # a header precompiled elsewhere is not reused

    def restore() -> None:
        codecache._HEADER_DIR, codecache._HEADER_LOCK_DIR = old
        codecache._precompile_header.cache_clear()

    return restore


#: In a cache folder: where and by whom it was made (see ``trust_cache``).
OWNER_FILE = ".occtrain-owner.json"


def trust_cache(folder: Path) -> bool:
    """Make ``folder`` a cache inductor may read: one made in this very folder by this user,
    as its owner file records (the folder's resolved path, device, inode and the user id; a
    copy, a download or an unpacked archive gets another inode). Anything else in it is
    removed first, since inductor unpickles what it finds there. True when it was trusted
    already (or new), False when something was removed."""
    folder.mkdir(parents=True, exist_ok=True)
    stat = folder.stat()
    here = {"path": str(folder.resolve()), "device": stat.st_dev, "inode": stat.st_ino, "uid": os.getuid()}
    owner = folder / OWNER_FILE
    try:
        recorded = json.loads(owner.read_text())
    except (OSError, ValueError):
        recorded = None
    if recorded == here:
        return True
    strangers = [entry for entry in folder.iterdir() if entry.name != OWNER_FILE]
    for entry in strangers:
        remove_inside(entry, folder)
    atomic_write_json(owner, here)
    return not strangers


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

"""The C allocator a training process runs with: freed memory kept for the next step.

glibc's malloc hands a block over its mmap threshold (32 MiB at most) straight to the
kernel and back on free. A 200 x 200 x 16 grid's activations and logits are such blocks,
so every training step of a scene tokenizer mapped and unmapped them and the kernel zeroed
their pages afresh: 12 % of the quickstart tokenizer's time went to page faults.
``keep_freed_memory`` serves large blocks from the heap instead and keeps freed heap,
which PyTorch's CPU allocator (no caching of its own) then reuses from step to step.
``tools/bench/allocator.py`` measures it side by side with glibc's defaults.

``OCCTRAIN_MALLOC=system`` keeps glibc's defaults; elsewhere than glibc nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: glibc's ``mallopt`` parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
#: Freed heap kept before it is returned to the kernel.
KEEP_BYTES = 1 << 30
ENV = "OCCTRAIN_MALLOC"


def keep_freed_memory() -> bool:
    """Serve large blocks from the heap and keep freed heap (glibc only); whether it did."""
    if os.environ.get(ENV, "") == "system":
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = libc.mallopt if libc is not None else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): their allocators differ
        return False
    if mallopt is None:
        return False
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_BYTES))

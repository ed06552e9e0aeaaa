"""Atomic file writes: a temp file in the same directory, fsync, then rename.

A reader (or a crash) never sees a half-written manifest, export, metrics file or label.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; parent directories are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=False) + "\n")


def npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """Serialise arrays as an ``.npz`` (never with object dtype, so loading needs no pickle)."""
    for name, arr in arrays.items():
        if arr.dtype == object:
            raise ValueError(f"array '{name}' has object dtype; only plain numeric arrays are stored")
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays)
    return buf.getvalue()


def atomic_write_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> Path:
    return atomic_write_bytes(path, npz_bytes(arrays, compress))


def rank_world() -> tuple[int, int]:
    """This process's rank and the world size of the initialized process group; (0, 1) without one."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def is_rank_zero() -> bool:
    """Whether this process writes shared files (manifests, exports, caches) under DDP.

    Read from the launcher's environment, so it holds before any process group exists.
    """
    return os.environ.get("LOCAL_RANK", "0") == "0" and os.environ.get("NODE_RANK", "0") == "0"

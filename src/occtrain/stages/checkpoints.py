"""Checkpoint files of a stage: written atomically, found again after a kill, read without unpickling."""

from __future__ import annotations

import io
import os
import re
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from occtrain.errors import OcctrainError
from occtrain.formats.io import atomic_open, remove_inside

LAST_CKPT = "last.ckpt"
#: The checkpoint ``last.ckpt`` replaced, kept so a damaged ``last.ckpt`` still resumes.
PREVIOUS_CKPT = "previous.ckpt"


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints written to a temp name, fsynced and renamed: a kill, a full disk or a
    read-only directory never leaves a partial ``last.ckpt`` or ``best.ckpt``. The
    ``last.ckpt`` being replaced stays as ``previous.ckpt`` (a hard link: no copy)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any = None) -> None:
        path = Path(path)
        # Serialized in memory first, so a failing write is an OSError of ours to explain,
        # not one torch's zip writer wraps in a RuntimeError.
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        with atomic_open(path) as fh:
            fh.write(buf.getbuffer())
            if path.name == LAST_CKPT and path.is_file():
                previous = path.with_name(PREVIOUS_CKPT)
                remove_inside(previous, path.parent)
                os.link(path, previous)


def readable_checkpoint(path: Path) -> str:
    """Why ``path`` cannot be a checkpoint to resume from ("" when it can).

    torch writes a zip archive; its central directory and per-entry CRCs catch truncation
    and damaged bytes without unpickling anything."""
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
        return f"damaged entry {bad}" if bad else ""
    except (zipfile.BadZipFile, OSError, EOFError) as err:
        return str(err) or type(err).__name__


def last_checkpoint(stage_dir: Path, say: Callable[[str], None] = lambda line: None) -> Path | None:
    """The checkpoint a cut-off stage resumes from: ``last.ckpt``, else the one before it
    when ``last.ckpt`` is unreadable (``say`` gets one line about it), else None."""
    ckpt_dir = stage_dir / "checkpoints"
    last, previous = ckpt_dir / LAST_CKPT, ckpt_dir / PREVIOUS_CKPT
    if not last.is_file():
        return None
    problem = readable_checkpoint(last)
    if not problem:
        _refuse_pickled(last)
        return last
    if previous.is_file() and not readable_checkpoint(previous):
        say(f"{last} is unreadable ({problem}); resuming from the checkpoint before it, {previous}")
        return previous
    say(f"{last} is unreadable ({problem}) and no earlier checkpoint is; the stage starts afresh")
    return None


def _refuse_pickled(path: Path) -> None:
    """A sound archive whose pickle names more than tensors and plain values (not one
    occtrain wrote) stops the run: never unpickled, and never overwritten by a fresh start."""
    import pickle

    try:
        torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError as err:
        found = re.search(r"Unsupported global: (?:GLOBAL )?(\S+)", str(err))
        what = f"object {found.group(1)}" if found else "objects"
        raise OcctrainError(
            f"{path}: holds pickled {what}, which a weights-only load refuses (occtrain never unpickles); "
            "move it away to start the stage afresh"
        ) from None


def checkpoint_step(path: Path) -> int:
    """The optimizer step a checkpoint was saved at (weights-only load: nothing unpickled)."""
    return int(torch.load(path, map_location="cpu", weights_only=True, mmap=True).get("global_step", 0))

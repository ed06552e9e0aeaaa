"""Where occtrain writes and deletes, made safe.

Atomic file writes: a temp file in the same directory, fsync, then rename, so a reader (or
a crash) never sees a half-written manifest, export, metrics file or label. Outputs checked
before long work (:func:`check_output`), so a bad ``--out`` fails in one line before the
hour it would take to reach it. And one door for deleting (:func:`remove_inside`): a path
is removed only when it resolves inside the directory that owns it. And one door for
reading JSON a user hands over (:func:`parse_json`): whatever the text, a one-line reason.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

from occtrain.errors import OcctrainError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: What a plain ``open(path, "w")`` gives a new file; temp files start at 0600.
FILE_MODE = 0o666 & ~_umask()

#: Write failures that are the machine's, not the program's: what happened, and what to do
#: when it happens mid-run (a check before any work says what to do itself).
_WRITE_ERRORS = {
    errno.ENOSPC: ("the disk is full", "free space and rerun (a run resumes where it stopped)"),
    errno.EDQUOT: ("the disk quota is exhausted", "free space and rerun (a run resumes where it stopped)"),
    errno.EROFS: ("the file system is read-only", "point the run (--run-dir) or --out at a writable place"),
    errno.EACCES: ("permission denied", "make the directory writable or choose another one"),
    errno.EPERM: ("permission denied", "make the directory writable or choose another one"),
}


class WriteError(OcctrainError):
    """A file could not be written for a reason outside occtrain (disk full, read-only, permissions)."""


def write_error(path: str | Path, err: OSError) -> OSError | WriteError:
    """The one-line error for a failed write of ``path``, or ``err`` itself when it is a bug."""
    what = _WRITE_ERRORS.get(err.errno or 0)
    return WriteError(f"cannot write {path}: {what[0]}; {what[1]}") if what else err


@contextmanager
def atomic_open(path: str | Path) -> Iterator[IO[bytes]]:
    """A binary file handle whose contents replace ``path`` atomically when the block ends.

    On any error the temp file is removed and ``path`` keeps its old contents; disk-full,
    read-only and permission errors become a one-line :class:`WriteError`.
    """
    path = Path(path)
    tmp: str | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise write_error(path, err) from None
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


#: What the probe of ``check_output`` writes: enough that a full disk refuses it.
PROBE_BYTES = 64 * 1024


def check_output(path: str | Path, flag: str, kind: str = "file", overwrite: bool = True, fix: str = "") -> Path:
    """Refuse, before any work, an output the command could not write at its end.

    ``kind`` is "file" or "dir" (a directory the command fills). Refused in one line naming
    ``path`` and ``flag``: a file where a directory goes or the reverse, an existing file
    without ``overwrite``, a parent that is a file, and a place that cannot be written
    (read-only, permissions, disk full), found by writing and removing a probe file in the
    nearest directory that exists, which is what the real write will need. ``fix`` says
    what to do then (default: choose another ``flag``).
    """
    path = Path(path)
    if kind == "dir" and path.exists() and not path.is_dir():
        raise WriteError(f"{path}: is a file; {flag} takes a directory (choose a new name or remove the file)")
    if kind == "file" and path.is_dir():
        raise WriteError(f"{path}: is a directory; {flag} takes a file name")
    if kind == "file" and path.exists() and not overwrite:
        raise WriteError(f"{path}: exists; choose another {flag} or remove it first")
    parent = path if kind == "dir" else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise WriteError(f"cannot write {path}: {parent} is a file, not a directory; choose another {flag}")
    probe = None
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".occtrain-probe.", suffix=".tmp")
        try:
            os.write(fd, bytes(PROBE_BYTES))  # a full disk still creates an empty file
        finally:
            os.close(fd)
    except OSError as err:
        what = _WRITE_ERRORS.get(err.errno or 0)
        if what is None:
            raise
        raise WriteError(f"cannot write {path}: {what[0]}; {fix or f'choose another {flag}'}") from None
    finally:
        if probe is not None:
            os.unlink(probe)
    return path


class OutsideError(OcctrainError):
    """A deletion whose target does not resolve inside the directory that owns it."""


def remove_inside(target: str | Path, root: str | Path) -> bool:
    """Delete ``target`` (a file, a link or a directory tree) if it lies inside ``root``.

    Every deletion occtrain makes goes through here: a name from a recipe or a manifest
    that reaches outside (``../x``, an absolute path, a link to elsewhere) is refused with
    :class:`OutsideError` instead of deleting someone's files. The last component is not
    followed: a link inside ``root`` is removed as a link, never what it points at.
    Returns whether anything was there to remove.
    """
    root_path = Path(root).resolve()
    target = Path(target)
    where = target.parent.resolve() / target.name
    if target.name in ("", ".", "..") or where == root_path or not where.is_relative_to(root_path):
        raise OutsideError(f"refusing to delete {target}: it is not inside {root_path}")
    if where.is_symlink() or where.is_file():
        where.unlink()
    elif where.is_dir():
        shutil.rmtree(where)
    else:
        return False
    return True


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; parent directories are created."""
    with atomic_open(path) as fh:
        fh.write(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def finite_or_null(obj: Any) -> Any:
    """``obj`` ready for standard JSON, recursively: numpy and torch scalars as Python
    numbers, and every NaN or infinite float as None.

    Python's json writes them as ``NaN`` / ``Infinity``, which standard JSON readers refuse;
    an undefined number is ``null`` in every file occtrain writes.
    """
    if getattr(obj, "ndim", None) == 0 and hasattr(obj, "item"):  # a numpy or torch scalar
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    return obj


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    """Standard JSON (non-finite numbers as null), written atomically."""
    text = json.dumps(finite_or_null(obj), indent=indent, sort_keys=False, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """Serialise arrays as an ``.npz`` (never with object dtype, so loading needs no pickle)."""
    for name, arr in arrays.items():
        if arr.dtype == object:
            raise ValueError(f"array '{name}' has object dtype; only plain numeric arrays are stored")
    buf = io.BytesIO()
    # Named, the flag cannot be taken from an array called "allow_pickle".
    (np.savez_compressed if compress else np.savez)(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def png_bytes(image: np.ndarray, optimize: bool = False) -> bytes:
    """Encode an image as PNG: (H, W, 3) uint8 RGB, (H, W) uint8 grey or (H, W) uint16."""
    from PIL import Image

    image = np.asarray(image)
    kinds = {(3, "uint8"), (2, "uint8"), (2, "uint16")}
    if (image.ndim, image.dtype.name) not in kinds or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"a PNG is (H, W, 3) uint8, (H, W) uint8 or (H, W) uint16, got {image.shape} {image.dtype}")
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", optimize=optimize)  # mode from the dtype and shape
    return buf.getvalue()


def atomic_write_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> Path:
    return atomic_write_bytes(path, npz_bytes(arrays, compress))


def atomic_write_safetensors(path: str | Path, tensors: dict) -> Path:
    """Write a name -> tensor dict as safetensors, atomically."""
    from safetensors.torch import save

    return atomic_write_bytes(path, save({k: v.contiguous() for k, v in tensors.items()}))


def parse_json(text: str | bytes) -> Any:
    """``json.loads`` whose every refusal of a text is a ValueError saying why in one line.

    The decoder's own errors (JSONDecodeError, UnicodeDecodeError) are ValueErrors already;
    two more ways a file fails are not caught by callers that expect those: nesting deeper
    than the interpreter's stack (a RecursionError) and an integer longer than Python
    converts (a ValueError whose advice, ``sys.set_int_max_str_digits``, is not the user's
    to take). Callers catch ValueError and name their file.
    """
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(
            f"nested deeper than Python's JSON reader goes (about {sys.getrecursionlimit()} levels)"
        ) from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise
    except ValueError as err:
        digits = re.search(r"value has (\d+) digits", str(err))
        if digits is None:
            raise
        raise ValueError(
            f"an integer of {digits.group(1)} digits, more than Python reads ({sys.get_int_max_str_digits()})"
        ) from None

"""A release's files placed in a dataset without doubling the disk: hard links.

A dataset's files must lie inside its root (a symbolic link out of it is refused where it
is read), so an import neither points into the release by symbolic links nor copies its
gigabytes: each file is hard-linked (the same bytes under a second name, inside the root),
and copied only where the filesystem refuses a hard link (another device, or one without
them). A folder appears whole or not at all: it is filled under a temporary name, then
renamed.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

#: os.link's refusals that mean "not here", where a copy does instead.
_NO_HARD_LINK = {errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP}


def place(src: Path, dst: Path, copy: bool = False) -> str:
    """``dst`` the same file as ``src``: "link" (a hard link) or "copy"."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if not copy:
        try:
            os.link(src, dst, follow_symlinks=True)
            return "link"
        except OSError as err:
            if err.errno not in _NO_HARD_LINK:
                raise
    shutil.copy2(src, dst)
    return "copy"


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial")


def _clear(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.exists():
        shutil.rmtree(path)


def place_tree(src: Path, dst: Path, copy: bool = False) -> int:
    """Every file under ``src`` at the same place under ``dst``, all at once (see the module
    docstring); nothing when ``dst`` exists. The number of files placed."""
    if dst.exists():
        return 0
    tmp = _tmp(dst)
    _clear(tmp)
    n = 0
    for path in sorted(src.rglob("*")):
        if path.is_file():
            place(path, tmp / path.relative_to(src), copy)
            n += 1
    tmp.mkdir(parents=True, exist_ok=True)
    tmp.rename(dst)
    return n


def place_files(pairs: list[tuple[Path, Path]], copy: bool = False) -> int:
    """Each (src, dst) placed, a ``dst`` that exists left as it is (an earlier run's)."""
    n = 0
    for src, dst in pairs:
        if dst.exists():
            continue
        tmp = _tmp(dst)
        _clear(tmp)
        place(src, tmp, copy)
        tmp.rename(dst)
        n += 1
    return n

"""Which process this is among a distributed run's: the one place that asks.

Rank zero writes what the ranks share (manifests, exports, caches, logs); every rank reads
its own part of the data. Kept apart from the file formats and the console, which both
ask it.
"""

from __future__ import annotations

import os


def rank_world() -> tuple[int, int]:
    """This process's rank and the world size of the initialized process group; (0, 1) without one."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def is_rank_zero() -> bool:
    """Whether this process writes shared files (manifests, exports, caches) under DDP.

    Read from the launcher's environment, so it holds before any process group exists:
    torchrun sets ``RANK`` (the global rank); Lightning's own launcher sets ``LOCAL_RANK``
    and ``NODE_RANK`` in the processes it starts.
    """
    env = os.environ
    if "RANK" in env:
        return env["RANK"] == "0"
    node = env.get("NODE_RANK", env.get("GROUP_RANK", "0"))
    return env.get("LOCAL_RANK", "0") == "0" and node == "0"

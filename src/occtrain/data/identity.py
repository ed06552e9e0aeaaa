"""Which world a dataset is: occtrain's record of what generated it, the world version
every table names, and an identity by content that a copy keeps and an edit changes (what
caches and scores are keyed by; ``data.shards.freshness`` asks whether shards are current)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from occtrain.data.layout import ANNOTATIONS_FILE, generator_record


def world_version(root: str | Path) -> str:
    """The version ("v<N>") of a world occtrain synthesized (its ``occtrain/dataset.json``), else "": the
    name every table measured on the world states."""
    record = generator_record(Path(root)) or {}
    return f"v{record['format_version']}" if record.get("generator") == "occtrain.synth" else ""


@dataclass(frozen=True)
class WorldIdentity:
    """A dataset by what it holds, wherever it lies: ``key`` hashes its annotations and
    generator record (a world synthesized again from the same settings, or copied to
    another machine, keeps it; a relabelled or re-split one does not), ``name`` reads."""

    key: str
    version: str
    name: str


def world_identity(root: str | Path) -> WorldIdentity:
    """The identity of the dataset at ``root`` (see :class:`WorldIdentity`). Labels are not
    hashed (gigabytes for a real release): they follow from the generator's settings, and a
    real release's annotations name every sample."""
    root = Path(root)
    record = generator_record(root)
    h = hashlib.sha256((root / ANNOTATIONS_FILE).read_bytes())
    h.update(json.dumps(record, sort_keys=True).encode())
    version = world_version(root)
    if version and record is not None:
        name = (
            f"occtrain world {version}, seed {record.get('seed')} ({record.get('train_scenes')} train + "
            f"{record.get('val_scenes')} val scenes of {record.get('frames_per_scene')} frames)"
        )
    else:
        name = f"dataset {root.resolve().name}"
    if (record or {}).get("cameras") == "blanked":  # ``data.blank_cameras``: a view, not a world
        name += ", its camera images blanked"
    return WorldIdentity(h.hexdigest()[:12], version, name)

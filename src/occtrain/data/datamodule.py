"""LightningDataModules over webdataset shards: one per data kind (frames, clips)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader
from torch.utils.data.dataloader import _BaseDataLoaderIter

from occtrain.config.groups import DataConfig, check_synth_config
from occtrain.data.camera_records import DEPTH_SCALE
from occtrain.data.cameras import CAMERA_NAMES
from occtrain.data.layout import ANNOTATIONS_FILE, DATASET_FILE, DatasetIndex, generator_record
from occtrain.data.shards import (
    KINDS,
    clip_shortfall,
    current_shards,
    make_pipeline,
    no_clips_note,
    shard_source,
    shard_urls,
    write_shards,
)
from occtrain.data.shards.positions import PAD_KEY, ShardSamples
from occtrain.errors import DataError


def shards_dir(cfg: DataConfig) -> Path:
    return Path(cfg.shards) if cfg.shards else Path(cfg.root) / "shards"


def check_data(cfg: DataConfig, clip_readers: Iterable[str] = ()) -> str:
    """Check, writing nothing, that ``cfg`` names data a run can use; say what the run will
    do with it. A dataset that exists is opened and checked (annotations, paths inside the
    root, camera folders, the synthesis record), and shards that exist must be of it as it
    is now.

    Scenes too short for one clip get frame shards only, as `occtrain data shards` writes
    by default, and the line says so; named ``clip_readers`` (stages that read clips) are
    then refused here, before anything is written, rather than when their turn comes."""
    root = Path(cfg.root)
    line, shortfall = _plan_synthesis(cfg) if not (root / ANNOTATIONS_FILE).is_file() else _plan_shards(cfg)
    if not shortfall:
        return line
    readers = list(clip_readers)
    if readers:
        raise DataError(
            f"stage '{readers[0]}' reads clips, and {shortfall}, so no clip fits; "
            "use longer scenes or shorten data.history/data.future"
        )
    return f"{line}; {no_clips_note(shortfall)}"


def _plan_synthesis(cfg: DataConfig) -> tuple[str, str | None]:
    """:func:`check_data` of a world still to synthesize: what the run will do, and why no
    clip would fit it (None when one does)."""
    root = Path(cfg.root)
    if root.exists() and not (root / DATASET_FILE).is_file():
        # Neither an Occ3D root nor a synthesis cut off halfway (which holds the record):
        # writing a synthetic world into it would train on data nobody asked for.
        what = "is empty" if root.is_dir() and not any(root.iterdir()) else "holds no annotations.json"
        raise DataError(
            f"data.root {root} {what}; point data.root at an Occ3D root (annotations.json + gts/), "
            "or at a path that does not exist yet for occtrain to synthesize its world there"
        )
    s = cfg.synth
    check_synth_config(s)
    _check_synth_record(root, cfg)  # a synthesis cut off halfway resumes only under its own settings
    line = (
        f"data.root {root} {'is incomplete' if root.exists() else 'does not exist'}: synthesizing occtrain's world "
        "there "
        f"(seed {s.seed}, {s.train_scenes}+{s.val_scenes} scenes of {s.frames_per_scene} frames)"
    )
    span = cfg.history + 1 + cfg.future
    if s.frames_per_scene >= span:
        return line, None
    return (
        line,
        f"data.synth.frames_per_scene is {s.frames_per_scene} and a clip spans history {cfg.history} + 1 + future "
        f"{cfg.future} = {span}",
    )


def _plan_shards(cfg: DataConfig) -> tuple[str, str | None]:
    """:func:`check_data` of a dataset that exists: what the run will do, and why no clip
    fits it (None when one does)."""
    root = Path(cfg.root)
    index = DatasetIndex.open(root)
    _check_synth_record(root, cfg)
    source = shard_source(index, cfg.samples_per_shard, cfg.history, cfg.future)
    ready = current_shards(index, shards_dir(cfg), source) is not None
    frames = sum(len(t) for t in index.scenes.values())
    line = f"data.root {root}: {frames} frames; shards {'ready' if ready else 'to be written'} in {shards_dir(cfg)}"
    return line, None if "clips" in source["kinds"] else clip_shortfall(index, cfg.history, cfg.future)


def ensure_data(cfg: DataConfig, verbose: bool = True) -> Path:
    """Synthesize the dataset if ``cfg.root`` is absent, write its shards if absent (see
    ``check_data``); return the shard dir."""
    root = Path(cfg.root)
    synthesized = not (root / ANNOTATIONS_FILE).is_file()
    if synthesized:
        from occtrain.data.synthesize import synthesize  # the world generator loads only when needed

        plan = check_data(cfg)  # refuses a folder that is neither a dataset nor a cut-off synthesis
        if verbose:
            from occtrain.progress import console

            console.print(plan)
        synthesize(root, cfg.synth, verbose=verbose)
    else:
        _check_synth_record(root, cfg)
    out = shards_dir(cfg)
    # Also when they exist: shards made before the dataset changed are refused, never read.
    # The kinds as `occtrain data shards` picks them: frames alone when no clip fits.
    index = write_shards(root, out, cfg.samples_per_shard, cfg.history, cfg.future)
    shortfall = index.get("missing", {}).get("clips")
    if shortfall and verbose and not synthesized:  # a synthesis's plan line said it already
        from occtrain.progress import console

        console.print(f"note: {no_clips_note(shortfall)}", markup=False)
    return out


def _check_synth_record(root: Path, cfg: DataConfig) -> None:
    """A world occtrain synthesized with other settings than the recipe's ``data.synth`` is
    refused (it would silently train on another dataset), complete or cut off halfway; real
    data has no such record, and a record of something else is refused as such."""
    record = generator_record(root)
    if not record:
        return
    if record.get("generator") != "occtrain.synth":
        if not (root / ANNOTATIONS_FILE).is_file():
            raise DataError(
                f"{root / DATASET_FILE}: records a dataset occtrain did not synthesize, and {root} has no "
                "annotations.json; point data.root elsewhere"
            )
        return
    from occtrain.data.synthesize import FORMAT_CHANGES, FORMAT_VERSION

    if record.get("format_version") != FORMAT_VERSION:
        raise DataError(
            f"{root} holds the synthetic world of an older occtrain (world v{record.get('format_version')}, now "
            f"v{FORMAT_VERSION}: "
            f"{FORMAT_CHANGES[FORMAT_VERSION]}); move it away and the run synthesizes it again"
        )
    wanted = {
        k: getattr(cfg.synth, k)
        for k in ("seed", "train_scenes", "val_scenes", "frames_per_scene", "camera_height", "camera_width")
    }
    differ = [f"{k}={record.get(k)} (recipe: {v})" for k, v in wanted.items() if record.get(k) != v]
    if differ:
        raise DataError(
            f"{root} was synthesized with {', '.join(differ)}; move it away to synthesize the recipe's world, "
            "or set data.synth to match it"
        )


def _unpadded(collate: Callable[[list[dict]], dict]) -> Callable[[list[dict]], dict]:
    """Drop the samples that only even out DDP ranks' validation batches (see ``PAD_KEY``)."""

    def wrapped(samples: list[dict]) -> dict:
        real = [s for s in samples if not s.get(PAD_KEY)]
        # A batch of padding alone (batch size 1) still goes through the model, so every
        # rank runs the same collectives; it then holds a single sample marked as padding.
        return collate(real) if real else {**collate(samples[:1]), PAD_KEY: True}

    return wrapped


#: The keys of a collated batch that hold per-sample records read from the shards' JSON
#: and text entries (sample tokens, frame metadata, clip annotations, questions, captions),
#: never a tensor: nothing to move to a device (``ShardDataModule.transfer_batch_to_device``).
RECORD_KEYS = frozenset({"token", "meta", "ann", "qa", "caption", "narration", PAD_KEY})


def collate_frames(samples: list[dict]) -> dict[str, Any]:
    """Stack single-frame samples: uint8 semantics (B,X,Y,Z), bool masks, token and meta lists,
    and the cameras when the stage reads them (see :func:`collate_cameras`)."""
    occ = [s["occ.npz"] for s in samples]
    return {
        "semantics": torch.from_numpy(np.stack([o["semantics"] for o in occ])),
        "mask_camera": torch.from_numpy(np.stack([o["mask_camera"] for o in occ]).astype(bool)),
        "mask_lidar": torch.from_numpy(np.stack([o["mask_lidar"] for o in occ]).astype(bool)),
        "token": [s["__key__"] for s in samples],
        "meta": [s["meta.json"] for s in samples],
        **collate_cameras(samples),
    }


def collate_cameras(samples: list[dict]) -> dict[str, Any]:
    """The six views of each sample, stacked in CAMERA_NAMES order: ``images`` uint8
    (B, 6, H, W, 3), ``intrinsics`` (B, 6, 3, 3), ``cam_to_ego`` (B, 6, 4, 4), and where
    the renderer wrote them ``cam_class`` uint8 (B, 6, H, W) and ``cam_depth`` metres."""
    if "cams.json" not in samples[0]:
        return {}
    names = [n.lower() for n in CAMERA_NAMES]

    def image(s: dict, stem: str) -> np.ndarray:
        png = f"{stem}.png"
        return s[png] if png in s else s[f"{stem}.jpg"]

    out: dict[str, Any] = {
        "images": torch.from_numpy(np.stack([np.stack([image(s, n) for n in names]) for s in samples])),
        "intrinsics": torch.tensor([s["cams.json"]["intrinsic"] for s in samples], dtype=torch.float32),
        "cam_to_ego": torch.tensor([s["cams.json"]["cam_to_ego"] for s in samples], dtype=torch.float32),
    }
    if all(f"{n}.class.png" in s for s in samples for n in names):
        out["cam_class"] = torch.from_numpy(np.stack([np.stack([s[f"{n}.class.png"] for n in names]) for s in samples]))
        depth = np.stack([np.stack([s[f"{n}.depth.png"] for n in names]) for s in samples]).astype(np.float32)
        out["cam_depth"] = torch.from_numpy(depth / DEPTH_SCALE)
    return out


def collate_clips(samples: list[dict]) -> dict[str, Any]:
    """Stack clip samples: semantics (B,T,X,Y,Z), camera masks, and per-sample annotations/text.

    Entries a stage chose not to read (see ``Stage.entries``) are left out of the batch.
    """
    batch: dict[str, Any] = {"token": [s["__key__"] for s in samples]}
    if "occ.npz" in samples[0]:
        occ = [s["occ.npz"] for s in samples]
        batch["semantics"] = torch.from_numpy(np.stack([o["semantics"] for o in occ]))
        batch["mask_camera"] = torch.from_numpy(np.stack([o["mask_camera"] for o in occ]).astype(bool))
    for key, entry in (
        ("ann", "ann.json"),
        ("qa", "qa.json"),
        ("caption", "caption.txt"),
        ("narration", "narration.txt"),
    ):
        if entry in samples[0]:
            batch[key] = [s[entry] for s in samples]
    batch.update(collate_cameras(samples))
    return batch


class ResumableLoader(DataLoader):
    """A training DataLoader whose position survives a checkpoint.

    Lightning stores ``state_dict()`` of stateful train loaders in its checkpoints. The
    position is the number of samples of the global training order the optimizer has
    consumed (batches set through ``consumed``, not fetched, because Lightning prefetches a
    batch ahead, times the global batch). On resume, ``__iter__`` starts the reader at that
    sample without reading what comes before: with any number of workers, and with another
    split of the same global batch over ranks, training continues on exactly the samples an
    uninterrupted run would have seen (see :mod:`occtrain.data.shards.positions`).
    """

    def __init__(self, source: ShardSamples, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.source = source
        self.consumed: Callable[[], int] = lambda: 0
        self._start = 0

    def state_dict(self) -> dict[str, int]:
        batches = int(self.consumed())
        return {"batches": batches, "samples": batches * self.source.world * self.source.batch_size}

    def load_state_dict(self, state: dict[str, int]) -> None:
        # Checkpoints before "samples" count batches of this same split over ranks.
        self._start = int(
            state.get("samples", int(state.get("batches", 0)) * self.source.world * self.source.batch_size)
        )

    def __iter__(self) -> _BaseDataLoaderIter:
        self.source.start, self._start = self._start, 0
        return super().__iter__()


COLLATE: dict[str, Callable[[list[dict]], dict]] = {
    "frames": _unpadded(collate_frames),
    "clips": _unpadded(collate_clips),
}


class ShardDataModule(L.LightningDataModule):
    """Feeds one kind of shard (``frames`` or ``clips``) to a stage.

    ``prepare_data`` (rank zero) synthesizes and shards the embedded world when the
    configured dataset is absent. Training reads a seeded order of epochs forever (set
    ``max_steps``), each rank its own batches of it; validation reads each val sample
    exactly once across DDP ranks.
    """

    def __init__(
        self,
        cfg: DataConfig,
        kind: str,
        entries: dict[str, tuple[str, ...] | None] | None = None,
        cameras: bool = False,
    ):
        super().__init__()
        if kind not in KINDS:
            raise DataError(f"unknown data kind '{kind}'; choose from {', '.join(KINDS)}")
        self.cfg, self.kind, self.entries, self.cameras = cfg, kind, entries or {}, cameras

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        """Lightning's move, less the batch's per-sample records (``RECORD_KEYS``): clip
        annotations with every box and future, questions, captions. Lightning walks a
        batch item by item looking for tensors; through those records that took 13 ms a
        quickstart clip batch, every step, to find none (``tools/bench/data.py transfer``)."""
        if not isinstance(batch, dict):
            return super().transfer_batch_to_device(batch, device, dataloader_idx)
        rest = {k: v for k, v in batch.items() if k not in RECORD_KEYS}
        moved = super().transfer_batch_to_device(rest, device, dataloader_idx)
        return {k: moved[k] if k in moved else v for k, v in batch.items()}

    def prepare_data(self) -> None:
        ensure_data(self.cfg)

    def loader(self, split: str, train: bool) -> DataLoader:
        urls, total = shard_urls(shards_dir(self.cfg), self.kind, split)
        if not urls:
            raise DataError(f"{shards_dir(self.cfg)}: no {split} {self.kind} shards; synthesize more {split} scenes")
        pipeline = make_pipeline(
            urls,
            train=train,
            total=total,
            shuffle_buffer=self.cfg.shuffle_buffer,
            seed=self.cfg.seed,
            entries=self.entries.get(split),
            batch_size=self.cfg.batch_size,
            cameras=self.cameras,
        )
        batch_size, workers, collate = self.cfg.batch_size, self.cfg.num_workers, COLLATE[self.kind]
        if not train:
            return DataLoader(pipeline, batch_size=batch_size, num_workers=workers, collate_fn=collate)
        return ResumableLoader(
            pipeline.pipeline[0], pipeline, batch_size=batch_size, num_workers=workers, collate_fn=collate
        )

    def train_dataloader(self) -> DataLoader:
        return self.loader("train", train=True)

    def val_dataloader(self) -> DataLoader:
        return self.loader("val", train=False)

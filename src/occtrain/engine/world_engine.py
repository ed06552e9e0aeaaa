"""The world-model engine: a family's world model with the frozen encoders it reads
through and the text tokenizer, used as one with the task settings the model is trained with.

It encodes what the prompts read through a frozen encoder once per dataset (scenes
through the scene encoder, and the per-sample inputs the family registered as encoded,
such as camera views through the vision encoder; cached on disk),
turns clips into token sequences through the family's tasks, and rolls answers out by
generation. Training stages, ``occtrain eval``, the planner, distillation, the Python API
and the benchmarks all use it; it names no family and never imports Lightning.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from occtrain.config.llm import MAX_NEW_TEXT_TOKENS
from occtrain.core.builder import collate
from occtrain.core.decoding import ActionAnswer, Answer, SceneAnswer, TextAnswer
from occtrain.core.lm_world_model import LMWorldModel
from occtrain.core.packing import pack_rows
from occtrain.core.protocols import CameraSceneEncoder, SceneEncoder
from occtrain.core.registry import get_world
from occtrain.core.sample_inputs import SampleInput
from occtrain.core.sequence import TokenSequence
from occtrain.core.shared_tasks import TaskConfig, sample_task, unpacked
from occtrain.core.vocab import JointVocab
from occtrain.data.clips import Actions, Branch, Clip, Part, Scene, Text, clip_rng
from occtrain.data.layout import DatasetIndex
from occtrain.data.shards import dataset_fingerprint
from occtrain.engine.moved_scenes import MovedScenes
from occtrain.errors import DataError
from occtrain.formats.io import atomic_write_safetensors
from occtrain.models.camera_encoder import MultiViewEncoder
from occtrain.progress import progress_bar
from occtrain.ranks import is_rank_zero

#: The scene cache's file name, completed by the key of what made it (``scene_cache_key``).
SCENE_CACHE = "scenes-{key}.safetensors"
#: The shard entries a world-model stage trains on when scenes come from the cache.
TEXT_ENTRIES = ("ann.json", "qa.json", "narration.txt")


def move_batch(batch: dict, device: torch.device) -> dict:
    """The batch's tensors on ``device`` (other values as they are)."""
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


def scene_cache_key(encoder: torch.nn.Module, index: DatasetIndex) -> str:
    """What a scene cache's rows depend on, hashed: the frozen encoder (every file of the
    export it was loaded from, or its weights when it has none) and the dataset (its root
    and fingerprint). Stages and evaluations that read the same encoder on the same data
    find one file; another encoder or another world never does."""
    h = hashlib.sha256(type(encoder).__name__.encode())
    export_dir = encoder.export_dir if isinstance(encoder, SceneEncoder) else None
    if export_dir is not None:
        for path in sorted(p for p in Path(export_dir).rglob("*") if p.is_file()):
            h.update(str(path.relative_to(export_dir)).encode())
            h.update(path.read_bytes())
    else:
        for name, tensor in encoder.state_dict().items():
            h.update(name.encode())
            h.update(tensor.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    h.update(str(index.root.resolve()).encode())
    h.update(dataset_fingerprint(index).encode())
    return h.hexdigest()[:16]


@torch.no_grad()
def per_sample_cache(
    index: DatasetIndex,
    cache_file: Path | None,
    what: str,
    encode: Callable[[list[tuple[str, str]]], torch.Tensor],
    batch_size: int = 8,
) -> dict[str, torch.Tensor]:
    """Sample token -> ``encode``'s row for it, over every frame of the dataset in chunks of
    ``(scene, token)``: read from ``cache_file`` when it exists, else computed (with a
    progress bar) and written there atomically by rank zero (kept in memory only without one)."""
    from safetensors.torch import load_file

    if cache_file is not None and cache_file.is_file():
        return load_file(str(cache_file))
    samples = list(index.samples())
    cache: dict[str, torch.Tensor] = {}
    with progress_bar(len(samples), what) as advance:
        for i in range(0, len(samples), batch_size):
            chunk = samples[i : i + batch_size]
            for (_, token), row in zip(chunk, encode(chunk).cpu()):
                cache[token] = row.contiguous()
            advance(len(chunk))
    if cache_file is not None and is_rank_zero():
        atomic_write_safetensors(cache_file, cache)
    return cache


class WorldModelEngine(torch.nn.Module):
    """A family's world model, its frozen encoders and its text tokenizer, used as one.

    ``scene_encoder``: what the prompts' scenes go through (``core.protocols.SceneEncoder``,
    None for a model whose prompts hold none); ``vision``: the frozen camera encoder of a
    model that reads the cameras (None otherwise).
    """

    scene_encoder: torch.nn.Module | None
    vision: MultiViewEncoder | None

    def __init__(
        self,
        scene_encoder: torch.nn.Module | None,
        world: LMWorldModel,
        text_tokenizer: Any,
        tasks: TaskConfig,
        max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS,
        family: str = "",
        vision: MultiViewEncoder | None = None,
    ):
        super().__init__()
        self.scene_encoder = scene_encoder.eval().requires_grad_(False) if scene_encoder is not None else None
        self.vision = vision.eval().requires_grad_(False) if vision is not None else None
        self.world = world
        self.text_tokenizer = text_tokenizer
        #: The task/prompt settings the model trains (or was trained) with: every prompt
        #: built through this engine, in training, evaluation or a later stage, uses them.
        self.tasks = tasks
        self.max_new_text_tokens = int(max_new_text_tokens)
        self.family = family
        self.spec = get_world(family, "family")
        #: The family's tasks (builders, evaluation items, scorers), by name.
        self.task_specs = dict(self.spec.tasks)
        #: The per-sample inputs the family's parts read (``PromptInputs.read``), by name.
        self.sample_inputs: dict[str, SampleInput] = {i.name: i for i in self.spec.sample_inputs}
        #: Sample token -> the scene encoder's row, when the dataset was encoded ahead (see
        #: ``prepare_inputs``); input name -> sample token -> row, for the encoded inputs;
        #: the dataset they come from.
        self.scene_cache: dict[str, torch.Tensor] | None = None
        self.input_caches: dict[str, dict[str, torch.Tensor]] = {}
        # The dataset of each sample met one at a time (``add_samples``): the caches may hold
        # frames of several (a run's dataset and the frames closed-loop training drove into).
        self._index_of: dict[str, DatasetIndex] = {}
        self.data_index: DatasetIndex | None = None
        self._scene_cache_root: Path | None = None
        # The scene cache's rows back to their frames, made from the cache it was made from.
        self._frame_of_codes: dict[bytes, str] = {}
        self._frames_from: dict[str, torch.Tensor] | None = None
        if isinstance(self.scene_encoder, SceneEncoder) and self.scene_encoder.discrete:
            # What query blocks that hold a scene moved by the ego read through.
            world.scene_mover = MovedScenes(world.vocab, self.scene_encoder, self.observed_labels)

    @property
    def vocab(self) -> JointVocab:
        return self.world.vocab

    def train(self, mode: bool = True) -> WorldModelEngine:
        super().train(mode)
        for frozen in (self.scene_encoder, self.vision):
            if frozen is not None:
                frozen.eval()  # no dropout, no codebook updates
        return self

    def operation(self, name: str) -> Callable[..., Any] | None:
        """The family's operation ``name`` (see ``WorldSpec.operations``), or None."""
        return self.spec.operations.get(name)

    # -- what the prompts read through frozen encoders
    def encoded_inputs(self) -> list[SampleInput]:
        """The family's inputs made through a frozen encoder (encoded once per dataset)."""
        return [i for i in self.sample_inputs.values() if i.encoded]

    def reads_scenes(self) -> bool:
        """Whether the world model's prompts hold scenes (through the scene encoder)."""
        return self.scene_encoder is not None and self.world.reads_scenes

    def needs_semantics(self) -> bool:
        """Whether a batch must carry label volumes for the prompts' scenes (no cache)."""
        return self.reads_scenes() and self.scene_cache is None

    def scenes_from_cameras(self) -> bool:
        """Whether the scene encoder reads the cameras (its rows come from ``encode_samples``)."""
        return isinstance(self.scene_encoder, CameraSceneEncoder)

    @property
    def encoder(self) -> SceneEncoder:
        """The scene encoder, for a model whose prompts hold scenes."""
        if not isinstance(self.scene_encoder, SceneEncoder):
            raise ValueError(f"the '{self.family}' world model has no scene encoder")
        return self.scene_encoder

    @torch.no_grad()
    def scenes(self, batch: dict, needed: list[set[int]]) -> dict[tuple[int, int], torch.Tensor]:
        """The scene-encoder row of each clip frame a sample needs: from the cache when
        there is one (then the batch needs no occupancy at all), else encoded in one batch."""
        keys = [(b, f) for b, frames in enumerate(needed) for f in sorted(frames)]
        if not keys:
            return {}
        if self.scene_cache is not None:
            return {(b, f): self.scene_cache[batch["ann"][b]["tokens"][f]] for b, f in keys}
        frames = torch.stack([batch["semantics"][b][f] for b, f in keys]).long()
        return dict(zip(keys, self.encoder.encode(frames)))

    def prepare_inputs(
        self, data_root: str | Path, cache_dir: Path | None = None, shared_cache_dir: Path | None = None
    ) -> None:
        """Encode once what the prompts read through a frozen encoder (the family's encoded
        inputs, such as camera views; the scenes of a model whose prompts hold scenes),
        cached in ``cache_dir`` (in memory only without one; scenes only with one, unless
        the scene encoder reads the cameras: its scenes are always encoded ahead).

        The scenes go to ``shared_cache_dir`` when given (else ``cache_dir``) under a name
        keyed by their content (``scene_cache_key``), so the stages of a run that read one
        scene encoder encode the dataset once between them."""
        self.data_index = index = DatasetIndex.open(data_root)
        for given in self.encoded_inputs():
            self.prepare_input(given, index, cache_dir / given.cache_file if cache_dir is not None else None)
        if (
            self.reads_scenes()
            and (cache_dir is not None or self.scenes_from_cameras())
            and not self._has_scenes_of(index)
        ):
            # The key reads the encoder's export: only when there is a cache file to name.
            where = shared_cache_dir or cache_dir
            encoder = self.scene_encoder
            assert encoder is not None  # reads_scenes()
            cache_file = where / SCENE_CACHE.format(key=scene_cache_key(encoder, index)) if where is not None else None
            self.build_scene_cache(data_root, cache_file)

    def _has_scenes_of(self, index: DatasetIndex) -> bool:
        return self.scene_cache is not None and self._scene_cache_root == index.root

    @torch.no_grad()
    def build_scene_cache(self, data_root: str | Path, cache_file: Path | None, batch_size: int = 8) -> None:
        """Encode every frame of the dataset once (the encoder is frozen), kept in
        ``cache_file`` (safetensors, written atomically) so a resumed stage reuses it; in
        memory only without one. A no-op when this dataset's scenes are encoded already."""
        index = DatasetIndex.open(data_root)
        if self._has_scenes_of(index):
            return
        self.scene_cache = per_sample_cache(
            index,
            cache_file,
            "encoding scenes with the frozen scene encoder",
            partial(self._scene_rows, index),
            batch_size,
        )
        self._scene_cache_root = index.root

    def _scene_rows(self, index: DatasetIndex, chunk: list[tuple[str, str]]) -> torch.Tensor:
        """The scene encoder's rows of some samples of ``index`` (as the scene cache keeps them)."""
        encoder = self.encoder
        if isinstance(encoder, CameraSceneEncoder):
            return encoder.encode_samples(index, chunk).float()
        sem = torch.from_numpy(np.stack([index.labels(s, t)["semantics"] for s, t in chunk])).long()
        rows = encoder.encode(sem)
        return rows.to(torch.int32) if encoder.discrete else rows.float()

    @torch.no_grad()
    def add_samples(self, index: DatasetIndex, samples: list[tuple[str, str]]) -> None:
        """Encode what the prompts read of these samples of ``index`` through the frozen
        encoders into the in-memory caches, beside what is there: closed-loop driving meets
        its frames one planning step at a time, where ``prepare_inputs`` encodes a dataset whole."""
        self.data_index = index
        tokens = [t for _, t in samples]
        self._index_of.update(dict.fromkeys(tokens, index))
        for given in self.encoded_inputs():
            cache = self.input_caches.setdefault(given.name, {})
            cache.update(zip(tokens, given.rows(self, index, samples).cpu()))
        if self.reads_scenes():
            cache = self.scene_cache if self.scene_cache is not None else {}
            cache.update(zip(tokens, self._scene_rows(index, samples).cpu()))
            self.scene_cache = cache
            self._scene_cache_root = index.root
            self._frames_from = None  # the same dict, grown: observed_labels maps its codes anew

    def observed_labels(self, codes: torch.Tensor) -> torch.Tensor | None:
        """The label volume (X, Y, Z) of the dataset frame whose cached scene row is ``codes``
        (flat), or None (no cache, or codes no frame has: a generated scene)."""
        if self.scene_cache is None or self.data_index is None:
            return None
        if self._frames_from is not self.scene_cache:  # another dataset's cache: map it anew
            self._frame_of_codes = {
                row.reshape(-1).long().numpy().tobytes(): token for token, row in self.scene_cache.items()
            }
            self._frames_from = self.scene_cache
        token = self._frame_of_codes.get(codes.reshape(-1).long().cpu().numpy().tobytes())
        if token is None:
            return None
        index = self.index_of(token)
        return torch.from_numpy(index.labels(index.scene_of(token), token)["semantics"]).long()

    @torch.no_grad()
    def decode_scenes(self, scenes: torch.Tensor) -> torch.Tensor:
        """Scene rows (N, ...) -> (N, X, Y, Z) class labels through the scene encoder."""
        return self.encoder.decode(scenes)

    def encodes_labels(self) -> bool:
        """Whether the scene encoder makes its rows from label volumes (not from the cameras)."""
        return isinstance(self.scene_encoder, SceneEncoder) and not self.scenes_from_cameras()

    @torch.no_grad()
    def encode_scenes(self, semantics: torch.Tensor) -> torch.Tensor:
        """Label volumes (N, X, Y, Z) -> their scene rows through the scene encoder (one that
        reads labels: ``encodes_labels``)."""
        if not self.encodes_labels():
            raise ValueError(f"the '{self.family}' world model's scene encoder does not read label volumes")
        encoder = self.scene_encoder
        assert isinstance(encoder, torch.nn.Module)
        first = next(itertools.chain(encoder.parameters(), encoder.buffers()), None)
        return self.encoder.encode(semantics.long().to(first.device if first is not None else "cpu"))

    @torch.no_grad()
    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 views (B, N, H, W, 3) -> the world model's image tokens (B, T, D): the frozen
        encoder's patch tokens, pooled as the world model reads them."""
        if self.vision is None:
            raise ValueError(f"the '{self.family}' world model reads no cameras")
        tokens, grid = self.vision(images.to(self.vision.camera_embed.device))
        return self.world.pool_images(tokens, grid, images.shape[1]).float()

    def prepare_input(
        self, given: SampleInput, index: DatasetIndex, cache_file: Path | None = None, batch_size: int = 8
    ) -> None:
        """Encode one of the family's encoded inputs for every frame of ``index`` once (its
        encoder is frozen), kept in ``cache_file`` (safetensors, written atomically; in
        memory only without one). A no-op when it is encoded already."""
        if given.name in self.input_caches:
            return
        if given.reads_cameras and not index.has_cameras and (cache_file is None or not cache_file.is_file()):
            raise DataError(
                f"{index.root}: the dataset has no camera images, which the '{self.family}' world model reads"
            )
        self.input_caches[given.name] = per_sample_cache(
            index, cache_file, given.what or f"encoding {given.name}", partial(given.rows, self, index), batch_size
        )

    # -- what a family's parts read (see ``SequenceBuilder.lay``)
    def scene(self, frame: int, scenes: dict[int, torch.Tensor]) -> torch.Tensor:
        return scenes[frame]

    def read(self, name: str, token: str) -> torch.Tensor:
        """The family's input ``name`` of sample ``token`` (``PromptInputs``): an encoded
        one from its cache, another read from the dataset (``prepare_inputs`` first)."""
        given = self.sample_inputs.get(name)
        if given is None:
            raise KeyError(f"the '{self.family}' family registers no input '{name}' (WorldSpec.sample_inputs)")
        if given.encoded:
            if name not in self.input_caches:
                raise RuntimeError(f"prepare_inputs(data_root) before laying out a part that reads '{name}'")
            return self.input_caches[name][token]
        if self.data_index is None:
            raise RuntimeError(f"prepare_inputs(data_root) before laying out a part that reads '{name}'")
        index = self.index_of(token)
        return given.rows(self, index, [(index.scene_of(token), token)])[0]

    def index_of(self, token: str) -> DatasetIndex:
        """The dataset sample ``token`` is of: the one it was added from, else the prepared one."""
        index = self._index_of.get(token, self.data_index)
        if index is None:
            raise RuntimeError("prepare_inputs(data_root) before reading a sample's dataset")
        return index

    # -- sequences
    def encode_parts(self, parts: list[Part], scenes: dict[int, torch.Tensor]) -> TokenSequence:
        """One task's parts -> a TokenSequence, scenes looked up by clip frame in ``scenes``."""
        builder = self.world.builder()
        for part in parts:
            builder.lay(part, self, scenes)
        return builder.build()

    def task_batch(
        self, clips: list[Clip], batch: dict, seed: int, pack: int | None = None
    ) -> tuple[dict | None, list[str | None]]:
        """Draw a task per clip (by the engine's task weights) and collate the sequences into
        a model batch, one to a row or, with ``pack``, packed into rows of that many tokens
        (0: the longest sequence's; see ``core.packing``). Returns the batch (None when no
        clip has a task) and per clip the task drawn, None for a clip that no configured
        task applies to: it is left out, not given a made-up answer."""
        drawn = [sample_task(c, self.tasks, seed, c.anchor["token"], self.task_specs) for c in clips]
        needed = [{p.frame for p in d[1] if isinstance(p, Scene)} if d else set() for d in drawn]
        scenes = self.scenes(batch, needed)
        seqs = [
            self.encode_parts(d[1], {f: scenes[(b, f)] for f in needed[b]})
            for b, d in enumerate(drawn)
            if d is not None
        ]
        names = [d[0] if d else None for d in drawn]
        if not seqs:
            return None, names
        rows = pack_rows([len(q) for q in seqs], pack) if pack is not None else None
        return collate(seqs, self.vocab.pad_id, rows), names

    # -- generation
    def prompt_and_plan(self, parts: list[Part], scenes: dict[int, torch.Tensor]) -> tuple[TokenSequence, list[Answer]]:
        """The prompt (the parts before the first supervised one) laid out, and what to
        generate after it: text up to end-of-text, as many waypoints as the reference, a scene."""
        if any(isinstance(p, Branch) for p in parts):
            # One decoder cannot keep branches apart: each would be generated as an answer.
            raise ValueError("a prompt with branches generates one branch at a time (core.shared_tasks.unpacked)")
        first = next(i for i, p in enumerate(parts) if p.supervise)
        # A part nothing after it reads (OccVLA's occupancy queries) is left out (its Setting 2).
        prompt = [p for p in parts[:first] if p.read_after]
        plan: list[Answer] = [
            TextAnswer(self.max_new_text_tokens)
            if isinstance(p, Text)
            else ActionAnswer(len(p.xy), p.base)
            if isinstance(p, Actions)
            else SceneAnswer()
            for p in parts[first:]
        ]
        return self.encode_parts(prompt, scenes), plan

    @torch.no_grad()
    def rollout(self, parts: list[Part], scenes: dict[int, torch.Tensor]) -> tuple[list[Part], dict[int, torch.Tensor]]:
        """Generate the answer parts of a task one after the other with one decoder, each
        conditioned on the ones generated before it (not on the ground truth). Returns the
        generated parts and the row of every scene, generated ones included."""
        prefix, plan = self.prompt_and_plan(parts, scenes)
        return self._as_parts(self.world.generate(prefix, plan), scenes)

    def task_items(self, task: str, clip: Clip, seed: int = 0, every: bool = False) -> list[list[Part]]:
        """The prompts of ``task`` on ``clip``: its one training draw (from ``seed`` and the
        clip's token; a packed draw's branches one prompt each), or with ``every`` each item
        evaluation asks (every question of the frame for QA); empty when the task does not apply."""
        spec = self.task_specs[task]
        if every and spec.every_item is not None:
            return spec.every_item(clip, self.tasks)
        parts = spec.build(clip, self.tasks, clip_rng(seed, clip.anchor["token"]))
        return unpacked(parts) if parts is not None else []

    def rollouts(
        self,
        task: str,
        clips: list[Clip],
        batch: dict,
        seed: int = 0,
        batched: bool = True,
        every: bool = False,
        select: Callable[[Clip, list[Part]], bool] | None = None,
    ) -> Iterator[tuple[int, list[Part], list[Part], dict[int, torch.Tensor]]]:
        """Build ``task``'s prompts for every clip (``task_items``, with the engine's prompt
        settings; ``select`` keeps some) and roll their answers out: (sample index, parts,
        generated parts, scenes) per prompt. The prompts generate together (one batched
        forward per step); ``batched=False`` rolls them out one after the other (the
        reference)."""
        built = [
            [parts for parts in self.task_items(task, c, seed, every) if select is None or select(c, parts)]
            for c in clips
        ]
        needed = [{p.frame for ps in items for p in ps if isinstance(p, Scene) and not p.supervise} for items in built]
        scenes = self.scenes(batch, needed)
        todo = [(b, parts, {f: scenes[(b, f)] for f in needed[b]}) for b, items in enumerate(built) for parts in items]
        if not batched:
            for b, parts, context in todo:
                yield (b, parts, *self.rollout(parts, context))
            return
        prompts = [self.prompt_and_plan(parts, context) for _, parts, context in todo]
        outputs = self.world.generate_batch(*map(list, zip(*prompts))) if todo else []
        for (b, parts, context), out in zip(todo, outputs):
            yield (b, parts, *self._as_parts(out, context))

    def _as_parts(self, out: list, scenes: dict[int, torch.Tensor]) -> tuple[list[Part], dict[int, torch.Tensor]]:
        """Decoded answers -> generated parts, and the scenes with the generated ones added."""
        scenes = dict(scenes)
        next_frame = max(scenes) + 1 if scenes else 0
        generated: list[Part] = []
        for value in out:
            if isinstance(value, list):
                generated.append(Text(self.vocab.decode_text(value), True))
            elif value.dtype.is_floating_point and value.dim() == 2 and value.shape[-1] == 2:
                generated.append(Actions(tuple(map(tuple, value.tolist())), True))
            else:
                scenes[next_frame] = value
                generated.append(Scene(next_frame, True))
                next_frame += 1
        return generated, scenes

    def default_tasks(self, kind: str) -> WorldModelEngine:
        """Give the engine's task settings the family's default tasks for stage ``kind``
        ("pretrain" or "instruct") when they name none; returns self."""
        if not self.tasks.weights:
            self.tasks.weights = dict(self.spec.default_tasks.get(kind, {}))
        return self

    def with_settings(
        self, tasks: TaskConfig | None = None, max_new_text_tokens: int | None = None
    ) -> WorldModelEngine:
        """A stage's own task settings and generation length in place of the saved ones; returns self."""
        if tasks is not None:
            self.tasks = tasks
        if max_new_text_tokens is not None:
            self.max_new_text_tokens = int(max_new_text_tokens)
        return self

"""The world-model engine: the frozen scene tokenizer, the world model and the text
tokenizer used as one, with the task settings the model is trained with.

It encodes scenes (once per dataset, through the code cache), turns clips into token
sequences through a family's tasks, and rolls answers out by generation. Training stages,
``occtrain eval``, the planner, distillation and the benchmarks all use it; nothing here
imports Lightning.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from occtrain.config.llm import MAX_NEW_TEXT_TOKENS
from occtrain.data.clips import Actions, Branch, Clip, Images, Occupancy, Part, Scene, Text, clip_rng
from occtrain.data.layout import DatasetIndex
from occtrain.data.text_formats import parse_meta_action
from occtrain.families.occllama.batch_decoding import ActionAnswer, Answer, SceneAnswer, TextAnswer
from occtrain.families.occllama.tasks import TaskConfig, sample_task
from occtrain.families.occllama.tokens import TokenSequence
from occtrain.families.occllama.world_model import OccWorldModel, collate
from occtrain.families.registry import get_family
from occtrain.errors import DataError
from occtrain.io import atomic_write_safetensors, is_rank_zero
from occtrain.models.vocab import JointVocab
from occtrain.progress import progress_bar

#: The file of the scene-code cache inside a stage directory's ``cache/``.
CODE_CACHE = "scene_codes.safetensors"
#: The file of the image-token cache (a vision-language world model's frozen camera features).
IMAGE_CACHE = "image_tokens.safetensors"
#: The shard entries a world-model stage trains on when scenes come from the code cache.
TEXT_ENTRIES = ("ann.json", "qa.json", "narration.txt")


def move_batch(batch: dict, device: torch.device) -> dict:
    """The batch's tensors on ``device`` (other values as they are)."""
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


@dataclass
class CotOutput:
    """A generated chain of thought: its text and the trajectory that follows it."""

    text: str
    waypoints: np.ndarray  # (6, 2)


@torch.no_grad()
def per_sample_cache(
    index: DatasetIndex, cache_file: Path | None, what: str, encode: Callable[[list[tuple[str, str]]], torch.Tensor],
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
    """The scene tokenizer (frozen), the world model and the text tokenizer, used as one.

    Turns clips and task parts into token sequences, and rolls answers out by generation.
    Stages, ``occtrain eval``, the planner and distillation all go through this class.
    """

    def __init__(
        self, scene_tokenizer: torch.nn.Module, world: OccWorldModel, text_tokenizer: Any, tasks: TaskConfig,
        max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS, family: str = "occllama", vision: torch.nn.Module | None = None,
    ):
        super().__init__()
        self.scene_tokenizer = scene_tokenizer.eval().requires_grad_(False)
        #: The frozen camera encoder of a vision-language world model (OccVLA), else None.
        self.vision = vision.eval().requires_grad_(False) if vision is not None else None
        self.world = world
        self.text_tokenizer = text_tokenizer
        #: The task/prompt settings the model trains (or was trained) with: every prompt
        #: built through this engine, in training, evaluation or a later stage, uses them.
        self.tasks = tasks
        self.max_new_text_tokens = int(max_new_text_tokens)
        self.family = family
        spec = get_family(family)
        #: The family's task builders: its prompts, by task name.
        self.task_builders = dict(spec.tasks)
        self.every_item = dict(spec.every_item)
        self._default_tasks = {kind: dict(weights) for kind, weights in spec.default_tasks.items()}
        #: Sample token -> codes, when the dataset was encoded ahead (see build_code_cache).
        self.code_cache: dict[str, torch.Tensor] | None = None
        #: Sample token -> pooled image tokens (see prepare_images), and the dataset they
        #: and the occupancy targets are read from.
        self.image_cache: dict[str, torch.Tensor] | None = None
        self.data_index: DatasetIndex | None = None

    @property
    def vocab(self) -> JointVocab:
        return self.world.vocab

    def train(self, mode: bool = True) -> WorldModelEngine:
        super().train(mode)
        self.scene_tokenizer.eval()  # frozen: no dropout, no codebook updates
        if self.vision is not None:
            self.vision.eval()
        return self

    # -- scenes
    @torch.no_grad()
    def scene_codes(self, batch: dict, needed: list[set[int]]) -> dict[tuple[int, int], torch.Tensor]:
        """Codes (codebooks * h*w,) of the clip frames each sample needs: from the code cache when one is
        set (then the batch needs no occupancy at all), else encoded in one tokenizer batch."""
        keys = [(b, f) for b, frames in enumerate(needed) for f in sorted(frames)]
        if not keys:
            return {}
        if self.code_cache is not None:
            return {(b, f): self.code_cache[batch["ann"][b]["tokens"][f]] for b, f in keys}
        frames = torch.stack([batch["semantics"][b][f] for b, f in keys]).long()
        codes = self.scene_tokenizer.encode(frames).flatten(1)
        return dict(zip(keys, codes))

    @torch.no_grad()
    def build_code_cache(self, data_root: str | Path, cache_file: Path, batch_size: int = 8) -> None:
        """Encode every frame of the dataset once (the tokenizer is frozen), kept in
        ``cache_file`` (safetensors, written atomically) so a resumed stage reuses it."""
        index = DatasetIndex.open(data_root)
        device = self.scene_tokenizer.codebook.device

        def encode(chunk: list[tuple[str, str]]) -> torch.Tensor:
            sem = torch.from_numpy(np.stack([index.labels(s, t)["semantics"] for s, t in chunk])).long().to(device)
            return self.scene_tokenizer.encode(sem).flatten(1).to(torch.int32)

        self.code_cache = per_sample_cache(index, cache_file, "encoding scenes with the frozen tokenizer", encode, batch_size)

    def prepare_inputs(self, data_root: str | Path, cache_dir: Path | None = None) -> None:
        """Encode once what the prompts read through a frozen encoder, cached in
        ``cache_dir`` (in memory only without one): the camera tokens of a model that reads
        cameras, else the scene codes."""
        if self.vision is not None:
            self.prepare_images(data_root, cache_dir / IMAGE_CACHE if cache_dir is not None else None)
        elif cache_dir is not None:
            self.build_code_cache(data_root, cache_dir / CODE_CACHE)

    # -- cameras (vision-language world models)
    @torch.no_grad()
    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 views (B, N, H, W, 3) -> the world model's image tokens (B, N * rows * cols, D):
        the frozen encoder's patch tokens, average-pooled per camera."""
        from occtrain.models.vision import pool_views

        tokens, grid = self.vision(images.to(self.vision.camera_embed.device))
        return pool_views(tokens, grid, images.shape[1], tuple(self.world.cfg.image_tokens)).float()

    def prepare_images(self, data_root: str | Path, cache_file: Path | None = None, batch_size: int = 8) -> None:
        """Encode every frame's cameras once (the encoder is frozen), kept in ``cache_file``
        (safetensors, written atomically; in memory only without one), and remember the
        dataset for the occupancy targets. A no-op for a world model without cameras."""
        if self.vision is None:
            return
        self.data_index = index = DatasetIndex.open(data_root)
        if self.image_cache is not None:
            return
        if not index.has_cameras and (cache_file is None or not cache_file.is_file()):
            raise DataError(f"{data_root}: the dataset has no camera images, which the '{self.family}' world model reads")

        def encode(chunk: list[tuple[str, str]]) -> torch.Tensor:
            return self.encode_images(torch.from_numpy(np.stack([index.images(s, t) for s, t in chunk])))

        self.image_cache = per_sample_cache(index, cache_file, "encoding the cameras with the frozen vision encoder", encode, batch_size)

    def image_tokens(self, token: str) -> torch.Tensor:
        """The pooled image tokens of sample ``token`` (``prepare_images`` first)."""
        if self.image_cache is None:
            raise RuntimeError("prepare_images(data_root) before laying out images")
        return self.image_cache[token]

    def voxels(self, token: str) -> torch.Tensor:
        """The occupancy labels uint8 (X, Y, Z) of sample ``token``, from the dataset."""
        if self.data_index is None:
            raise RuntimeError("prepare_images(data_root) before laying out occupancy queries")
        index = self.data_index
        return torch.from_numpy(index.labels(index.scene_of(token), token)["semantics"])

    @torch.no_grad()
    def decode_scenes(self, codes: torch.Tensor) -> torch.Tensor:
        """(N, codebooks * h*w) codes -> (N, X, Y, Z) class labels through the tokenizer's decoder."""
        h, w = self.scene_tokenizer.latent_hw
        k = self.scene_tokenizer.num_codebooks
        grids = codes.view(-1, h, w) if k == 1 else codes.view(-1, k, h, w)
        return self.scene_tokenizer.decode(grids).argmax(1)

    # -- sequences
    def encode_parts(self, parts: list[Part], codes: dict[int, torch.Tensor]):
        """One task's parts -> a TokenSequence, scenes looked up by clip frame in ``codes``."""
        builder = self.world.builder()
        for part in parts:
            if isinstance(part, Text):
                builder.text(part.text, part.supervise)
            elif isinstance(part, Scene):
                builder.scene(codes[part.frame], part.supervise)
            elif isinstance(part, Branch):
                builder.branch()
            elif isinstance(part, Images):
                builder.images(self.image_tokens(part.token))
            elif isinstance(part, Occupancy):
                builder.occupancy(self.voxels(part.token), part.weight)
            else:
                builder.actions(torch.tensor(part.xy, dtype=torch.float32), part.supervise)
        return builder.build()

    def task_batch(self, clips: list[Clip], batch: dict, seed: int) -> tuple[dict | None, list[str | None]]:
        """Draw a task per clip (by the engine's task weights) and collate the sequences into
        a model batch. Returns the batch (None when no clip has a task) and per clip the task
        drawn, None for a clip that no configured task applies to: it is left out, not
        given a made-up answer."""
        drawn = [sample_task(c, self.tasks, seed, c.anchor["token"], self.task_builders) for c in clips]
        needed = [{p.frame for p in d[1] if isinstance(p, Scene)} if d else set() for d in drawn]
        codes = self.scene_codes(batch, needed)
        seqs = [
            self.encode_parts(d[1], {f: codes[(b, f)] for f in needed[b]}) for b, d in enumerate(drawn) if d is not None
        ]
        names = [d[0] if d else None for d in drawn]
        return (collate(seqs, pad_id=self.vocab.pad_id) if seqs else None), names

    # -- generation
    def prompt_and_plan(self, parts: list[Part], codes: dict[int, torch.Tensor]) -> tuple[TokenSequence, list[Answer]]:
        """The prompt (the parts before the first supervised one) laid out, and what to
        generate after it: text up to end-of-text, as many waypoints as the reference, a scene."""
        first = next(i for i, p in enumerate(parts) if p.supervise)
        # Occupancy queries are seen by nothing after them: a prompt skips them (OccVLA's Setting 2).
        prompt = [p for p in parts[:first] if not isinstance(p, Occupancy)]
        plan: list[Answer] = [
            TextAnswer(self.max_new_text_tokens) if isinstance(p, Text)
            else ActionAnswer(len(p.xy)) if isinstance(p, Actions) else SceneAnswer()
            for p in parts[first:]
        ]
        return self.encode_parts(prompt, codes), plan

    @torch.no_grad()
    def rollout(self, parts: list[Part], codes: dict[int, torch.Tensor]) -> tuple[list[Part], dict[int, torch.Tensor]]:
        """Generate the answer parts of a task one after the other with one decoder, each
        conditioned on the ones generated before it (not on the ground truth). Returns the
        generated parts and the codes of every scene, generated ones included."""
        prefix, plan = self.prompt_and_plan(parts, codes)
        decoder = self.world.decoder(prefix)
        return self._as_parts([decoder.answer(a) for a in plan], codes)

    def task_items(self, task: str, clip: Clip, seed: int = 0, every: bool = False) -> list[list[Part]]:
        """The prompts of ``task`` on ``clip``: its one training draw (from ``seed`` and the
        clip's token), or with ``every`` each item evaluation asks (every question of the
        frame for QA); empty when the task does not apply."""
        if every and task in self.every_item:
            return self.every_item[task](clip, self.tasks)
        parts = self.task_builders[task](clip, self.tasks, clip_rng(seed, clip.anchor["token"]))
        return [parts] if parts is not None else []

    def rollouts(
        self, task: str, clips: list[Clip], batch: dict, seed: int = 0, batched: bool = True,
        every: bool = False, select: Callable[[Clip, list[Part]], bool] | None = None,
    ) -> Iterator[tuple[int, list[Part], list[Part], dict[int, torch.Tensor]]]:
        """Build ``task``'s prompts for every clip (``task_items``, with the engine's prompt
        settings; ``select`` keeps some) and roll their answers out: (sample index, parts,
        generated parts, scene codes) per prompt. The prompts generate together (one
        batched forward per step); ``batched=False`` rolls them out one after the other (the
        reference)."""
        built = [
            [parts for parts in self.task_items(task, c, seed, every) if select is None or select(c, parts)] for c in clips
        ]
        needed = [{p.frame for ps in items for p in ps if isinstance(p, Scene) and not p.supervise} for items in built]
        codes = self.scene_codes(batch, needed)
        todo = [(b, parts, {f: codes[(b, f)] for f in needed[b]}) for b, items in enumerate(built) for parts in items]
        if not batched:
            for b, parts, context in todo:
                yield (b, parts, *self.rollout(parts, context))
            return
        prompts = [self.prompt_and_plan(parts, context) for _, parts, context in todo]
        outputs = self.world.generate_batch(*map(list, zip(*prompts))) if todo else []
        for (b, parts, context), out in zip(todo, outputs):
            yield (b, parts, *self._as_parts(out, context))

    def _as_parts(self, out: list, codes: dict[int, torch.Tensor]) -> tuple[list[Part], dict[int, torch.Tensor]]:
        """Decoded answers -> generated parts, and the scene codes with the generated scenes added."""
        codes = dict(codes)
        next_frame = max(codes) + 1 if codes else 0
        generated: list[Part] = []
        for value in out:
            if isinstance(value, list):
                generated.append(Text(self.vocab.decode_text(value), True))
            elif value.dtype.is_floating_point:
                generated.append(Actions(tuple(map(tuple, value.tolist())), True))
            else:
                codes[next_frame] = value
                generated.append(Scene(next_frame, True))
                next_frame += 1
        return generated, codes

    def chain_of_thought(self, clips: list[Clip], batch: dict) -> list[CotOutput | None]:
        """Narration, meta action and trajectory generated for each clip (OccLLaMA's CoT
        planning), built with the prompt settings the model was trained with; None for a
        clip the task does not apply to (no known future or no narration)."""
        outputs: list[CotOutput | None] = [None] * len(clips)
        for b, _, (text, traj), _ in self.rollouts("cot_planning", clips, batch):
            outputs[b] = CotOutput(text.text, np.asarray(traj.xy))
        return outputs

    # -- what a planning head reads from a trained world model
    def reference_meta_action(self, clip: Clip) -> dict | None:
        """The clip's meta action as the family's tasks define it: OccVLA's labelled from the
        poses with the task settings' rules (the answer its ``meta_action`` task trains on),
        else the frame sidecar's."""
        if "meta_action" in self.task_builders:
            items = self.task_items("meta_action", clip)
            return parse_meta_action(items[0][-1].text) if items else None
        return clip.anchor.get("meta_action")

    def generated_meta_actions(self, clips: list[Clip]) -> list[tuple[dict | None, np.ndarray | None] | None]:
        """Per clip, the meta action parsed from the model's chain of thought (None when it
        cannot be parsed) and the trajectory it generated after it (None for a model that
        generates none); None for a clip the chain of thought does not apply to."""
        if "meta_action" in self.task_builders:
            out: list = [None] * len(clips)
            for b, _, generated, _ in self.rollouts("meta_action", clips, {"ann": [c.ann for c in clips]}):
                out[b] = (parse_meta_action(generated[0].text), None)
            return out
        cot = self.chain_of_thought(clips, {"ann": [c.ann for c in clips]})
        return [None if o is None else (parse_meta_action(o.text), o.waypoints) for o in cot]

    @torch.no_grad()
    def visual_summary(self, clips: list[Clip]) -> torch.Tensor:
        """(B, hidden): the world model's last-layer outputs at each anchor's image tokens,
        averaged (what OccVLA's planning head reads of the scene)."""
        seqs = [self.encode_parts([Images(c.anchor["token"])], {}) for c in clips]
        batch = move_batch(collate(seqs, self.vocab.pad_id), self.world.codebook.device)
        hidden = self.world(batch, output_hidden_states=True).hidden.float()
        images = self.vocab.is_image(batch["input_ids"]).float()[..., None]
        return (hidden * images).sum(1) / images.sum(1).clamp(min=1)

    def default_tasks(self, kind: str) -> WorldModelEngine:
        """Give the engine's task settings the family's default tasks for stage ``kind``
        ("pretrain" or "instruct") when they name none; returns self."""
        if not self.tasks.weights:
            self.tasks.weights = dict(self._default_tasks.get(kind, {}))
        return self

    def with_settings(self, tasks: TaskConfig | None = None, max_new_text_tokens: int | None = None) -> WorldModelEngine:
        """A stage's own task settings and generation length in place of the saved ones; returns self."""
        if tasks is not None:
            self.tasks = tasks
        if max_new_text_tokens is not None:
            self.max_new_text_tokens = int(max_new_text_tokens)
        return self

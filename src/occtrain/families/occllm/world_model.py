"""Occ-LLM's world model (Sec. III-B): an LLM over patch tokens of the MS-VAE's latents.

A scene is ``N = (h/p)(w/p)`` tokens ``<patch_0> ... <patch_{N-1}>`` (the joint
vocabulary's patches layout), wrapped in ``<occ>`` ... ``</occ>`` when frame separation is
on. A patch token's id says which patch it is; its input embedding adds what the patch
holds: each cell's code vector from every codebook (motion and static with the MS-VAE),
gated per channel by the ego action when pre-fusion is on, flattened and projected to the
LLM's width. The action fused into a scene is the last waypoint of the action block right
before it (the ego's position at that frame, in the anchor's ego frame, in Occ-LLM's
tasks); in a forecast that is the waypoint the model generated for that step.

The LLM emits a patch through a head on a hidden state: per cell and codebook, a code
(``PatchHead``). With "next_scene" prediction the hidden states are those of a query
block (as OccLLaMA's, one pass per scene); with "next_token" the output before a patch
token emits it, patch after patch. The loss is one cross-entropy averaged over every target:
text, action and marker tokens through the LM head, and each cell's code in each codebook.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.core.builder import SequenceBuilder, batch_payload, sample_means
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs, WorldModelOutput, token_ce
from occtrain.core.sequence import IGNORE, PayloadSpec, TokenSequence
from occtrain.core.vocab import JointVocab
from occtrain.families.occllm.config import OccLLMWorldConfig
from occtrain.families.occllm.scene_tokens import PatchEmbedding, PatchHead, PreFusion
from occtrain.models.patches import patchify, unpatchify

#: The pre-fusion action: one waypoint (x, y).
ACTION_DIM = 2


def last_waypoint(vocab: JointVocab, recent: torch.Tensor) -> torch.Tensor | None:
    """Float[2]: the last waypoint of the action block that ``recent`` ids end with, if they
    end with one (``... x y </act>``): what is fused into the scene that follows."""
    if recent.numel() < 3 or int(recent[-1]) != vocab.act_close_id or not bool(vocab.is_action(recent[-3:-1]).all()):
        return None
    return vocab.actions_from_ids(recent[-3:-1].cpu()).reshape(2)


class PatchSequenceBuilder(SequenceBuilder):
    """Lays scenes out as patch tokens with their cells and fused action as payload."""

    def __init__(self, world: OccLLMWorldModel):
        super().__init__(world.vocab, world.scene_prediction, world.payload_spec)
        self.world = world
        self._fusion: torch.Tensor | None = None  # the waypoint that ended the last part, if it was actions

    def add(self, ids, supervise, seg=0, query_target=None, payload=None) -> None:
        super().add(ids, supervise, seg, query_target, payload)
        self._fusion = None

    def actions(
        self, xy: torch.Tensor, supervise: bool = False, base: tuple[tuple[float, float], ...] | None = None
    ) -> PatchSequenceBuilder:
        super().actions(xy, supervise, base)
        # What was written (the offset from ``base`` when given), read back from its bins:
        # generation fuses what it reads back from the bins it wrote.
        written = torch.as_tensor(xy, dtype=torch.float32).reshape(-1, 2)
        if base is not None:
            written = written - torch.as_tensor(base, dtype=torch.float32).reshape(-1, 2)
        self._fusion = self.vocab.actions_from_ids(self.vocab.action_ids(written))[-1]
        return self

    def branch(self) -> PatchSequenceBuilder:
        super().branch()
        self._fusion = None
        return self

    def scene(self, codes: torch.Tensor, supervise: bool = False) -> PatchSequenceBuilder:
        v, world = self.vocab, self.world
        cells = world.cells_of(torch.as_tensor(codes).reshape(-1).long().cpu())
        n = v.scene_len
        fusion = self._fusion if self._fusion is not None else torch.zeros(ACTION_DIM)
        slots = {
            "cells": cells,
            "fusion": fusion.expand(n, ACTION_DIM).clone(),
            "target": torch.full_like(cells, IGNORE),
        }
        slot_ids = torch.arange(v.occ_start, v.occ_start + n)
        if world.frame_separation:
            self.add(torch.tensor([v.occ_open_id]), supervise)
        if self.next_scene:
            block = self.next_block()
            if supervise:
                queries = {"cells": torch.zeros_like(cells), "fusion": torch.zeros(n, ACTION_DIM), "target": cells}
                self.add(v.query_ids(), False, seg=-block, payload=queries)
            self.add(slot_ids, False, seg=block, payload=slots)
        else:
            if supervise:  # the output before each patch token emits that patch
                self.last_payload()["target"][-1] = cells[0]
                slots["target"][:-1] = cells[1:]
            self.add(slot_ids, False, payload=slots)
        if world.frame_separation:
            self.add(torch.tensor([v.occ_close_id]), supervise)
        return self


class PatchScene:
    """Writes a generated scene patch by patch through the patch head (see ``CodeScene``)."""

    def __init__(self, world: OccLLMWorldModel, fusion: torch.Tensor):
        self.world = world
        self.fusion = fusion
        self.patches: list[torch.Tensor] = []

    def _write(self, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        cells = torch.stack([logits.argmax(-1) for logits in self.world.head(hidden)], -1)  # (n, p*p, codebooks)
        first = sum(len(p) for p in self.patches)
        self.patches.append(cells)
        n = cells.shape[0]
        v = self.world.vocab
        ids = torch.arange(v.occ_start + first, v.occ_start + first + n, device=hidden.device)
        payload = {
            "cells": cells,
            "fusion": self.fusion.to(hidden.device).expand(n, ACTION_DIM),
            "target": torch.full_like(cells, IGNORE),
        }
        return ids, payload

    def from_queries(self, logits: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        return self._write(hidden)

    def next_token(self, logits: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        return self._write(hidden.reshape(1, -1))

    def codes(self) -> torch.Tensor:
        return self.world.codes_of(torch.cat(self.patches))


class OccLLMWorldModel(LMWorldModel):
    """The LLM, Occ-LLM's patch embedding and head, and pre-fusion (see the module docstring).

    ``codebooks`` are the frozen scene tokenizer's (motion then static for the MS-VAE), kept
    as non-persistent buffers: the tokenizer's export owns them.
    """

    def __init__(
        self,
        llm: nn.Module,
        vocab: JointVocab,
        codebooks: list[torch.Tensor],
        scene_prediction: str,
        cfg: OccLLMWorldConfig,
        latent_hw: tuple[int, int],
    ):
        super().__init__(llm, vocab, scene_prediction)
        if vocab.patch != cfg.patch_size:
            raise ValueError(f"the vocabulary lays out {vocab.patch}-patches, the model {cfg.patch_size}")
        self.cfg = cfg
        self.latent_hw = (int(latent_hw[0]), int(latent_hw[1]))
        self.frame_separation = cfg.frame_separation
        self.num_codebooks = len(codebooks)
        for i, book in enumerate(codebooks):
            self.register_buffer(f"codebook_{i}", book.detach().float().clone(), persistent=False)
        hidden = llm.get_input_embeddings().embedding_dim
        channels = sum(int(b.shape[1]) for b in codebooks)
        p = cfg.patch_size
        self.fusion = PreFusion(ACTION_DIM, channels, cfg.fusion_hidden) if cfg.pre_fusion else None
        self.patch_embed = PatchEmbedding(channels, p, hidden)
        self.head = PatchHead(hidden, p, [int(b.shape[0]) for b in codebooks], cfg.cell_dim)
        cells = (p * p, self.num_codebooks)
        self.payload_spec: PayloadSpec = {
            "cells": (cells, torch.long, 0),
            "fusion": ((ACTION_DIM,), torch.float32, 0.0),
            "target": (cells, torch.long, IGNORE),
        }

    # -- scenes <-> patches
    def cells_of(self, codes: torch.Tensor) -> torch.Tensor:
        """A scene's codes (flat, codebook-major) -> Long[N, p*p, codebooks], patch by patch."""
        h, w = self.latent_hw
        grid = codes.reshape(1, self.num_codebooks, h, w)
        p = self.cfg.patch_size
        return patchify(grid, p).reshape(-1, p * p, self.num_codebooks)

    def codes_of(self, cells: torch.Tensor) -> torch.Tensor:
        """Inverse of ``cells_of``."""
        p = self.cfg.patch_size
        return unpatchify(cells.reshape(1, cells.shape[0], -1), p, self.latent_hw).reshape(-1)

    def builder(self) -> PatchSequenceBuilder:
        return PatchSequenceBuilder(self)

    def check_prompt(self, prefix):
        """A laid-out prompt: patch tokens need their cells, which bare ids lack."""
        if not isinstance(prefix, TokenSequence) and bool(self.vocab.is_occ(torch.as_tensor(prefix)).any()):
            raise ValueError(
                "a prompt with patch tokens needs their cells: pass the laid-out sequence (builder().build()), not "
                "bare ids"
            )
        return prefix

    def scene_writer(self, recent: torch.Tensor) -> PatchScene:
        fusion = last_waypoint(self.vocab, recent)
        return PatchScene(self, fusion if fusion is not None else torch.zeros(ACTION_DIM))

    # -- the model
    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Input embeddings: a patch token's own row (which patch) plus what it holds."""
        emb = self.llm.get_input_embeddings()(input_ids)
        slots = self.vocab.is_occ(input_ids)
        if not payload:
            if bool(slots.any()):
                raise ValueError("patch tokens need their cells: pass the laid-out sequence, not bare ids")
            return emb
        # No early return when a batch has no patch: under DDP every parameter must take
        # part in every step (zero rows give zero gradients).
        cells = payload["cells"][slots]  # (M, p*p, codebooks)
        books = [getattr(self, f"codebook_{i}") for i in range(self.num_codebooks)]
        latents = torch.cat([F.embedding(cells[..., i], book) for i, book in enumerate(books)], -1)  # (M, p*p, C)
        if self.fusion is not None:
            latents = self.fusion(latents.transpose(1, 2), payload["fusion"][slots].float()).transpose(1, 2)
        tokens = self.patch_embed(latents.flatten(1)).to(emb.dtype)
        # masked_scatter fills the patch positions in order; its backward is a masked select.
        return emb.masked_scatter(slots[..., None], tokens)

    def forward(self, batch: dict[str, torch.Tensor], output_hidden_states: bool = False) -> WorldModelOutput:
        """One cross-entropy over text/action/marker targets (LM head) and cell codes (patch head)."""
        payload = batch_payload(batch)
        out = self._run(
            batch["input_ids"], batch["attention_mask"], batch["position_ids"], hidden=True, payload=payload
        )
        logits, hidden = out.logits, out.hidden_states[-1]
        labels = batch["labels"]
        ce = token_ce(logits, labels)
        valid = labels != IGNORE
        target = payload["target"]
        emits = (target[..., 0, 0] != IGNORE) & batch["pad_mask"]
        per_patch = target.shape[2] * target.shape[3]
        # The head runs even on zero rows: under DDP every parameter takes part in every step.
        heads = self.head(hidden[emits])
        picked = target[emits]
        sums = sum(
            F.cross_entropy(h.flatten(0, 1).float(), picked[..., i].flatten(), reduction="none")
            .view(picked.shape[:2])
            .sum(1)
            for i, h in enumerate(heads)
        )
        # Summed over a patch's cells and codebooks, at the position that emits the patch.
        cell_ce = torch.zeros(labels.shape, dtype=ce.dtype, device=ce.device).masked_scatter(emits, sums)
        n_text, n_cells = valid.sum(1), emits.sum(1) * per_patch
        text_sum, cell_sum = (ce * valid).sum(1), cell_ce.sum(1)
        loss = (text_sum.sum() + cell_sum.sum()) / (n_text.sum() + n_cells.sum()).clamp(min=1)
        per_sample = sample_means(ce * valid + cell_ce, valid.long() + emits.long() * per_patch, batch)
        return WorldModelOutput(
            loss,
            text_sum.sum() / n_text.sum().clamp(min=1),
            cell_sum.sum() / n_cells.sum().clamp(min=1),
            logits,
            hidden if output_hidden_states else None,
            per_sample,
        )

    # -- export
    def export_config(self) -> dict:
        return {
            **super().export_config(),
            "code_dim": int(self.codebook_0.shape[1]),
            "latent_hw": list(self.latent_hw),
            "occllm": {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__},
        }

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: OccLLMWorldConfig | None = None) -> dict:
        """One ``<patch_j>`` token per p x p patch of the latent grid (the patches layout)."""
        cfg = world_cfg or OccLLMWorldConfig()
        return {
            "codebook_sizes": inputs.scene.codebook_sizes,
            "scene_hw": inputs.scene.latent_hw,
            "patch": cfg.patch_size,
        }

    @classmethod
    def create(cls, llm, vocab, inputs: WorldInputs, scene_prediction, world_cfg=None) -> OccLLMWorldModel:
        scene = inputs.scene
        return cls(llm, vocab, scene.codebooks, scene_prediction, world_cfg or OccLLMWorldConfig(), scene.latent_hw)

    @classmethod
    def from_export(cls, data: dict, llm, vocab, inputs: WorldInputs) -> OccLLMWorldModel:
        scene = inputs.scene
        return cls(
            llm, vocab, scene.codebooks, data["scene_prediction"], OccLLMWorldConfig(**data["occllm"]), scene.latent_hw
        )

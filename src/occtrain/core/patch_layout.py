"""The joint vocabulary's patches layout, for any family whose LLM reads a scene as patches
of its tokenizer's latent grid (Occ-LLM's; OccLLaMA's with ``patch_size``).

A scene is ``N = (h/p)(w/p)`` tokens ``<patch_0> ... <patch_{N-1}>``. A patch token's id
says only which patch it is; what the patch holds rides beside the ids as payload:
``cells``, each cell's code in every codebook, embedded through the frozen codebooks and
projected to the LLM's width (:class:`PatchEmbedding`), and ``fusion``, the last waypoint
of the action block right before the scene (the ego's position at that frame), which a
family may fuse into the latents before they are patchified (``prepare_latents``: Occ-LLM's
pre-fusion).

The LLM emits a patch through a head on a hidden state (:class:`PatchHead`): per cell and
codebook, a code. With "next_scene" prediction the hidden states are those of a query
block (one pass per scene); with "next_token" the output before a patch token emits it,
patch after patch. The loss is one cross-entropy averaged over every target: text, action
and marker tokens through the LM head, and each cell's code in each codebook.

Query blocks that carry a scene. A supervised scene's query block is the learnable
``<scene_q_j>`` tokens with zero cells, unless the world model's ``query_cells`` makes it
carry a scene from what came before (``core.ego_steps.SceneContext``, whose scenes the
patches layout tracks as raw codes: a patch id names only a position). A query that carries
a scene is embedded as a patch token is, and, with ``copy_bias``, its head adds a learned
per-codebook scalar to the logit of the code its cell carries, so an untrained model writes
its queries back and training learns where the scene differs from them. Training
(:class:`PatchSequenceBuilder`) and generation (``core.decoding``, through
``scene_query_payload`` and ``query_scene_writer``) ask the same hook with the same context.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.core.builder import SequenceBuilder, batch_payload, sample_means
from occtrain.core.ego_steps import SceneContext, query_scene
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs, WorldModelOutput, token_ce
from occtrain.core.sequence import IGNORE, PayloadSpec, TokenSequence, empty_payload
from occtrain.core.vocab import JointVocab
from occtrain.models.patches import patchify, unpatchify

#: The waypoint a scene's patches carry: (x, y).
ACTION_DIM = 2


def scene_vocab_layout(inputs: WorldInputs, patch: int) -> dict:
    """The joint vocabulary's scene part over a discrete scene encoder: its codebooks and
    latent grid, one token per cell and codebook (``patch`` 0) or per p x p patch."""
    return {"codebook_sizes": inputs.scene.codebook_sizes, "scene_hw": inputs.scene.latent_hw, "patch": patch}


class PatchEmbedding(nn.Module):
    """Latent patches (B, N, p * p * C) -> LLM input embeddings (B, N, hidden)."""

    def __init__(self, channels: int, patch: int, hidden: int):
        super().__init__()
        self.proj = nn.Sequential(nn.LayerNorm(patch * patch * channels), nn.Linear(patch * patch * channels, hidden))

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.proj(patches)


class PatchHead(nn.Module):
    """A patch token's hidden state (B, N, hidden) -> per-cell code logits of each codebook:
    a list, one (B, N, p * p, K_i) tensor per codebook.

    Factored: the hidden state becomes a ``cell_dim`` vector per cell (position-specific
    weights), and one classifier per codebook, shared by the cells, scores it. A direct
    hidden -> p*p*K layer would need 400 M weights at Occ-LLM's p = 10, K = 512 x 2.
    """

    def __init__(self, hidden: int, patch: int, codebook_sizes: list[int], cell_dim: int = 64):
        super().__init__()
        self.cells = patch * patch
        self.cell_dim = cell_dim
        self.to_cells = nn.Sequential(nn.Linear(hidden, self.cells * cell_dim), nn.GELU())
        self.norm = nn.LayerNorm(cell_dim)
        self.classify = nn.ModuleList(nn.Linear(cell_dim, k) for k in codebook_sizes)

    def forward(self, hidden: torch.Tensor) -> list[torch.Tensor]:
        cells = self.norm(self.to_cells(hidden).unflatten(-1, (self.cells, self.cell_dim)))
        return [classify(cells) for classify in self.classify]


def last_waypoint(vocab: JointVocab, recent: torch.Tensor) -> torch.Tensor | None:
    """Float[2]: the last waypoint of the action block that ``recent`` ids end with, if they
    end with one (``... x y </act>``): what the scene that follows carries as ``fusion``."""
    if recent.numel() < 3 or int(recent[-1]) != vocab.act_close_id or not bool(vocab.is_action(recent[-3:-1]).all()):
        return None
    return vocab.actions_from_ids(recent[-3:-1].cpu()).reshape(2)


class PatchSequenceBuilder(SequenceBuilder):
    """Lays scenes out as patch tokens with their cells and the waypoint before them as payload."""

    def __init__(self, world: PatchWorldModel):
        super().__init__(
            world.vocab, world.scene_prediction, world.payload_spec, world.scene_query_ids, world.forecast_target
        )
        self.world = world
        self._fusion: torch.Tensor | None = None  # the waypoint that ended the last part, if it was actions

    def add(
        self,
        ids: torch.Tensor,
        supervise: bool,
        seg: int = 0,
        query_target: torch.Tensor | None = None,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> None:
        super().add(ids, supervise, seg, query_target, payload)
        self._fusion = None

    def actions(
        self, xy: torch.Tensor, supervise: bool = False, base: tuple[tuple[float, float], ...] | None = None
    ) -> PatchSequenceBuilder:
        super().actions(xy, supervise, base)
        # The position the bins say, as generation has it: the written offset from ``base``
        # read back from its bins, plus the base. So a scene is fused with the ego's position
        # whether its waypoint was written as a position (history) or an offset (a forecast
        # under a plan prior): one input, one meaning.
        written = torch.as_tensor(xy, dtype=torch.float32).reshape(-1, 2)
        base_xy = (
            torch.zeros_like(written) if base is None else torch.as_tensor(base, dtype=torch.float32).reshape(-1, 2)
        )
        self._fusion = (self.vocab.actions_from_ids(self.vocab.action_ids(written - base_xy)) + base_xy)[-1]
        return self

    def branch(self) -> PatchSequenceBuilder:
        super().branch()
        self._fusion = None
        return self

    def scene(self, codes: torch.Tensor, supervise: bool = False) -> PatchSequenceBuilder:
        v, world = self.vocab, self.world
        codes = torch.as_tensor(codes).reshape(-1).long().cpu()
        cells = world.cells_of(codes)
        slots = world.patch_payload(cells, self._fusion if self._fusion is not None else torch.zeros(ACTION_DIM))
        slot_ids = torch.arange(v.occ_start, v.occ_start + v.scene_len)
        if world.frame_separation:
            self.add(torch.tensor([v.occ_open_id]), supervise)
        if self.next_scene:
            block = self.next_block()
            if supervise:
                context = self._track.context()
                queries = world.scene_query_payload(context)
                target = self.forecast_target(context, codes)
                queries["target"] = world.cells_of(target.codes)
                if target.movers is not None:  # (h, w) -> each patch's cells, as its codes lie
                    flat = target.movers.reshape(1, -1).expand(world.num_codebooks, -1).reshape(-1).long()
                    queries["mover"] = world.cells_of(flat)[..., 0].bool()
                self.add(self.scene_queries(context), False, seg=-block, payload=queries)
            self.add(slot_ids, False, seg=block, payload=slots)
        else:
            if supervise:  # the output before each patch token emits that patch
                self.last_payload()["target"][-1] = cells[0]
                slots["target"][:-1] = cells[1:]
            self.add(slot_ids, False, payload=slots)
        if world.frame_separation:
            self.add(torch.tensor([v.occ_close_id]), supervise)
        self._track.scene(codes, predicted=supervise)
        return self


class PatchScene:
    """Writes a generated scene patch by patch through the patch head (see ``CodeScene``);
    ``queries``: the payload of the query block it is written from (what the copy path reads)."""

    def __init__(self, world: PatchWorldModel, fusion: torch.Tensor, queries: dict[str, torch.Tensor] | None = None):
        self.world = world
        self.fusion = fusion
        self.queries = queries
        self.patches: list[torch.Tensor] = []

    def _write(
        self, hidden: torch.Tensor, queries: dict[str, torch.Tensor] | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        logits = self.world.patch_logits(hidden, queries)
        cells = torch.stack([scores.argmax(-1) for scores in logits], -1)  # (n, p*p, codebooks)
        first = sum(len(p) for p in self.patches)
        self.patches.append(cells)
        v = self.world.vocab
        ids = torch.arange(v.occ_start + first, v.occ_start + first + cells.shape[0], device=hidden.device)
        return ids, self.world.patch_payload(cells, self.fusion)

    def from_queries(
        self, logits: torch.Tensor, hidden: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        assert hidden is not None  # a model with a payload keeps its hidden states (LMWorldModel.step)
        return self._write(hidden, self.queries)

    def next_token(
        self, logits: torch.Tensor, hidden: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        assert hidden is not None
        return self._write(hidden.reshape(1, -1), None)

    def codes(self) -> torch.Tensor:
        return self.world.codes_of(torch.cat(self.patches))


class PatchWorldModel(LMWorldModel):
    """An LLM over patch tokens of a frozen tokenizer's latents (see the module docstring).

    ``codebooks`` are the tokenizer's (their sizes and widths), kept as non-persistent
    buffers: the tokenizer's export owns them. ``latent_parts``: modules a family applies to
    the latents (through ``prepare_latents``), registered before the patch parts so their
    parameters come first. ``copy_bias``: None, the queries never carry a scene; else the
    initial per-codebook bias of the copy path (and queries may carry a scene).
    ``change_weight``: the loss weight of a cell whose target differs from the code its
    query carries (1 for the rest, and everywhere when queries carry nothing).
    ``scene_queries``: what a query block carries (``core.ego_steps.SCENE_QUERIES``; a scene
    only with a copy path).
    """

    copy_bias: nn.Parameter | None

    def __init__(
        self,
        llm: nn.Module,
        vocab: JointVocab,
        codebooks: Sequence[torch.Tensor],
        scene_prediction: str,
        latent_hw: tuple[int, int],
        patch: int,
        cell_dim: int = 64,
        frame_separation: bool = True,
        copy_bias: float | None = None,
        latent_parts: dict[str, nn.Module | None] | None = None,
        change_weight: float = 1.0,
        scene_queries: str = "learned",
        mover_weight: float = 1.0,
    ):
        super().__init__(llm, vocab, scene_prediction)
        if vocab.patch != patch:
            raise ValueError(f"the vocabulary lays out {vocab.patch}-patches, the model {patch}")
        self.patch = int(patch)
        self.latent_hw = (int(latent_hw[0]), int(latent_hw[1]))
        self.frame_separation = frame_separation
        self.change_weight = float(change_weight)
        self.mover_weight = float(mover_weight)
        self.scene_queries = scene_queries
        self.num_codebooks = len(codebooks)
        self.code_dim = int(codebooks[0].shape[1])
        for i, book in enumerate(codebooks):
            self.register_buffer(f"codebook_{i}", book.detach().float().clone(), persistent=False)
        for name, module in (latent_parts or {}).items():
            setattr(self, name, module)
        hidden = self.hidden_size
        channels = sum(int(b.shape[1]) for b in codebooks)
        self.patch_embed = PatchEmbedding(channels, self.patch, hidden)
        self.head = PatchHead(hidden, self.patch, [int(b.shape[0]) for b in codebooks], cell_dim)
        books = self.num_codebooks
        self.copy_bias = None if copy_bias is None else nn.Parameter(torch.full((books,), float(copy_bias)))
        cells = (self.patch * self.patch, books)
        self.payload_spec: PayloadSpec = {
            "cells": (cells, torch.long, 0),
            "fusion": ((ACTION_DIM,), torch.float32, 0.0),
            "target": (cells, torch.long, IGNORE),
        }
        if copy_bias is not None:  # True at a query that carries a scene
            self.payload_spec["carries"] = ((), torch.bool, False)
            # True at a query's cell where an agent moved (``core.forecast_targets.mover_cells``).
            self.payload_spec["mover"] = ((self.patch * self.patch,), torch.bool, False)

    # -- scenes <-> patches
    def cells_of(self, codes: torch.Tensor) -> torch.Tensor:
        """A scene's codes (flat, codebook-major) -> Long[N, p*p, codebooks], patch by patch."""
        h, w = self.latent_hw
        grid = codes.reshape(1, self.num_codebooks, h, w)
        return patchify(grid, self.patch).reshape(-1, self.patch * self.patch, self.num_codebooks)

    def codes_of(self, cells: torch.Tensor) -> torch.Tensor:
        """Inverse of ``cells_of``."""
        return unpatchify(cells.reshape(1, cells.shape[0], -1), self.patch, self.latent_hw).reshape(-1)

    def patch_payload(self, cells: torch.Tensor, fusion: torch.Tensor) -> dict[str, torch.Tensor]:
        """The payload of a scene's patch tokens: their ``cells`` and the waypoint before them."""
        n = cells.shape[0]
        payload = empty_payload(self.payload_spec, n, cells.device)
        payload["cells"] = cells
        payload["fusion"] = fusion.to(cells.device, torch.float32).expand(n, ACTION_DIM).clone()
        return payload

    # -- query blocks
    def query_cells(self, context: SceneContext) -> torch.Tensor | None:
        """The cells Long[N, p*p, codebooks] a predicted scene's query block carries, given
        what came before it (its scenes are raw codes here, moved through
        ``SceneMover.codes``): the scene ``scene_queries`` names, or None, the learned queries."""
        move = None if self.scene_mover is None else self.scene_mover.codes
        scene = query_scene(self.scene_queries, context, move)
        return None if scene is None else self.cells_of(scene)

    def scene_query_payload(self, context: SceneContext) -> dict[str, torch.Tensor]:
        """The query block's payload: zero cells (the learned queries), or the scene
        ``query_cells`` gives, marked as carried."""
        cells = self.query_cells(context)
        payload = empty_payload(self.payload_spec, self.vocab.scene_len, None if cells is None else cells.device)
        if cells is not None:
            if "carries" not in payload:
                raise ValueError(f"{type(self).__name__}: a query block carries a scene only with a copy_bias")
            payload["cells"] = cells.long()
            payload["carries"][:] = True
        return payload

    def tracked_scene(self, ids: torch.Tensor, payload: dict[str, torch.Tensor]) -> torch.Tensor:
        """A scene's raw codes (what a patch id cannot say), from its patches' cells."""
        return self.codes_of(payload["cells"])

    def raw_codes(self, tracked: torch.Tensor) -> torch.Tensor:
        """The patches layout tracks scenes as their raw codes already."""
        return tracked.detach().reshape(-1).long().cpu()

    def builder(self) -> PatchSequenceBuilder:
        return PatchSequenceBuilder(self)

    def check_prompt(self, prefix: torch.Tensor | TokenSequence) -> torch.Tensor | TokenSequence:
        """A laid-out prompt: patch tokens need their cells, which bare ids lack."""
        if not isinstance(prefix, TokenSequence) and bool(self.vocab.is_occ(torch.as_tensor(prefix)).any()):
            raise ValueError(
                "a prompt with patch tokens needs their cells: pass the laid-out sequence (builder().build()), not "
                "bare ids"
            )
        return prefix

    def scene_writer(self, recent: torch.Tensor, waypoint: torch.Tensor | None = None) -> PatchScene:
        """A scene right after an action block carries its last waypoint as ``fusion``: the
        position, as laid out in training (``PatchSequenceBuilder.actions``), not the offset
        from a plan prior its bins hold; zeros after anything else."""
        read = last_waypoint(self.vocab, recent)
        fusion = None if read is None else (read if waypoint is None else waypoint.reshape(2).float())
        return PatchScene(self, fusion if fusion is not None else torch.zeros(ACTION_DIM))

    def query_scene_writer(
        self, recent: torch.Tensor, queries: dict[str, torch.Tensor] | None, waypoint: torch.Tensor | None = None
    ) -> PatchScene:
        writer = self.scene_writer(recent, waypoint)
        writer.queries = queries
        return writer

    # -- the model
    def prepare_latents(
        self, latents: torch.Tensor, payload: dict[str, torch.Tensor], slots: torch.Tensor
    ) -> torch.Tensor:
        """What a family does to the latents (M, p*p, C) of the tokens at ``slots`` before
        they are patchified (Occ-LLM: pre-fusion of the waypoint they carry): nothing here."""
        return latents

    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Input embeddings: a patch token's (and a query's that carries a scene) from what it holds."""
        emb = self.llm.get_input_embeddings()(input_ids)
        slots = self.vocab.is_occ(input_ids)
        if not payload:
            if bool(slots.any()):
                raise ValueError("patch tokens need their cells: pass the laid-out sequence, not bare ids")
            return emb
        if "carries" in payload:
            slots = slots | payload["carries"].bool()
        # No early return when a batch has no patch: under DDP every parameter must take
        # part in every step (zero rows give zero gradients).
        cells = payload["cells"][slots]  # (M, p*p, codebooks)
        books = [getattr(self, f"codebook_{i}") for i in range(self.num_codebooks)]
        latents = torch.cat([F.embedding(cells[..., i], book) for i, book in enumerate(books)], -1)  # (M, p*p, C)
        latents = self.prepare_latents(latents, payload, slots)
        tokens = self.patch_embed(latents.flatten(1)).to(emb.dtype)
        # masked_scatter fills the patch positions in order; its backward is a masked select.
        return emb.masked_scatter(slots[..., None], tokens)

    def patch_logits(self, hidden: torch.Tensor, queries: dict[str, torch.Tensor] | None = None) -> list[torch.Tensor]:
        """The head's per-cell code logits at ``hidden`` (M, hidden); with the copy path and
        the payload ``queries`` at the same positions, each query that carries a scene adds
        ``copy_bias`` to the logit of the code its cell holds."""
        logits = self.head(hidden)
        if self.copy_bias is None or queries is None:
            return logits
        cells = queries["cells"].to(hidden.device)
        carries = queries["carries"].to(hidden.device)
        copied = []
        # Also with no query carrying a scene: under DDP the bias takes part in every step.
        for i, scores in enumerate(logits):
            bias = (self.copy_bias[i] * carries).to(scores.dtype)[:, None, None].expand(*cells.shape[:2], 1)
            copied.append(scores.scatter_add(-1, cells[..., i : i + 1], bias))
        return copied

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
        heads = self.patch_logits(hidden[emits], {k: v[emits] for k, v in payload.items() if k in ("cells", "carries")})
        picked = target[emits]
        weight = self.cell_weights(picked, payload, emits)
        sums = sum(
            (
                (
                    F.cross_entropy(h.flatten(0, 1).float(), picked[..., i].flatten(), reduction="none")
                    * weight[..., i].flatten()
                )
                .view(picked.shape[:2])
                .sum(1)
                for i, h in enumerate(heads)
            ),
            ce.new_zeros(()),
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

    def cell_weights(self, picked: torch.Tensor, payload: dict[str, torch.Tensor], emits: torch.Tensor) -> torch.Tensor:
        """(M, p*p, codebooks) loss weights of the emitted cells ``picked``: ``mover_weight``
        where an agent moved (the query's ``mover`` cells), ``change_weight`` where a query
        carried a code the target changes (the larger where both), else 1."""
        weight = torch.ones(picked.shape, dtype=torch.float32, device=picked.device)
        if "carries" not in payload:
            return weight
        if self.change_weight != 1.0:
            carried = payload["cells"][emits]
            changed = payload["carries"][emits].bool()[:, None, None] & (carried != picked)
            weight = weight.masked_fill(changed, self.change_weight)
        if self.mover_weight != 1.0:
            movers = payload["mover"][emits].bool()[..., None].expand_as(weight)
            weight = torch.where(movers, weight.clamp(min=self.mover_weight), weight)
        return weight

    # -- export
    def export_config(self) -> dict:
        return {**super().export_config(), "code_dim": self.code_dim, "latent_hw": list(self.latent_hw)}

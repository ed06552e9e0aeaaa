"""OccLLaMA's unified world model: a causal LM over the joint vocabulary with
spatial-temporal attention and next-token-or-scene prediction (Sec. III-B, Algorithm 1).

Its scenes are laid out in the joint vocabulary's codes layout (``core.builder``): one
token per latent cell and codebook, a supervised scene predicted at once from a query
block in "next_scene" mode (Algorithm 1 at training time: there, the queries are appended
after ``<occ>``, their outputs become the scene, and the scene then replaces the queries in
the context; generation does exactly that with the KV cache). The model computes one
uniform cross-entropy over every target (``LMWorldModel.forward``).

Occupancy inputs. The input embedding of ``<occ_k>`` is ``occ_proj(codebook[k])``, a
LayerNorm + two-layer GELU MLP (LLaVA-style projector) of the frozen scene tokenizer's
codebook vector, instead of the embedding-table row; the lm-head keeps one row per code.

Scene queries (``model.occllama.scene_queries``). The paper's query block is learnable
``<scene_q_j>`` tokens; ``last_scene`` makes it the code tokens of the scene before it,
so predicting an unchanged cell is copying its own input; ``moved_last_scene`` moves that
scene by the ego's step first (shifted and re-encoded by the frozen tokenizer), so the
ego's own motion needs no learning either; ``moved_observed_scene`` moves the last
observed scene (the present) by the ego's whole move since it, so every forecast scene's
queries are one encoding away from what was observed, however far the forecast runs.

Patches (``model.occllama.patch_size``, not the paper's). A scene may instead be read as
one token per p x p patch of the latent grid (``core.patch_layout``: 25 tokens for a 25 x
25 latent at p = 5, where the codes layout takes 625), the patch's cells riding beside its
id: :class:`OccLLaMAPatchWorldModel`, with the same query modes. A query block that holds a
scene carries its cells (the scene before, or the present, moved as above through the
frozen tokenizer), and the patch head's copy path (``copy_bias``) starts the model off
writing that scene back.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.core.decoding import CodeScene
from occtrain.core.ego_steps import SceneContext, query_scene
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs
from occtrain.core.patch_layout import PatchWorldModel, scene_vocab_layout
from occtrain.core.vocab import JointVocab
from occtrain.families.occllama.config import OccLLaMAWorldConfig

if TYPE_CHECKING:
    from transformers import PreTrainedModel


class OccLLaMAWorldModel(LMWorldModel):
    """The LLM, the joint vocabulary and the occupancy input projection.

    ``codebook`` Float[K, code_dim] is the frozen scene tokenizer's codebook (its codebooks
    stacked, in the vocabulary's order, when it has several); it is a non-persistent buffer
    (the tokenizer's export owns it), the projection is trained.
    """

    codebook: torch.Tensor

    def __init__(
        self,
        llm: PreTrainedModel,
        vocab: JointVocab,
        codebook: torch.Tensor,
        scene_prediction: str = "next_scene",
        cfg: OccLLaMAWorldConfig | None = None,
    ):
        super().__init__(llm, vocab, scene_prediction)
        self.cfg = cfg or OccLLaMAWorldConfig()
        self.scene_queries = self.cfg.scene_queries
        if codebook.shape[0] != vocab.num_codes:
            raise ValueError(f"codebook has {codebook.shape[0]} codes, the vocabulary {vocab.num_codes}")
        self.register_buffer("codebook", codebook.detach().float().clone(), persistent=False)
        hidden = llm.get_input_embeddings().embedding_dim
        dim = codebook.shape[1]
        self.occ_proj = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden))

    def scene_query_ids(self, context: SceneContext) -> torch.Tensor:
        """The query block of ``scene_queries``' kind (see the module docstring): the
        learnable queries, or a scene before this one, moved by the ego as it says; the
        learnable queries when there is no such scene, a scene unmoved when no waypoint
        came before this one."""
        scene = query_scene(self.scene_queries, context, self.scene_mover)
        return super().scene_query_ids(context) if scene is None else scene

    def scene_writer(self, recent: torch.Tensor, waypoint: torch.Tensor | None = None) -> CodeScene:
        """What writes the next generated scene; ``recent`` are the last ids before it."""
        return CodeScene(self.vocab)

    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Input embeddings; occupancy tokens through the codebook projection (the codebooks
        stacked in the vocabulary's order, so a token's offset is its row)."""
        emb = self.llm.get_input_embeddings()(input_ids)
        table = self.occ_proj(self.codebook).to(emb.dtype)
        codes = (input_ids - self.vocab.occ_start).clamp(0, self.vocab.num_codes - 1)
        # F.embedding, not table[codes]: indexing's backward accumulates rows with
        # index_put_, whose order across CPU threads varies run to run, so a resumed run
        # would drift from an uninterrupted one in the last bits.
        return torch.where(self.vocab.is_occ(input_ids)[..., None], F.embedding(codes, table), emb)

    # -- export
    def export_config(self) -> dict:
        return {**super().export_config(), "code_dim": int(self.codebook.shape[1]), "occllama": asdict(self.cfg)}

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: OccLLaMAWorldConfig | None = None) -> dict:
        """One token per latent cell and codebook (the codes layout), or with ``patch_size``
        one per p x p patch of the latent grid (the patches layout)."""
        return scene_vocab_layout(inputs, (world_cfg or OccLLaMAWorldConfig()).patch_size)

    @classmethod
    def create(
        cls,
        llm: nn.Module,
        vocab: JointVocab,
        inputs: WorldInputs,
        scene_prediction: str,
        world_cfg: OccLLaMAWorldConfig | None = None,
    ) -> LMWorldModel:
        """The codes layout's model, or with ``patch_size`` the patches layout's."""
        cfg = world_cfg or OccLLaMAWorldConfig()
        if cfg.patch_size:
            return OccLLaMAPatchWorldModel(
                llm, vocab, inputs.scene.codebooks, scene_prediction, cfg, inputs.scene.latent_hw
            )
        return cls(llm, vocab, torch.cat(inputs.scene.codebooks), scene_prediction, cfg)

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs) -> LMWorldModel:
        # Exports written before a setting existed used its default (the paper's queries, codes).
        return cls.create(llm, vocab, inputs, data["scene_prediction"], OccLLaMAWorldConfig(**data.get("occllama", {})))

    def scene_token_rows(self) -> torch.Tensor:
        """The scene tokens' input embeddings: their rows of an exported LLM's table, so
        plain transformers reads them too."""
        return self.occ_proj(self.codebook)


class OccLLaMAPatchWorldModel(PatchWorldModel):
    """OccLLaMA over the patches layout (``patch_size`` > 0; see the module docstring): the
    patch embedding and head of ``core.patch_layout`` with OccLLaMA's query modes and the
    copy path. ``OccLLaMAWorldModel.create`` and ``from_export`` build it."""

    def __init__(
        self,
        llm: nn.Module,
        vocab: JointVocab,
        codebooks: list[torch.Tensor],
        scene_prediction: str,
        cfg: OccLLaMAWorldConfig,
        latent_hw: tuple[int, int],
    ):
        super().__init__(
            llm,
            vocab,
            codebooks,
            scene_prediction,
            latent_hw,
            cfg.patch_size,
            cfg.cell_dim,
            copy_bias=cfg.copy_bias,
            change_weight=cfg.change_weight,
            scene_queries=cfg.scene_queries,
            mover_weight=cfg.mover_weight,
        )
        self.cfg = cfg

    def export_config(self) -> dict:
        return {**super().export_config(), "occllama": asdict(self.cfg)}

"""Occ-LLM's world model (Sec. III-B): an LLM over patch tokens of the MS-VAE's latents.

A scene is ``N = (h/p)(w/p)`` tokens ``<patch_0> ... <patch_{N-1}>`` in the joint
vocabulary's patches layout (``core.patch_layout``: the patch embedding, the patch head,
the patch loss and how patches are laid out and generated), wrapped in ``<occ>`` ...
``</occ>`` when frame separation is on. What Occ-LLM adds: a patch token's latents (each
cell's code vector from every codebook, motion and static with the MS-VAE) are gated per
channel by the ego action before they are patchified, when pre-fusion is on. The action
fused into a scene is the last waypoint of the action block right before it (the ego's
position at that frame, in the anchor's ego frame, in Occ-LLM's tasks, also where a plan
prior writes the forecast's waypoints as offsets: the prior is added back); in a forecast
that is the waypoint the model generated for that step. Its query blocks are the paper's
learnable queries, or (``scene_queries``, not the paper's) a scene they carry, the present
moved by the ego as OccLLaMA's can (``core.ego_steps.query_scene``), with the copy path.
"""

from __future__ import annotations

import torch
from torch import nn

from occtrain.core.lm_world_model import WorldInputs
from occtrain.core.patch_layout import ACTION_DIM, PatchWorldModel, scene_vocab_layout
from occtrain.core.vocab import JointVocab
from occtrain.families.occllm.config import OccLLMWorldConfig
from occtrain.families.occllm.scene_tokens import PreFusion


class OccLLMWorldModel(PatchWorldModel):
    """The patches layout with Occ-LLM's settings and pre-fusion (see the module docstring).

    ``codebooks`` are the frozen scene tokenizer's (motion then static for the MS-VAE), kept
    as non-persistent buffers: the tokenizer's export owns them.
    """

    fusion: PreFusion | None

    def __init__(
        self,
        llm: nn.Module,
        vocab: JointVocab,
        codebooks: list[torch.Tensor],
        scene_prediction: str,
        cfg: OccLLMWorldConfig,
        latent_hw: tuple[int, int],
    ):
        channels = sum(int(b.shape[1]) for b in codebooks)
        # Made and registered before the patch parts, as before they moved to core: a seed
        # gives the same initial weights, and the parameters keep their order (a checkpoint's
        # optimizer state lists them by position).
        fusion = PreFusion(ACTION_DIM, channels, cfg.fusion_hidden) if cfg.pre_fusion else None
        super().__init__(
            llm,
            vocab,
            codebooks,
            scene_prediction,
            latent_hw,
            cfg.patch_size,
            cfg.cell_dim,
            cfg.frame_separation,
            # Learned queries carry nothing to copy: no copy path (and an export as before it).
            copy_bias=None if cfg.scene_queries == "learned" else cfg.copy_bias,
            latent_parts={"fusion": fusion},
            change_weight=cfg.change_weight,
            scene_queries=cfg.scene_queries,
            mover_weight=cfg.mover_weight,
        )
        self.cfg = cfg

    def prepare_latents(
        self, latents: torch.Tensor, payload: dict[str, torch.Tensor], slots: torch.Tensor
    ) -> torch.Tensor:
        """Pre-fusion (Table V): the waypoint a patch carries gates its latents' channels."""
        if self.fusion is None:
            return latents
        return self.fusion(latents.transpose(1, 2), payload["fusion"][slots].float()).transpose(1, 2)

    # -- export
    def export_config(self) -> dict:
        return {**super().export_config(), "occllm": {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__}}

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: OccLLMWorldConfig | None = None) -> dict:
        """One ``<patch_j>`` token per p x p patch of the latent grid (the patches layout)."""
        return scene_vocab_layout(inputs, (world_cfg or OccLLMWorldConfig()).patch_size)

    @classmethod
    def create(
        cls,
        llm: nn.Module,
        vocab: JointVocab,
        inputs: WorldInputs,
        scene_prediction: str,
        world_cfg: OccLLMWorldConfig | None = None,
    ) -> OccLLMWorldModel:
        scene = inputs.scene
        return cls(llm, vocab, scene.codebooks, scene_prediction, world_cfg or OccLLMWorldConfig(), scene.latent_hw)

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs) -> OccLLMWorldModel:
        scene = inputs.scene
        return cls(
            llm, vocab, scene.codebooks, data["scene_prediction"], OccLLMWorldConfig(**data["occllm"]), scene.latent_hw
        )

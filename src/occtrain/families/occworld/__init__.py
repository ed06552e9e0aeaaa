"""OccWorld (the baseline scene tokenizer of the papers): its 2D VQ-VAE over the BEV plane,
registered as the ``occworld_vqvae`` tokenizer architecture. The model itself is a shared
block (``models.tokenizers.occworld_vqvae``): Occ-LLM's MS-VAE and OccVLA's decoder build on it."""

from __future__ import annotations

from occtrain.core.registry import FamilySpec, TokenizerArch, register_family
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAE, OccWorldVQVAEConfig

OCCWORLD = register_family(
    FamilySpec(
        name="occworld",
        paper="OccWorld (baseline tokenizer of OccLLaMA and Occ-LLM)",
        tokenizers=(TokenizerArch("occworld_vqvae", OccWorldVQVAEConfig, OccWorldVQVAE),),
    )
)

__all__ = ["OCCWORLD", "OccWorldVQVAE", "OccWorldVQVAEConfig"]

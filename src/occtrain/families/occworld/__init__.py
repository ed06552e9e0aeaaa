"""OccWorld (the baseline scene tokenizer of the papers): its 2D VQ-VAE over the BEV plane."""

from __future__ import annotations

from occtrain.families.occworld.config import OccWorldVQVAEConfig
from occtrain.families.occworld.vqvae import OccWorldVQVAE
from occtrain.families.registry import FamilySpec, TokenizerArch, register_family

OCCWORLD = register_family(
    FamilySpec(
        name="occworld",
        paper="OccWorld (baseline tokenizer of OccLLaMA and Occ-LLM)",
        tokenizers=(TokenizerArch("occworld_vqvae", OccWorldVQVAEConfig, OccWorldVQVAE),),
    )
)

__all__ = ["OCCWORLD", "OccWorldVQVAE", "OccWorldVQVAEConfig"]

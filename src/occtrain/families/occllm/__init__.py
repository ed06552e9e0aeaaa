"""Occ-LLM (seeds/003): the Motion-Separation VAE scene tokenizer.

Its world model (patchified scene tokens, frame separation, pre-fusion of ego actions) and
tasks are not here yet: the tokenizer trains through the shared ``tokenizer`` stage kind
(``model.arch: occllm_msvae``), on any Occ3D-layout data.
"""

from __future__ import annotations

from occtrain.families.occllm.config import MOVABLE_CLASSES, MSVAEConfig
from occtrain.families.occllm.msvae import MSVAE, merge, separate
from occtrain.families.registry import FamilySpec, TokenizerArch, register_family

OCCLLM = register_family(
    FamilySpec(
        name="occllm",
        paper="Occ-LLM",
        tokenizers=(TokenizerArch("occllm_msvae", MSVAEConfig, MSVAE),),
    )
)

__all__ = ["MOVABLE_CLASSES", "MSVAE", "MSVAEConfig", "OCCLLM", "merge", "separate"]

"""Scene tokenizers: occupancy volumes <-> grids of codebook ids (OccWorld VQ-VAE, OccLLaMA)."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from occtrain.config.tokenizer import OccLLaMATokenizerConfig, OccWorldVQVAEConfig, validate_tokenizer_config
from occtrain.errors import ConfigError
from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerOutput
from occtrain.models.tokenizers.occllama import OccLLaMATokenizer
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAE
from occtrain.models.tokenizers.quantizer import QuantizerOutput, VectorQuantizer

#: arch name -> (config schema, model class)
TOKENIZERS: dict[str, tuple[type, type[SceneTokenizer]]] = {
    "occworld_vqvae": (OccWorldVQVAEConfig, OccWorldVQVAE),
    "occllama_tokenizer": (OccLLaMATokenizerConfig, OccLLaMATokenizer),
}


def build_tokenizer(arch: str, cfg: Any) -> SceneTokenizer:
    """Build tokenizer ``arch`` from its config: a dataclass, a DictConfig or a plain mapping."""
    if arch not in TOKENIZERS:
        raise ConfigError(f"model.arch: '{arch}' is not a tokenizer; use one of {', '.join(TOKENIZERS)}")
    schema, model_cls = TOKENIZERS[arch]
    if not isinstance(cfg, schema):
        node = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
        cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), node))
    validate_tokenizer_config(cfg, f"model.{arch}")
    return model_cls(cfg)


__all__ = [
    "TOKENIZERS",
    "OccLLaMATokenizer",
    "OccWorldVQVAE",
    "QuantizerOutput",
    "SceneTokenizer",
    "TokenizerOutput",
    "VectorQuantizer",
    "build_tokenizer",
]

"""One folder per paper family: its configs, model pieces, prompt and task formats, and one
registration (:class:`FamilySpec`). Blocks the families share live in ``occtrain.models``."""

from __future__ import annotations

from occtrain.families.registry import (
    FamilySpec, TokenizerArch, build_tokenizer, families, get_family, load_tokenizer, register_family, save_tokenizer,
    tokenizer_archs, tokenizer_config, tokenizer_family,
)

__all__ = [
    "FamilySpec", "TokenizerArch", "build_tokenizer", "families", "get_family", "load_tokenizer", "register_family", "save_tokenizer",
    "tokenizer_archs", "tokenizer_config", "tokenizer_family",
]

"""A scene tokenizer built from its architecture's config, written as an export and read back.

The architectures are the families' (:func:`occtrain.core.registry.tokenizer_arch` finds
one by name); what is here is the same for all of them: the config validated as its
dataclass, the export's weights and ``config.json`` (the architecture, its config and the
layout a world model's joint vocabulary is built from), and a frozen model rebuilt from it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from occtrain.core.registry import tokenizer_arch
from occtrain.errors import ConfigError
from occtrain.formats.exports import check_section, load_state_strict, read_export, require_config, write_export
from occtrain.models import count_parameters
from occtrain.models.tokenizers.base import SceneTokenizer, TokenizerModel


def tokenizer_config(arch: str, cfg: Any, where: str | None = None) -> Any:
    """``cfg`` (a dataclass, a DictConfig or a mapping) as ``arch``'s validated config dataclass."""
    schema = tokenizer_arch(arch).config
    if not isinstance(cfg, schema):
        node = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
        cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), node))
    cfg.validate(where or f"model.{arch}")
    return cfg


def build_tokenizer(arch: str, cfg: Any) -> Any:
    """Build tokenizer ``arch`` from its config: a dataclass, a DictConfig or a plain mapping."""
    return tokenizer_arch(arch).model(tokenizer_config(arch, cfg))


def save_tokenizer(model: TokenizerModel, arch: str, cfg: dict, export_dir: Path) -> Path:
    """Write a tokenizer export: weights, ``arch`` and its config, and what a world model's
    joint vocabulary is laid out from: the codebooks (sizes, latent grid) of a discrete
    tokenizer, the token count and width of a continuous one."""
    if isinstance(model, SceneTokenizer):
        layout = {
            "num_codes": int(model.num_codes),
            "codebook_sizes": model.codebook_sizes,
            "latent_hw": list(model.latent_hw),
        }
    else:
        layout = {"discrete": False, "tokens": int(model.num_tokens), "token_dim": int(model.token_dim)}
    config = {
        "stage_kind": "tokenizer",
        "arch": arch,
        "config": cfg,
        **layout,
        "params": count_parameters(model),
        "label_convention": "occ3d",
    }
    # A training-only branch (a distillation head) is left out where the model says so.
    return write_export(export_dir, model.export_state_dict(), config)


def load_tokenizer(export_dir: Path) -> Any:
    """Rebuild a scene tokenizer from a tokenizer stage's export (frozen, eval mode)."""
    state, config = read_export(export_dir)
    if config.get("stage_kind") != "tokenizer":
        raise ConfigError(
            f"{export_dir}: not a tokenizer export (stage kind '{config.get('stage_kind')}'); consume the tokenizer "
            "stage"
        )
    require_config(config, ("arch", "config"), export_dir)
    check_section(tokenizer_arch(config["arch"]).config, config["config"], "config", export_dir)
    model = build_tokenizer(config["arch"], config["config"])
    load_state_strict(model, state, (), str(export_dir))
    model.export_dir = Path(export_dir)  # a world-model export copies it from here
    model.arch = config["arch"]
    return model.eval().requires_grad_(False)

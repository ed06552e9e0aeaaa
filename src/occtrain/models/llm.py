"""The world model's causal LM: any Hugging Face causal LM the backend drives, built tiny
from config or loaded from a local directory; its text tokenizer; the peft LoRA adapter.

A world model feeds its LLM input embeddings under a 4D attention mask (boolean for SDPA,
additive for eager) with explicit position ids, and decodes with a KV cache it crops
after a query block and re-indexes when a batch's sequences finish. The model types below
are the ones tested to do all of that; another is refused in one line naming it. A
multimodal directory (PaliGemma: SigLIP + Gemma) gives its language model here and its
vision tower to ``vision.path``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from transformers import AutoConfig, AutoModelForCausalLM, AutoTokenizer, PreTrainedModel

from occtrain.config.llm import BACKENDS, LLMConfig, LoRAConfig, validate_llm_config
from occtrain.errors import ConfigError

#: Backends transformers runs without SDPA: they attend eagerly (additive masks).
EAGER_ONLY = ("gemma2",)
#: Multimodal model types whose language model a world model can take (its vision tower
#: loads through ``vision.path``).
MULTIMODAL = ("paligemma",)


#: Hugging Face config keys of a tiny model and the ``LLMConfig`` keys that size them.
SIZE_KEYS = (
    ("hidden_size", "hidden_size"), ("intermediate_size", "intermediate_size"), ("num_hidden_layers", "num_layers"),
    ("num_attention_heads", "num_heads"), ("max_position_embeddings", "max_position_embeddings"),
)


def attention_for(model_type: str, requested: str) -> str:
    """The attention implementation to build ``model_type`` with (eager where SDPA is not offered)."""
    return "eager" if model_type in EAGER_ONLY else requested


def _tiny_config(cfg: LLMConfig, vocab_size: int) -> Any:
    """The config of a tiny ``cfg.model_type`` LM from the size keys."""
    kw: dict[str, Any] = {hf: getattr(cfg, ours) for hf, ours in SIZE_KEYS}
    kw.update(
        vocab_size=vocab_size, num_key_value_heads=cfg.num_heads, tie_word_embeddings=False,
        attn_implementation=attention_for(cfg.model_type, cfg.attn_implementation),
    )
    if cfg.model_type == "gemma2":  # its defaults size heads for 2B models: give it the tiny model's
        head = cfg.hidden_size // cfg.num_heads
        kw.update(head_dim=head, query_pre_attn_scalar=head)
    return AutoConfig.for_model(cfg.model_type, **kw)


def check_backend(model_type: str, where: str) -> None:
    """One line when ``model_type`` is not a causal LM the world model can drive."""
    if model_type not in BACKENDS:
        raise ConfigError(
            f"{where}: model type '{model_type}' is not an LLM backend occtrain drives ({', '.join(BACKENDS)}): "
            "a world model needs 4D attention masks, position ids and a KV cache it can crop and re-index"
        )


def build_llm(cfg: LLMConfig, vocab_size: int) -> PreTrainedModel:
    """The causal LM with its embeddings and lm-head sized to ``vocab_size`` (the joint vocabulary).

    ``cfg.path`` empty: a tiny ``cfg.model_type`` LM from the size keys, randomly initialised
    under the current torch seed. Otherwise the model in that local directory (no
    download); the rows of the new tokens start at the mean of the old ones (transformers'
    default).
    """
    validate_llm_config(cfg)
    if not cfg.path:
        check_backend(cfg.model_type, "llm.model_type")
        return AutoModelForCausalLM.from_config(_tiny_config(cfg, vocab_size))
    model = load_llm(cfg.path, cfg.attn_implementation)
    model.resize_token_embeddings(vocab_size)
    return model


def load_llm(path: str | Path, attn_implementation: str = "sdpa") -> PreTrainedModel:
    """A causal LM from a local Hugging Face directory: a backend's own, or the language
    model of a multimodal one (see ``MULTIMODAL``)."""
    _check_dir(path)
    try:
        config = AutoConfig.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(f"llm.path: cannot load the model config in {path} ({_first_line(e)}); point it at a Hugging Face model directory") from None
    if config.model_type in MULTIMODAL:
        return _language_model(path, config, attn_implementation)
    check_backend(config.model_type, f"llm.path {path}")
    try:
        return AutoModelForCausalLM.from_pretrained(
            str(path), local_files_only=True, attn_implementation=attention_for(config.model_type, attn_implementation),
        )
    except (OSError, ValueError) as e:
        raise ConfigError(f"llm.path: cannot load a causal LM from {path} ({_first_line(e)}); point it at a Hugging Face model directory") from None


def _language_model(path: str | Path, config: Any, attn_implementation: str) -> PreTrainedModel:
    """The language model of a multimodal directory as a causal LM of its text type."""
    from transformers import AutoModelForImageTextToText

    text = config.get_text_config()
    check_backend(text.model_type, f"llm.path {path} (its language model)")
    text._attn_implementation = attention_for(text.model_type, attn_implementation)
    try:
        full = AutoModelForImageTextToText.from_pretrained(str(path), local_files_only=True, dtype=torch.float32)
    except (OSError, ValueError) as e:
        raise ConfigError(f"llm.path: cannot load the {config.model_type} model in {path} ({_first_line(e)})") from None
    lm = AutoModelForCausalLM.from_config(text)
    state = {f"model.{k}": v for k, v in full.get_decoder().state_dict().items()}
    state.update({f"lm_head.{k}": v for k, v in full.get_output_embeddings().state_dict().items()})
    missing, unexpected = lm.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ConfigError(f"llm.path: the language model of {path} does not match its config (key '{(missing or unexpected)[0]}')")
    return lm


def load_text_tokenizer(path: str | Path) -> Any:
    """The tokenizer saved beside a local LLM (``llm.path``); padding falls back to eos."""
    _check_dir(path)
    try:
        tok = AutoTokenizer.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError) as e:
        raise ConfigError(f"llm.path: cannot load a tokenizer from {path} ({_first_line(e)}); the directory needs its tokenizer files") from None
    if tok.eos_token_id is None:
        raise ConfigError(f"llm.path: the tokenizer in {path} has no eos token; the world model needs one to end text")
    if tok.pad_token_id is None:
        tok.pad_token = tok.eos_token
    return tok


def apply_lora(model: PreTrainedModel, cfg: LoRAConfig) -> Any:
    """Wrap ``model`` in a peft LoRA adapter (``PeftModel``); only the adapter trains."""
    from peft import LoraConfig, get_peft_model

    lora = LoraConfig(
        r=cfg.r,
        lora_alpha=cfg.alpha,
        lora_dropout=cfg.dropout,
        target_modules=list(cfg.target_modules),
        task_type="CAUSAL_LM",
    )
    try:
        return get_peft_model(model, lora)
    except ValueError as e:
        raise ConfigError(f"lora.target_modules: {list(cfg.target_modules)} ({_first_line(e)})") from None


def _check_dir(path: str | Path) -> None:
    if not (Path(path) / "config.json").is_file():
        raise ConfigError(f"llm.path: {path} is not a local Hugging Face model directory (no config.json); fix the path or leave it empty for the tiny Llama")


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__

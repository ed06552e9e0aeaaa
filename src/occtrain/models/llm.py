"""The world model's causal LM: a tiny Llama built from config, or a local Hugging Face
model directory; its text tokenizer; and the peft LoRA adapter."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from transformers import AutoModelForCausalLM, AutoTokenizer, LlamaConfig, LlamaForCausalLM, PreTrainedModel

from occtrain.config.llm import LLMConfig, LoRAConfig, validate_llm_config
from occtrain.errors import ConfigError


def build_llm(cfg: LLMConfig, vocab_size: int) -> PreTrainedModel:
    """The causal LM with its embeddings and lm-head sized to ``vocab_size`` (the joint vocabulary).

    ``cfg.path`` empty: a tiny Llama from the size keys, randomly initialised under the
    current torch seed. Otherwise the model in that local directory (no download); the
    rows of the new tokens start at the mean of the old ones (transformers' default).
    """
    validate_llm_config(cfg)
    if not cfg.path:
        config = LlamaConfig(
            vocab_size=vocab_size,
            hidden_size=cfg.hidden_size,
            intermediate_size=cfg.intermediate_size,
            num_hidden_layers=cfg.num_layers,
            num_attention_heads=cfg.num_heads,
            num_key_value_heads=cfg.num_heads,
            max_position_embeddings=cfg.max_position_embeddings,
            tie_word_embeddings=False,
            attn_implementation=cfg.attn_implementation,
        )
        return LlamaForCausalLM(config)
    _check_dir(cfg.path)
    try:
        model = AutoModelForCausalLM.from_pretrained(cfg.path, local_files_only=True, attn_implementation=cfg.attn_implementation)
    except (OSError, ValueError) as e:
        raise ConfigError(f"llm.path: cannot load a causal LM from {cfg.path} ({_first_line(e)}); point it at a Hugging Face model directory") from None
    model.resize_token_embeddings(vocab_size)
    return model


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

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
from torch import nn
from transformers import AutoConfig, AutoModelForCausalLM, AutoTokenizer, PreTrainedModel

from occtrain.config.llm import BACKENDS, LLMConfig, LoRAConfig, validate_llm_config
from occtrain.errors import ConfigError, cause_line
from occtrain.models import without_peft

#: Backends transformers runs without SDPA: they attend eagerly (additive masks).
EAGER_ONLY = ("gemma2",)
#: Multimodal model types whose language model a world model can take (its vision tower
#: loads through ``vision.path``).
MULTIMODAL = ("paligemma",)


#: Hugging Face config keys of a tiny model and the ``LLMConfig`` keys that size them.
SIZE_KEYS = (
    ("hidden_size", "hidden_size"),
    ("intermediate_size", "intermediate_size"),
    ("num_hidden_layers", "num_layers"),
    ("num_attention_heads", "num_heads"),
    ("max_position_embeddings", "max_position_embeddings"),
)


def attention_for(model_type: str, requested: str) -> str:
    """The attention implementation to build ``model_type`` with (eager where SDPA is not offered)."""
    return "eager" if model_type in EAGER_ONLY else requested


def tiny_config(cfg: LLMConfig, vocab_size: int) -> Any:
    """The config of a tiny ``cfg.model_type`` LM from the size keys."""
    kw: dict[str, Any] = {hf: getattr(cfg, ours) for hf, ours in SIZE_KEYS}
    kw.update(
        vocab_size=vocab_size,
        num_key_value_heads=cfg.num_heads,
        tie_word_embeddings=False,
        attn_implementation=attention_for(cfg.model_type, cfg.attn_implementation),
    )
    if cfg.model_type == "gemma2":  # its defaults size heads for 2B models: give it the tiny model's
        head = cfg.hidden_size // cfg.num_heads
        kw.update(head_dim=head, query_pre_attn_scalar=head)
    return AutoConfig.for_model(cfg.model_type, **kw)


def check_llm(cfg: LLMConfig, key: str) -> None:
    """What :func:`build_llm` would refuse, found without building it: occtrain's own
    checks, then the backend config's validators (transformers checks the architecture
    when its config is made), so ``occtrain validate`` refuses what ``run`` would."""
    validate_llm_config(cfg, key)
    if cfg.path:  # loaded from its directory at build time, where its config.json is checked
        return
    try:
        tiny_config(cfg, cfg.text_vocab_size)
    except Exception as err:  # noqa: BLE001 - any validator's refusal is the user's config
        raise ConfigError(f"{key}: the {cfg.model_type} config is refused ({cause_line(err)})") from None


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
        return AutoModelForCausalLM.from_config(tiny_config(cfg, vocab_size))
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
        raise ConfigError(
            f"llm.path: cannot load the model config in {path} ({_first_line(e)}); point it at a Hugging Face model "
            "directory"
        ) from None
    if config.model_type in MULTIMODAL:
        return _language_model(path, config, attn_implementation)
    check_backend(config.model_type, f"llm.path {path}")
    return load_pretrained_strict(
        AutoModelForCausalLM,
        path,
        "llm.path",
        "point llm.path at a Hugging Face model directory whose weights match its config",
        attn_implementation=attention_for(config.model_type, attn_implementation),
    )


def load_pretrained_strict(
    auto: Any,
    path: str | Path,
    what: str,
    hint: str,
    allow_unexpected: bool = False,
    **kwargs: Any,
) -> PreTrainedModel:
    """``auto.from_pretrained(path)`` that refuses, in one line naming the tensor, weights
    that disagree with the directory's config: a layer the weights lack would otherwise
    start random, and transformers only reports it. ``allow_unexpected``: the directory
    may hold more than the model (a full image-text model read for its vision tower)."""
    from transformers.utils import logging as hf_logging

    pickled = sorted(p.name for p in Path(path).glob("*.bin"))
    if pickled and not any(Path(path).glob("*.safetensors")):
        raise ConfigError(
            f"{what}: {path} holds its weights as {pickled[0]}, a pickle, which occtrain never loads (unpickling "
            "runs whatever the file says); convert them to safetensors where you trust the file (transformers' "
            "save_pretrained writes them), or use a release that ships model.safetensors"
        )
    verbosity = hf_logging.get_verbosity()
    hf_logging.set_verbosity_error()  # its load report is replaced by the check below
    hf_logging.disable_progress_bar()  # a bar per load says nothing in a run's log
    try:
        model, info = auto.from_pretrained(
            str(path), local_files_only=True, output_loading_info=True, use_safetensors=True, **kwargs
        )
    except Exception as e:  # safetensors, OSError, ValueError, RuntimeError (shapes): a broken directory either way
        raise ConfigError(
            f"{what}: cannot load the model in {path} ({type(e).__name__}: {_first_line(e)}); {hint}"
        ) from None
    finally:
        hf_logging.set_verbosity(verbosity)
        hf_logging.enable_progress_bar()
    for kind in ("missing", "mismatched", "unexpected"):
        if kind == "unexpected" and allow_unexpected:
            continue
        keys = sorted(str(k[0] if isinstance(k, tuple) else k) for k in info.get(f"{kind}_keys") or [])
        if keys:
            raise ConfigError(
                f"{what}: the weights in {path} do not match its config.json ({kind} tensor '{keys[0]}'"
                f"{f' and {len(keys) - 1} more' if len(keys) > 1 else ''}); {hint}"
            )
    return model


def _language_model(path: str | Path, config: Any, attn_implementation: str) -> PreTrainedModel:
    """The language model of a multimodal directory as a causal LM of its text type."""
    from transformers import AutoModelForImageTextToText

    text = config.get_text_config()
    check_backend(text.model_type, f"llm.path {path} (its language model)")
    text._attn_implementation = attention_for(text.model_type, attn_implementation)
    full = load_pretrained_strict(
        AutoModelForImageTextToText,
        path,
        "llm.path",
        f"point llm.path at a {config.model_type} directory whose weights match its config",
        dtype=torch.float32,
    )
    lm = AutoModelForCausalLM.from_config(text)
    state = {f"model.{k}": v for k, v in full.get_decoder().state_dict().items()}
    state.update({f"lm_head.{k}": v for k, v in full.get_output_embeddings().state_dict().items()})
    missing, unexpected = lm.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ConfigError(
            f"llm.path: the language model of {path} does not match its config (tensor '{(missing or unexpected)[0]}')"
        )
    return lm


def checkpoint_layers(model: nn.Module) -> None:
    """Recompute each transformer layer's activations in backward instead of keeping them
    (Hugging Face's gradient checkpointing, non-reentrant: frozen inputs, LoRA and adapter
    hooks need nothing extra). Only training forwards recompute; generation is unchanged."""
    base = without_peft(model)
    if not getattr(base, "supports_gradient_checkpointing", False):
        raise ConfigError(f"gradient_checkpointing: {type(base).__name__} does not support it")
    base.activation_checkpointing_enable(activation_checkpointing_kwargs={"use_reentrant": False})


def load_text_tokenizer(path: str | Path) -> Any:
    """The tokenizer saved beside a local LLM (``llm.path``); padding falls back to eos."""
    _check_dir(path)
    try:
        tok = AutoTokenizer.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError) as e:
        raise ConfigError(
            f"llm.path: cannot load a tokenizer from {path} ({_first_line(e)}); the directory needs its tokenizer files"
        ) from None
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


def load_lora_strict(
    model: PreTrainedModel, adapter_dir: str | Path, hint: str = "re-run the stage that wrote it"
) -> Any:
    """``PeftModel.from_pretrained`` (frozen) that refuses, naming the tensor, an adapter whose
    weights do not fit the model: peft would start the missing ones at their init and drop
    the unexpected ones with at most a warning."""
    from peft import PeftModel, get_peft_model_state_dict
    from safetensors import safe_open

    adapter_dir = Path(adapter_dir)
    try:
        with safe_open(str(adapter_dir / "adapter_model.safetensors"), "pt") as fh:
            saved = set(fh.keys())
        wrapped = PeftModel.from_pretrained(model, str(adapter_dir), is_trainable=False)
    except Exception as e:  # a damaged file, a config that does not fit, a shape mismatch
        raise ConfigError(
            f"{adapter_dir}: cannot load the LoRA adapter ({type(e).__name__}: {_first_line(e)}); {hint}"
        ) from None
    # peft's own state dict also names base layers it saves only when they changed (an
    # embedding or head it wraps): only its LoRA matrices must all be in the file.
    wanted = set(get_peft_model_state_dict(wrapped))
    missing = sorted(k for k in wanted - saved if ".lora_" in k)
    unexpected = sorted(saved - wanted)
    if missing or unexpected:
        odd, what = (missing[0], "missing") if missing else (unexpected[0], "unexpected")
        raise ConfigError(f"{adapter_dir}: adapter weights do not match the model ({what} tensor '{odd}'); {hint}")
    return wrapped


def _check_dir(path: str | Path) -> None:
    if not (Path(path) / "config.json").is_file():
        raise ConfigError(
            f"llm.path: {path} is not a local Hugging Face model directory (no config.json); fix the path or leave it "
            "empty for the tiny Llama"
        )


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__

"""Structured configs of the world model's language model: the LLM, the joint vocabulary's
action bins and the scene-prediction mode, and the LoRA adapter."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

SCENE_PREDICTION_MODES = ("next_scene", "next_token")
#: Hugging Face causal-LM model types a world model runs on (``models.llm``): the seeds'
#: Vicuna/LLaMA, PaliGemma2's Gemma2 and InternVL2's Qwen2 families.
BACKENDS = ("llama", "qwen2", "gemma2")
#: Text tokens a generated answer may take before it is cut off, unless a stage says otherwise.
MAX_NEW_TEXT_TOKENS = 96


@dataclass
class LLMConfig:
    """The causal LM behind the world model.

    With ``path`` empty a tiny ``model_type`` LM is built from the size keys below (no
    download) and the text tokenizer is a byte-level BPE trained on the dataset's text;
    with ``path`` set the model and its tokenizer load from that local Hugging Face
    directory (a backend's, or a multimodal PaliGemma's language model) and the size keys
    are ignored.
    """

    #: A local Hugging Face model directory (config.json, weights, tokenizer); empty = a tiny model.
    path: str = ""
    #: The tiny model's architecture (``BACKENDS``): llama, qwen2 or gemma2.
    model_type: str = "llama"
    hidden_size: int = 128
    num_layers: int = 2
    num_heads: int = 4
    intermediate_size: int = 344
    max_position_embeddings: int = 4096
    #: Size of the BPE vocabulary trained on the dataset's text (tiny Llama only).
    text_vocab_size: int = 2048
    #: Attention kernel; both "sdpa" and "eager" honour the spatial-temporal 4D mask (a
    #: backend without SDPA in transformers, Gemma2, runs eager).
    attn_implementation: str = "sdpa"
    #: "next_scene": a scene's tokens come from the query tokens in one pass (OccLLaMA
    #: Algorithm 1, bidirectional inside a scene); "next_token": token by token, causal
    #: everywhere (the paper's "w/o spatial attention" ablation).
    scene_prediction: str = "next_scene"
    #: Waypoint quantisation: bins per axis (paper: 256) over [low, high] metres per axis.
    action_bins: int = 256
    #: [[x_low, x_high], [y_low, y_high]] in metres, ego frame (x forward, y left). The
    #: default covers the whole 80 m Occ3D grid (detections, ego past) and the ego's 3 s
    #: future at the synthetic world's top speed (13.5 m/s -> 40.5 m): bins of 0.39 m in
    #: x and 0.31 m in y.
    action_range: list[list[float]] = field(default_factory=lambda: [[-40.0, 60.0], [-40.0, 40.0]])
    #: What an action block's bins hold. "absolute" (the papers): each waypoint's position.
    #: "delta": each waypoint's move from the one before it (the first's from the ego), the
    #: same tokens as the moves between history scenes, so keeping the last move is copying
    #: a token; quantized with error feedback, so the block's positions stay within half a
    #: bin. A one-waypoint block is the same either way.
    action_encoding: str = "absolute"
    #: How a generated bin is chosen. "greedy" (the papers): the likeliest bin. "expected":
    #: the bin holding the expected value of the bins' centres under the model's
    #: distribution, which a spread-out distribution over neighbouring bins rewards.
    action_decoding: str = "greedy"


#: ``action_encoding`` and ``action_decoding`` values, the papers' first.
ACTION_ENCODINGS = ("absolute", "delta")
ACTION_DECODINGS = ("greedy", "expected")


@dataclass
class LoRAConfig:
    """A peft LoRA adapter over the LLM's attention projections."""

    r: int = 16
    alpha: int = 32
    dropout: float = 0.05
    target_modules: list[str] = field(default_factory=lambda: ["q_proj", "v_proj"])


#: The keys that size a tiny LLM; a model at ``path`` takes its sizes from its config.json instead.
TINY_SIZE_KEYS = (
    "hidden_size",
    "num_layers",
    "num_heads",
    "intermediate_size",
    "max_position_embeddings",
    "text_vocab_size",
)


def check_llm_sizes(sizes: dict[str, Any], where: str, hidden: str, heads: str, kv_heads: str = "") -> None:
    """One line when ``sizes`` cannot shape a decoder: each a positive integer, ``heads``
    dividing ``hidden`` and ``kv_heads`` dividing ``heads`` (where both are given).

    ``sizes`` holds the values under the names the user wrote (``LLMConfig``'s or a
    config.json's); ``where`` goes before each name in the message (``stages.pretrain.model.llm.``
    or ``<dir>/config.json: ``), so the line points at what to edit.
    """
    from occtrain.errors import ConfigError

    for name, value in sizes.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(
                f"{where}{name} is {value!r}; it sizes the model's tensors, so it must be a positive integer"
            )
    for part, whole in ((heads, hidden), (kv_heads, heads)):
        if part in sizes and whole in sizes and sizes[whole] % sizes[part]:
            n, total = sizes[part], sizes[whole]
            raise ConfigError(
                f"{where}{part} is {n}, which does not divide {whole} {total}; "
                f"set {part} to a divisor of {total} (e.g. {_near_divisor(total, n)}) or {whole} to a multiple of {n}"
            )


def _near_divisor(total: int, n: int) -> int:
    """A divisor of ``total`` close to ``n`` (the search is capped: sizes may be absurd)."""
    n = min(n, total)
    for step in range(min(n, 100_000)):
        for d in (n + step, n - step):
            if 1 <= d <= total and total % d == 0:
                return d
    return 1


def validate_llm_config(cfg: LLMConfig, key: str = "llm") -> None:
    """One line naming the key when a value of ``cfg`` cannot work."""
    from occtrain.errors import ConfigError

    if not cfg.path and cfg.model_type not in BACKENDS:
        raise ConfigError(
            f"{key}.model_type: '{cfg.model_type}' is not an LLM backend occtrain drives; use one of "
            f"{', '.join(BACKENDS)}"
        )
    if not cfg.path:  # with a path the sizes come from its config.json (checked where it is read)
        check_llm_sizes({k: getattr(cfg, k) for k in TINY_SIZE_KEYS}, f"{key}.", "hidden_size", "num_heads")
    if cfg.scene_prediction not in SCENE_PREDICTION_MODES:
        raise ConfigError(
            f"{key}.scene_prediction: '{cfg.scene_prediction}' is not one of {', '.join(SCENE_PREDICTION_MODES)}"
        )
    if cfg.action_bins < 2:
        raise ConfigError(
            f"{key}.action_bins: {cfg.action_bins} bins cannot encode a waypoint; use at least 2 (paper: 256)"
        )
    rng = [list(r) for r in cfg.action_range]
    if len(rng) != 2 or any(len(r) != 2 or not r[0] < r[1] for r in rng):
        raise ConfigError(f"{key}.action_range: {rng} must be [[x_low, x_high], [y_low, y_high]] with low < high")
    for name, allowed in (("action_encoding", ACTION_ENCODINGS), ("action_decoding", ACTION_DECODINGS)):
        if getattr(cfg, name) not in allowed:
            raise ConfigError(
                f"{key}.{name}: '{getattr(cfg, name)}' is not one of {', '.join(allowed)} (paper: {allowed[0]})"
            )
    if cfg.attn_implementation not in ("sdpa", "eager"):
        raise ConfigError(
            f"{key}.attn_implementation: '{cfg.attn_implementation}' does not take the 4D spatial-temporal mask; use "
            "sdpa or eager"
        )

"""How much GPU memory each LLM stage of a recipe needs per rank, before anything is
downloaded or trained (``occtrain plan-memory``).

The stage's language model is built on the ``meta`` device from its config alone (a tiny
one from the size keys, or the ``config.json`` of ``llm.path``, which needs no weights),
with the stage's LoRA or bottleneck adapters applied, so parameter and trainable counts
are exact. Memory per rank is then counted term by term:

- weights: every parameter, in the precision's parameter dtype (fp32 under ``*-mixed``);
- gradients and AdamW's two moments: the trainable parameters only;
- DDP's gradient buckets: a second copy of the gradients (Lightning's DDP keeps
  ``gradient_as_bucket_view`` off); under ``*-mixed``, autocast's 16-bit copy of the weights;
- sharded over N ranks (FSDP): weights, gradients and moments divided by N, plus two
  decoder layers gathered whole (the one computing and the one prefetched), in 16-bit
  under ``*-mixed`` (FSDP2's MixedPrecisionPolicy);
- activations, per sample and token: what a Llama-style decoder layer keeps for backward
  under fused (SDPA) attention, ``8 h + 2 kv + 4 i`` elements (each RMSNorm's input,
  normalised input and output, q/k/v, the attention output, the MLP's four i-wide
  tensors), or only the layer's input
  ``h`` with activation checkpointing plus one layer recomputed; eager attention adds
  ``2 heads x seq`` per token (scores and probabilities); the logits add ``V`` elements in
  the activation dtype, their float log-softmax ``V`` floats, and under 16-bit
  activations the float copy the loss makes first another ``V``.

It leaves out the CUDA context, allocator fragmentation and kernels' workspaces: a plan
fits when its total is under 90 % of the GPU's memory. The "Scale" page (docs/scale.md) checks it
against what this machine measures.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from occtrain.config.llm import TINY_SIZE_KEYS, check_llm_sizes, validate_llm_config
from occtrain.errors import ConfigError, cause_line
from occtrain.formats.io import parse_json

GIB = 1024**3
#: Precision -> (parameter bytes, activation bytes); gradients and moments take the parameter's.
PRECISIONS = {
    "32-true": (4, 4),
    "32": (4, 4),
    "bf16-mixed": (4, 2),
    "16-mixed": (4, 2),
    "bf16-true": (2, 2),
    "16-true": (2, 2),
}
#: Headroom for what the plan leaves out (CUDA context, fragmentation, workspaces).
USABLE_FRACTION = 0.9
#: Stage kinds whose model is a world model over an LLM.
LLM_STAGE_KINDS = ("pretrain", "instruct", "distill")
#: Longest --seq-len planned: 4 M tokens, past any context the papers' models train at; a
#: larger number is a typo, and its activations overflow any table.
MAX_SEQ_LEN = 2**22
#: Largest --gpu-memory (GiB) taken as meant: past any accelerator made (an H200 holds 141).
MAX_GPU_GIB = 10_000
#: A Hugging Face text config's sizes (``num_key_value_heads``: grouped-query attention, optional).
HF_SIZE_KEYS = (
    "hidden_size",
    "num_hidden_layers",
    "num_attention_heads",
    "intermediate_size",
    "vocab_size",
    "num_key_value_heads",
)
#: ``LLMConfig`` keys a model at ``llm.path`` ignores: its config.json decides them.
PATH_SHADOWS = (*TINY_SIZE_KEYS, "model_type")


@dataclass
class ModelCount:
    """A stage's language model, counted on the meta device."""

    name: str
    params: int
    trainable: int
    #: Frozen parameters beside the LLM held in memory (a consumed vision stage's tower, a
    #: distillation teacher).
    frozen_beside: int
    layers: int
    hidden: int
    kv_hidden: int
    intermediate: int
    heads: int
    vocab: int
    #: Parameters of one decoder layer (FSDP gathers one at a time).
    layer_params: int
    attention: str


@dataclass
class MemoryRow:
    """Bytes per rank of one strategy, term by term."""

    strategy: str
    weights: float
    gradients: float
    optimizer: float
    extra: float
    activations: float

    @property
    def total(self) -> float:
        return self.weights + self.gradients + self.optimizer + self.extra + self.activations

    def fits(self, gpu_gib: float) -> bool:
        return self.total <= USABLE_FRACTION * gpu_gib * GIB


def check_flags(gpus: int, seq: int, gpu_gib: float | None) -> None:
    """One line naming the flag when a plan-memory option cannot describe a machine."""
    if gpus < 1:
        raise ConfigError(f"--gpus {gpus}: plan at least 1 GPU (the ranks a sharded model is split over)")
    if not 1 <= seq <= MAX_SEQ_LEN:
        raise ConfigError(f"--seq-len {seq}: tokens per training sequence must be in 1..{MAX_SEQ_LEN} (2**22)")
    # ``not 0 < x`` also refuses NaN, which argparse's float() accepts.
    if gpu_gib is not None and not 0 < gpu_gib <= MAX_GPU_GIB:
        raise ConfigError(
            f"--gpu-memory {gpu_gib:g}: a GPU's memory in GiB must be above 0 and at most {MAX_GPU_GIB} (an H100 has "
            "80)"
        )


def _read_config(path: str, key: str) -> Any:
    from huggingface_hub.errors import StrictDataclassError
    from transformers import AutoConfig

    if not (Path(path) / "config.json").is_file():
        raise ConfigError(
            f"{key}: {path} has no config.json; plan-memory reads a model's config.json (weights not needed)"
        )
    try:
        return AutoConfig.from_pretrained(path, local_files_only=True)
    except (
        OSError,
        ValueError,
        KeyError,
        StrictDataclassError,
    ) as e:  # transformers' own checks of the values raise the last
        raise ConfigError(
            f"{key}: cannot read the model config in {path} ({cause_line(e)}); fix its config.json"
        ) from None


def _check_config_sizes(path: str) -> None:
    """Refuse sizes in ``path``'s config.json that cannot shape a decoder, naming the file and
    key: transformers builds a negative one into a tensor (a traceback) and words its own
    refusals without either."""
    file = Path(path) / "config.json"
    try:
        raw = parse_json(file.read_text())
    except (OSError, ValueError):
        return  # unreadable: AutoConfig's refusal names the directory
    if not isinstance(raw, dict):
        return
    nested = isinstance(raw.get("text_config"), dict)  # a multimodal model's language model
    text = raw["text_config"] if nested else raw
    sizes = {k: text[k] for k in HF_SIZE_KEYS if k in text}
    if text.get("head_dim") is not None:
        sizes["head_dim"] = text["head_dim"]
    # An explicit head_dim sizes q/k/v as heads x head_dim: hidden_size need not divide then.
    hidden = "" if "head_dim" in sizes else "hidden_size"
    check_llm_sizes(
        sizes, f"{file}: {'text_config.' if nested else ''}", hidden, "num_attention_heads", "num_key_value_heads"
    )


def _on_meta(config: Any, auto: Any) -> nn.Module:
    with torch.device("meta"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation notes from transformers say nothing about memory
        return auto.from_config(config)


def count_llm(
    llm_cfg: Any,
    extra_vocab: int,
    lora: Any = None,
    adapter: Any = None,
    vocab: int | None = None,
    freeze: tuple[str, ...] = (),
    key: str = "llm",
) -> ModelCount:
    """Build ``llm_cfg``'s LM on the meta device (vocabulary grown by ``extra_vocab`` rows,
    or ``vocab`` rows for a tiny LM sharing another's vocabulary), apply the LoRA or
    adapter config and the stage's ``freeze`` prefixes (world-model names: ``llm.``), and
    count it. ``key``: where ``llm_cfg`` sits in the recipe, for messages."""
    from transformers import AutoModelForCausalLM

    from occtrain.models import without_peft
    from occtrain.models.adapters import add_adapters
    from occtrain.models.llm import apply_lora, tiny_config

    validate_llm_config(llm_cfg, key)  # the checks ``run`` makes before it builds the model
    if llm_cfg.path:
        _check_config_sizes(llm_cfg.path)
        # The language model alone, as ``models.llm.load_llm`` keeps it from a multimodal directory.
        text = _read_config(llm_cfg.path, f"{key}.path").get_text_config()
        text.vocab_size += extra_vocab
        name = Path(llm_cfg.path).name
    else:
        text = tiny_config(llm_cfg, vocab or llm_cfg.text_vocab_size + extra_vocab)
        name = f"tiny {llm_cfg.model_type}"
    model = _on_meta(text, AutoModelForCausalLM)
    if lora is not None:
        model.requires_grad_(False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = apply_lora(model, lora)
    elif adapter is not None:
        model.requires_grad_(False)
        add_adapters(model, adapter)
    for pname, p in model.named_parameters():
        if any(f"llm.{pname}".startswith(prefix) for prefix in freeze):
            p.requires_grad_(False)
    params = sum(p.numel() for p in model.parameters())
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    layer = without_peft(model).get_decoder().layers[0]
    heads = text.num_attention_heads
    head_dim = getattr(text, "head_dim", None) or text.hidden_size // heads
    return ModelCount(
        name=name,
        params=params,
        trainable=trainable,
        frozen_beside=0,
        layers=text.num_hidden_layers,
        hidden=text.hidden_size,
        kv_hidden=(getattr(text, "num_key_value_heads", None) or heads) * head_dim,
        intermediate=text.intermediate_size,
        heads=heads,
        vocab=text.vocab_size,
        layer_params=sum(p.numel() for p in layer.parameters()),
        attention=getattr(text, "_attn_implementation", None) or "sdpa",
    )


def count_vision(vision_cfg: Any) -> int:
    """Parameters of a vision stage's tower (frozen inside the world models that consume it)."""
    from transformers import AutoModel

    from occtrain.models.camera_encoder import build_vision_tower

    if not vision_cfg.path:
        with torch.device("meta"):
            tower = build_vision_tower(vision_cfg)
    else:
        config = _read_config(vision_cfg.path, "vision.path")
        tower = _on_meta(getattr(config, "vision_config", None) or config, AutoModel)
    return sum(p.numel() for p in tower.parameters())


def activation_bytes(m: ModelCount, batch: int, seq: int, act: int, checkpointing: bool) -> float:
    """What the forward keeps for backward, per rank (see the module docstring)."""
    per_layer = 8 * m.hidden + 2 * m.kv_hidden + 4 * m.intermediate
    if m.attention == "eager":
        per_layer += 2 * m.heads * seq
    kept = (m.layers * m.hidden + per_layer) if checkpointing else m.layers * per_layer
    # The logits stay alive in the model's output; the loss keeps their float log-softmax,
    # and under 16-bit activations also makes a transient float copy of them first.
    logits = m.vocab * act + 4 * m.vocab + (4 * m.vocab if act < 4 else 0)
    return batch * seq * (kept * act + logits)


def plan(m: ModelCount, precision: str, batch: int, seq: int, gpus: int, checkpointing: bool) -> list[MemoryRow]:
    """DDP and sharded-over-``gpus`` memory per rank of one training step."""
    if precision not in PRECISIONS:
        raise ConfigError(f"trainer.precision: '{precision}' is not one plan-memory knows ({', '.join(PRECISIONS)})")
    pb, act = PRECISIONS[precision]
    mixed = precision.endswith("-mixed")
    weights = (m.params + m.frozen_beside) * pb
    grads = m.trainable * pb
    moments = 2 * m.trainable * pb
    acts = activation_bytes(m, batch, seq, act, checkpointing)
    autocast = m.params * 2 if mixed else 0
    ddp = MemoryRow("DDP", weights, grads, moments, grads + autocast, acts)
    gathered = 2 * m.layer_params * (2 if mixed else pb)
    sharded = MemoryRow(f"sharded x{gpus}", weights / gpus, grads / gpus, moments / gpus, gathered, acts)
    return [ddp, sharded]


@dataclass
class StagePlan:
    """One stage's count and its memory rows."""

    stage: str
    kind: str
    count: ModelCount
    batch: int
    precision: str
    rows: list[MemoryRow]


def _pretrain_of(name: str, planned: dict[str, Any]) -> Any:
    """The pretrain stage whose LLM ``name`` trains on (following ``consumes``)."""
    stage = planned[name]
    while stage.spec.kind != "pretrain":
        parents = [planned[c] for c in stage.spec.consumes if planned[c].spec.kind in LLM_STAGE_KINDS]
        if not parents:
            raise ConfigError(f"stage '{name}' consumes no pretrain stage; plan-memory cannot tell its LLM")
        stage = parents[0]
    return stage


def _extra_vocab(stage: Any, planned: dict[str, Any]) -> int:
    """Rows the joint vocabulary adds to the text vocabulary: the consumed tokenizer's codes
    and the action bins of both axes (the few marker tokens are left out)."""
    codes = 0
    for dep in stage.spec.consumes:
        tok = planned[dep]
        if tok.spec.kind == "tokenizer":
            model = tok.model_cfg
            section = getattr(model, str(getattr(model, "arch", "")), None)
            codes += int(getattr(section, "num_codes", 0) or 0)
    return codes + 2 * int(stage.model_cfg.llm.action_bins)


def _refuse_shadowed(llm_cfg: Any, key: str, written: list[tuple[str, str]]) -> None:
    """Refuse a command-line override of a key that ``llm.path`` makes ``run`` ignore.

    ``written``: each override's key as the user wrote it, beside its ``stages.<name>.``
    form. Refused, not noted: plan-memory's whole output is numbers, and a table for the
    model at ``llm.path`` reads as the answer for the sizes asked about (a note above it
    is easily missed); rerunning without the override costs seconds.
    """
    if not llm_cfg.path:
        return
    for as_written, normal in written:
        if normal in {f"{key}.{k}" for k in PATH_SHADOWS}:
            raise ConfigError(
                f"{as_written}: ignored, since {key}.path is set ({llm_cfg.path}) and its config.json decides the "
                "model; "
                f"drop the override to plan that model, or point {key}.path at a config.json with the sizes you want"
            )


def _override_keys(overrides: list[str], names: list[str], recipe_path: str) -> list[tuple[str, str]]:
    """Each override's key as written, and its ``stages.<name>.`` form (what messages name)."""
    from occtrain.run.planning import stage_override

    keys = []
    for item in overrides:
        normal = stage_override(item, names, recipe_path).split("=", 1)[0].strip()
        if normal.startswith("stages["):  # stages[<i>].rest -> stages.<name>.rest
            index, rest = normal[len("stages[") :].split("]", 1)
            normal = f"stages.{names[int(index)]}{rest}" if index.isdigit() and int(index) < len(names) else normal
        keys.append((item.split("=", 1)[0].strip(), normal))
    return keys


def _count_stage(p: Any, planned: dict[str, Any], written: list[tuple[str, str]]) -> ModelCount:
    """The LLM stage ``p``'s model, counted, with its LLM config checked as ``run`` checks it."""
    cfg = p.model_cfg
    pretrain = _pretrain_of(p.spec.name, planned)
    llm_key = f"stages.{pretrain.spec.name}.model.llm"
    _refuse_shadowed(pretrain.model_cfg.llm, llm_key, written)
    extra = _extra_vocab(pretrain, planned)
    if p.spec.kind == "distill":
        student_key = f"stages.{p.spec.name}.model.student"
        _refuse_shadowed(cfg.student, student_key, written)
        teacher = count_llm(pretrain.model_cfg.llm, extra, key=llm_key)
        count = count_llm(
            cfg.student, extra, vocab=teacher.vocab, key=student_key
        )  # the student speaks the teacher's vocabulary
        count.frozen_beside += teacher.params
        return count
    lora = cfg.lora if getattr(cfg, "use_lora", False) else None
    adapter = cfg.adapter if getattr(cfg, "use_adapters", False) else None
    count = count_llm(pretrain.model_cfg.llm, extra, lora, adapter, freeze=tuple(p.spec.freeze), key=llm_key)
    count.frozen_beside += sum(
        count_vision(planned[d].model_cfg.vision) for d in pretrain.spec.consumes if planned[d].spec.kind == "vision"
    )
    return count


def plan_recipe(
    recipe_path: str,
    overrides: list[str],
    gpus: int,
    seq: int,
    checkpointing: bool,
    gpu_gib: float | None = None,
) -> list[StagePlan]:
    """A plan for every LLM stage of the recipe at its batch and precision (``gpu_gib``, the
    GPU a table will be checked against, is only validated here)."""
    from occtrain.run.planning import load_recipe

    check_flags(gpus, seq, gpu_gib)
    recipe, stages = load_recipe(recipe_path, overrides)
    planned = {p.spec.name: p for p in stages}
    written = _override_keys(overrides, [s.name for s in recipe.stages], str(recipe_path))
    plans = []
    for p in stages:
        if p.spec.kind not in LLM_STAGE_KINDS:
            continue
        count = _count_stage(p, planned, written)
        batch = int(p.data.batch_size)
        precision = str(p.trainer.precision)
        plans.append(
            StagePlan(
                p.spec.name,
                p.spec.kind,
                count,
                batch,
                precision,
                plan(count, precision, batch, seq, gpus, checkpointing),
            )
        )
    if not plans:
        raise ConfigError(f"{recipe_path} has no pretrain, instruct or distill stage: plan-memory plans LLM stages")
    return plans


def _gib(n: float) -> str:
    return f"{n / GIB:.1f}" if n >= 0.05 * GIB else f"{n / GIB:.3f}"


def format_plans(plans: list[StagePlan], seq: int, gpu_gib: float | None, checkpointing: bool) -> str:
    """A table per stage, GiB per rank, and whether each strategy fits ``gpu_gib``."""
    lines = [
        f"memory per rank (GiB) of one training step at {seq} tokens per sequence, activation checkpointing "
        f"{'on' if checkpointing else 'off'}",
        "(CUDA context, fragmentation and workspaces not included; a plan fits under 90 % of the GPU)",
    ]
    for sp in plans:
        c = sp.count
        lines += [
            "",
            f"{sp.stage} ({sp.kind}): {c.name}, {c.params / 1e9:.3f} B parameters, {c.trainable / 1e6:.2f} M trainable"
            + (f", {c.frozen_beside / 1e9:.3f} B frozen beside it" if c.frozen_beside else "")
            + f", batch {sp.batch} per rank, {sp.precision}",
            f"  {'strategy':<12} {'weights':>8} {'grads':>8} {'AdamW':>8} {'extra':>8} {'activ.':>8} {'total':>8}"
            + ("  fits" if gpu_gib else ""),
        ]
        for r in sp.rows:
            fit = f"  {'yes' if r.fits(gpu_gib) else 'no'} ({gpu_gib:g} GiB)" if gpu_gib else ""
            cells = (r.weights, r.gradients, r.optimizer, r.extra, r.activations, r.total)
            lines.append(f"  {r.strategy:<12} " + " ".join(f"{_gib(v):>8}" for v in cells) + fit)
    return "\n".join(lines)


__all__ = [
    "GIB",
    "ModelCount",
    "MemoryRow",
    "StagePlan",
    "activation_bytes",
    "count_llm",
    "format_plans",
    "plan",
    "plan_recipe",
]

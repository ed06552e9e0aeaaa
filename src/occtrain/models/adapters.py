"""Bottleneck adapters at the residual connections of a causal LM's decoder layers
(Pfeiffer et al. 2020, what OccVLA fine-tunes its VLM with in stage 2).

peft has no bottleneck adapter and AdapterHub's ``adapters`` package pins transformers
4.57, which occtrain cannot use, so this is our own small module. Each decoder layer's
feed-forward output ``m`` becomes ``m + up(act(down(m)))`` before the residual add (the
Pfeiffer placement); ``up`` starts at zero, so a fresh adapter leaves the model unchanged.
The adapters hang on the MLPs as forward hooks: the LM's own parameter names stay as they
are, so its Hugging Face directory is written without them and they are saved beside it
(``adapter.safetensors`` + ``adapter_config.json``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from safetensors.torch import load_file, save_file
from torch import nn

from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_write_json, parse_json
from occtrain.models import without_peft

if TYPE_CHECKING:
    from transformers import PreTrainedModel

ADAPTER_WEIGHTS = "adapter.safetensors"
ADAPTER_CONFIG = "adapter_config.json"
#: The attribute an adapter takes on its MLP (so its weights are named ``...mlp.bottleneck_adapter.*``).
ATTRIBUTE = "bottleneck_adapter"


@dataclass
class AdapterConfig:
    """Bottleneck adapters: ``hidden / reduction_factor`` wide (Pfeiffer's default: 16)."""

    reduction_factor: int = 16
    #: The decoder-layer submodule whose output the adapter reads and adds to.
    module: str = "mlp"

    def validate(self, where: str) -> None:
        if self.reduction_factor < 1:
            raise ConfigError(f"{where}.reduction_factor: must be >= 1, got {self.reduction_factor}")


class BottleneckAdapter(nn.Module):
    """``x + up(gelu(down(LayerNorm(x))))``; ``up`` zero-initialised (identity at the start)."""

    def __init__(self, hidden: int, bottleneck: int, cfg: AdapterConfig):
        super().__init__()
        #: What it was made from, saved beside its weights.
        self.cfg = cfg
        self.norm = nn.LayerNorm(hidden)
        self.down = nn.Linear(hidden, bottleneck)
        self.up = nn.Linear(bottleneck, hidden)
        nn.init.zeros_(self.up.weight)
        nn.init.zeros_(self.up.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.up(nn.functional.gelu(self.down(self.norm(x))))

    def hook(self, module: nn.Module, inputs: tuple, output: torch.Tensor) -> torch.Tensor:
        """A forward hook: the hooked module's output through the adapter."""
        return self(output)


def _layers(llm: nn.Module) -> list[nn.Module]:
    """The decoder layers of a Hugging Face causal LM (Llama, Qwen2, Gemma2: ``get_decoder().layers``)."""
    base = without_peft(llm)
    body = base.get_decoder() if hasattr(base, "get_decoder") else getattr(base, "model", base)
    layers = getattr(body, "layers", None)
    if layers is None:
        raise ConfigError(
            f"adapters: {type(base).__name__} has no decoder layers (get_decoder().layers); adapters fit decoder-only "
            "causal LMs"
        )
    return list(layers)


def add_adapters(llm: PreTrainedModel, cfg: AdapterConfig) -> list[BottleneckAdapter]:
    """Hook a fresh adapter onto every decoder layer's ``cfg.module``; returns them (trainable)."""
    hidden = llm.get_input_embeddings().embedding_dim
    width = max(1, hidden // cfg.reduction_factor)
    adapters = []
    for i, layer in enumerate(_layers(llm)):
        target = getattr(layer, cfg.module, None)
        if target is None:
            raise ConfigError(f"adapter.module: decoder layer {i} has no submodule '{cfg.module}'")
        if hasattr(target, ATTRIBUTE):
            raise ValueError(f"decoder layer {i} already has an adapter")
        adapter = BottleneckAdapter(hidden, width, cfg).to(next(target.parameters()).device)
        target.add_module(ATTRIBUTE, adapter)
        target.register_forward_hook(adapter.hook)
        adapters.append(adapter)
    return adapters


def adapters_of(llm: nn.Module) -> list[BottleneckAdapter]:
    """The bottleneck adapters hooked onto ``llm``, layer by layer."""
    return [m for m in llm.modules() if isinstance(m, BottleneckAdapter)]


def has_adapters(llm: nn.Module) -> bool:
    return bool(adapters_of(llm))


def without_adapters(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A state dict with the adapters' weights left out (the LM's own, for its HF directory)."""
    return {k: v for k, v in state.items() if f".{ATTRIBUTE}." not in k}


def save_adapters(llm: nn.Module, out: Path) -> Path:
    """Write the adapters' weights (safetensors) and config (JSON) into ``out``."""
    cfg = next(m.cfg for m in llm.modules() if isinstance(m, BottleneckAdapter))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in llm.state_dict().items() if f".{ATTRIBUTE}." in k}
    save_file(state, str(out / ADAPTER_WEIGHTS))
    atomic_write_json(out / ADAPTER_CONFIG, {"type": "bottleneck", "placement": "pfeiffer", **asdict(cfg)})
    return out


def load_adapters(llm: PreTrainedModel, source: Path) -> AdapterConfig:
    """Hook adapters onto ``llm`` as saved in ``source`` and load their weights (strict)."""
    source = Path(source)
    try:
        data = parse_json((source / ADAPTER_CONFIG).read_text())
        state = load_file(str(source / ADAPTER_WEIGHTS))
    except Exception as err:  # OSError, JSON and safetensors' own errors: a damaged adapter either way
        raise ConfigError(
            f"{source}: unreadable bottleneck adapter ({type(err).__name__}: {str(err).splitlines()[0]}); re-run the "
            "stage that wrote it"
        ) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source / ADAPTER_CONFIG}: is not a JSON object; re-run the stage that wrote it")
    cfg = AdapterConfig(**{k: data[k] for k in AdapterConfig.__dataclass_fields__ if k in data})
    add_adapters(llm, cfg)
    own = {k: v for k, v in llm.state_dict().items() if f".{ATTRIBUTE}." in k}
    if set(own) != set(state):
        odd = sorted(set(own) ^ set(state))[0]
        raise ConfigError(
            f"{source}: adapter weights do not match the model ({'missing' if odd in own else 'unexpected'} tensor "
            f"'{odd}'); re-run the stage that wrote it"
        )
    misshapen = next((k for k in own if own[k].shape != state[k].shape), None)
    if misshapen is not None:
        raise ConfigError(
            f"{source}: adapter tensor '{misshapen}' has shape {tuple(state[misshapen].shape)}, the model wants "
            f"{tuple(own[misshapen].shape)}; re-run the stage that wrote it"
        )
    llm.load_state_dict(state, strict=False)
    return cfg

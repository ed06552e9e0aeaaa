"""``trainer.strategy: fsdp``: parameters, gradients and AdamW state sharded over every rank.

Lightning's ``ModelParallelStrategy`` as pure data parallelism (FSDP2), on CPU processes
(gloo) and GPUs alike; a stage that shards (``Stage.shards``) applies ``fully_shard`` in its
``configure_model`` (:func:`shard_world_model`) and runs generation and its export on an
unsharded copy (:class:`FullCopy`), where no forward is a collective.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from lightning.pytorch.strategies import ModelParallelStrategy

from occtrain.config.groups import TrainerConfig
from occtrain.core.lm_world_model import LMWorldModel
from occtrain.errors import ConfigError
from occtrain.stages.stage import Stage

#: ``trainer.strategy`` that shards parameters, gradients and AdamW state over every rank (FSDP2).
SHARDED = "fsdp"


class ShardedStrategy(ModelParallelStrategy):
    """``trainer.strategy: fsdp``: Lightning's ``ModelParallelStrategy`` as pure data
    parallelism over every rank of every node (FSDP2, no tensor parallelism), on CPU
    processes (gloo) and GPUs (NCCL) alike. A stage shards itself in ``configure_model``
    (see :func:`shard_world_model`).

    Checkpoints are one file with the full state dict, gathered on rank zero (``AtomicCheckpointIO``
    writes it), so ``last.ckpt``, its fallback and the weights-only load work as under DDP.
    A resume checks the checkpoint's keys as strictly as :meth:`Stage.load_state_dict` does
    (the frozen sub-models are not in it) and loads it back into the shards.
    """

    def __init__(self) -> None:
        super().__init__(data_parallel_size="auto", tensor_parallel_size=1, save_distributed_checkpoint=False)

    def setup_environment(self) -> None:
        # Every process is a data-parallel rank, whatever devices (-1: all GPUs) and num_nodes say.
        self._data_parallel_size = self.num_nodes * self.num_processes
        super().setup_environment()

    def load_checkpoint(self, checkpoint_path: Any, weights_only: bool | None = None) -> dict[str, Any]:
        module = self.lightning_module
        if not isinstance(module, Stage):
            return super().load_checkpoint(checkpoint_path, weights_only)
        module.check_checkpoint_keys(
            torch.load(checkpoint_path, map_location="cpu", weights_only=True, mmap=True)["state_dict"].keys()
        )
        strict, module.strict_loading = module.strict_loading, False  # the frozen keys are absent by design
        try:
            return super().load_checkpoint(checkpoint_path, weights_only)
        finally:
            module.strict_loading = strict


def trainer_strategy(cfg: TrainerConfig) -> Any:
    """What ``L.Trainer(strategy=...)`` gets for ``cfg.strategy``: ``fsdp`` is
    :class:`ShardedStrategy`, any other name is Lightning's own."""
    return ShardedStrategy() if cfg.strategy == SHARDED else cfg.strategy


def _decoder_layers(model: torch.nn.Module) -> list[torch.nn.Module]:
    """The outermost transformer layers of a Hugging Face model (transformers marks them
    ``GradientCheckpointingLayer``, what activation checkpointing recomputes)."""
    from transformers.modeling_layers import GradientCheckpointingLayer

    layers: dict[str, torch.nn.Module] = {}
    for name, module in model.named_modules():
        if isinstance(module, GradientCheckpointingLayer) and not any(name.startswith(f"{outer}.") for outer in layers):
            layers[name] = module
    return list(layers.values())


def shard_world_model(world: LMWorldModel, mesh: Any) -> None:
    """FSDP2 over ``mesh``: each decoder layer of ``world.llm`` (under a peft wrapper too) is
    one unit gathered for its forward and backward, and ``world`` itself the root unit that
    holds the rest (embeddings, lm-head, final norm, the family's own parts). Frozen and
    trainable parameters (LoRA, adapters) shard alike."""
    from torch.distributed.fsdp import fully_shard

    from occtrain.models import without_peft

    layers = _decoder_layers(without_peft(world.llm))
    if not layers:
        raise ConfigError(
            f"trainer.strategy={SHARDED}: found no decoder layers in {type(without_peft(world.llm)).__name__} to shard"
        )
    for layer in layers:
        fully_shard(layer, mesh=mesh)
    fully_shard(world, mesh=mesh)


def is_sharded(module: torch.nn.Module) -> bool:
    """Whether ``module`` was sharded by FSDP2 already (``configure_model`` runs again for ``validate``)."""
    from torch.distributed.fsdp import FSDPModule

    return isinstance(module, FSDPModule)


def local_numel(module: torch.nn.Module) -> int:
    """Parameters this rank holds of ``module``: its shards' sizes under FSDP2."""
    from torch.distributed.tensor import DTensor

    return sum(p.to_local().numel() if isinstance(p, DTensor) else p.numel() for p in module.parameters())


class FullCopy:
    """An unsharded twin of a module about to be sharded, for what runs outside FSDP's
    forward-and-backward: generation (each rank its own prompts, no collectives),
    validation and the export. Its parameters stay on the ``meta`` device (no memory)
    until :meth:`gather` fills them with the full weights; :meth:`release` empties them.

    Built before ``fully_shard`` by a deep copy whose parameters are mapped to ``meta``
    ones: buffers (small: rotary frequencies, ...) are copied, tied weights stay tied, and
    a model held by reference in a plain attribute (a frozen decoder) stays shared.
    """

    def __init__(self, module: torch.nn.Module):
        import copy

        memo: dict[int, Any] = {
            id(p): torch.nn.Parameter(torch.empty_like(p, device="meta"), p.requires_grad) for p in module.parameters()
        }
        for sub in module.modules():
            memo.update((id(v), v) for v in vars(sub).values() if isinstance(v, torch.nn.Module))
        self.module = copy.deepcopy(module, memo)
        self.loaded = False

    def _replace(self, make: Callable[[torch.nn.Parameter], torch.nn.Parameter]) -> None:
        made: dict[int, torch.nn.Parameter] = {}
        for sub in self.module.modules():
            for name, p in sub._parameters.items():
                if p is not None:
                    if id(p) not in made:
                        made[id(p)] = make(p)
                    sub._parameters[name] = made[id(p)]

    def gather(self, sharded: torch.nn.Module, device: torch.device, everywhere: bool) -> bool:
        """Fill the copy with ``sharded``'s full weights: on every rank (``everywhere``),
        else on rank zero only, on the CPU. A collective: every rank calls it. Returns
        whether this rank holds them."""
        from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

        options = StateDictOptions(full_state_dict=True, cpu_offload=not everywhere)
        state: dict[str, torch.Tensor] = get_model_state_dict(sharded, options=options)  # type: ignore[assignment]
        if not state:
            return False
        # The gathered tensors become the copy's parameters (no second copy of the weights);
        # tied parameters take their first name's. The load then checks every key and fills
        # the buffers.
        first: dict[int, str] = {}
        for name, p in self.module.named_parameters(remove_duplicate=False):
            first.setdefault(id(p), name)
        self._replace(lambda p: torch.nn.Parameter(state[first[id(p)]], p.requires_grad))
        self.module.to(device if everywhere else torch.device("cpu"))  # the buffers
        self.module.load_state_dict(state)
        self.module.eval()
        self.loaded = True
        return True

    def release(self) -> None:
        """Back to ``meta``: the full weights' memory is freed."""
        if self.loaded:
            self._replace(lambda p: torch.nn.Parameter(torch.empty_like(p, device="meta"), p.requires_grad))
            self.loaded = False

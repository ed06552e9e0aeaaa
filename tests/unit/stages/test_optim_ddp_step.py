"""One DDP step on a global batch equals one single-process step on the same batch.

Two gloo processes each take half of a 2-sample batch through the tokenizer with an EMA
codebook (whose statistics are all-reduced across ranks); their averaged gradients must
equal those of one process on both samples, and so must the weights and EMA statistics
after one step. Gradients, not only weights: one AdamW step moves a weight by about
lr x sign(gradient) whatever the gradient's size, so a rank that scaled its loss would
still step alike. Lovasz is off for this
check: it is defined on the whole batch's voxel set, so a per-rank Lovasz is a different
loss by design, not a synchronisation bug.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist
from omegaconf import OmegaConf
from torch.nn.parallel import DistributedDataParallel

from conftest import free_port, two_ranks
from occtrain.config.recipe import OptimConfig
from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAEConfig
from occtrain.stages.optim import configure_adamw

CFG = dict(
    num_codes=16,
    code_dim=8,
    class_embed_dim=4,
    base_channels=8,
    channel_mult=[1, 1, 1],
    strides=[4, 5],
    num_res_blocks=1,
    latent_attention=False,
    z_channels=8,
    ema_decay=0.9,
    lovasz_weight=0.0,
)


def _model() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_tokenizer("occworld_vqvae", OmegaConf.merge(OmegaConf.structured(OccWorldVQVAEConfig), CFG))


def _batch() -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return torch.randint(0, 18, (2, 200, 200, 16), generator=g)


def _step(model: torch.nn.Module, forward, batch: torch.Tensor) -> dict[str, torch.Tensor]:
    """One AdamW step; returns the gradients it stepped on, by parameter name."""
    opt = configure_adamw(model.parameters(), OptimConfig(lr=1e-2, weight_decay=0.0), 10)["optimizer"]
    forward(batch).losses["loss"].backward()
    grads = {n: p.grad.detach().clone() for n, p in model.named_parameters() if p.grad is not None}
    opt.step()
    return grads


def _worker(rank: int, port: int, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=2)
    model = _model()
    ddp = DistributedDataParallel(model)
    grads = _step(model, ddp, _batch()[rank : rank + 1])
    if rank == 0:
        state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        torch.save({"state": state, "grads": grads}, out)
    dist.destroy_process_group()


def test_ddp_step_equals_single_process_step(tmp_path):
    out = str(tmp_path / "ddp.pt")
    two_ranks(_worker, free_port(), out)
    ddp = torch.load(out, weights_only=True)

    model = _model()
    grads = _step(model, model, _batch())
    assert ddp["grads"].keys() == grads.keys() and len(grads) > 10
    for name, grad in grads.items():
        # Up to the order the two halves are summed in: within 0.1 % of the tensor's largest
        # gradient (a rank that scaled its loss by 1.5 is 50 % off).
        atol = 1e-3 * float(grad.abs().max())
        torch.testing.assert_close(
            ddp["grads"][name], grad, rtol=1e-3, atol=atol, msg=lambda m, name=name: f"grad of {name}: {m}"
        )
    assert sum(int(g.abs().max() > 1e-6) for g in grads.values()) > 10  # real gradients, so equality means something

    single = model.state_dict()
    assert ddp["state"].keys() == single.keys()
    moved = 0
    for name, value in single.items():
        torch.testing.assert_close(
            ddp["state"][name], value, rtol=1e-4, atol=1e-5, msg=lambda m, name=name: f"{name}: {m}"
        )
        moved += int(not torch.equal(value, _model().state_dict()[name]))
    assert moved > 10  # the step changed the weights (and the EMA codebook)

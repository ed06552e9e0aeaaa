"""Peak memory per rank of one training step of a ~300 M-parameter LLM, measured on this
machine beside what `occtrain plan-memory` predicts for it.

    python tools/bench/scale.py [--hidden 1024 --layers 22 --seq 256 --batch 1]

The LLM is the one a world-model stage trains (``models.llm.build_llm``, a Llama built
from config; the world model's own parts are a few thousand parameters beside it), with
AdamW over all of it and fp32 weights (``32-true``). Each setting runs in fresh
processes and reads each rank's peak RSS (``ru_maxrss``) after two optimizer steps, minus
the same process's RSS before the model was built (torch and Python themselves):

- 1 process;
- DDP x 2 (gloo, ``DistributedDataParallel``);
- sharded x 2: FSDP2's ``fully_shard`` on each decoder layer and the root, over gloo, as
  the world-model stages shard under ``trainer.strategy: fsdp`` (``stages/sharding.py``);
- each of them again with the decoder layers checkpointed (``models.llm.checkpoint_layers``).

The plan is ``plan_memory.plan`` for the same model, batch and sequence length.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
import torch.distributed as dist  # noqa: E402
import torch.multiprocessing as mp  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.commands.plan_memory import GIB, MemoryRow, count_llm, plan  # noqa: E402
from occtrain.config.llm import LLMConfig  # noqa: E402
from occtrain.models.llm import build_llm, checkpoint_layers  # noqa: E402

VOCAB = 8000
MODES = ("1 process", "DDP x2", "sharded x2")


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def one_process(ddp: MemoryRow) -> float:
    """The plan of one process: DDP's row without its gradient buckets (a gradients' copy)."""
    return ddp.total - ddp.gradients


def _step(rank: int, world: int, mode: str, cfg: LLMConfig, args: argparse.Namespace, store: str, out: str) -> None:
    import warnings

    from transformers.utils import logging as hf_logging

    warnings.filterwarnings("ignore")
    hf_logging.set_verbosity_error()  # "use_cache=True is incompatible with gradient checkpointing", once per rank
    torch.set_num_threads(max(1, 2 // world))
    if world > 1:
        dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    before = _rss_bytes()
    torch.manual_seed(0)
    model = build_llm(cfg, VOCAB)
    if args.checkpointing:
        checkpoint_layers(model)
    model.train()
    if mode == "DDP x2":
        model = torch.nn.parallel.DistributedDataParallel(model)
    elif mode == "sharded x2":
        from torch.distributed.fsdp import fully_shard

        for layer in model.model.layers:
            fully_shard(layer)
        fully_shard(model)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    ids = torch.randint(0, VOCAB, (args.batch, args.seq), generator=torch.Generator().manual_seed(rank))
    for _ in range(2):
        loss = model(input_ids=ids, labels=ids).loss
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
    Path(f"{out}.{rank}").write_text(f"{_peak_bytes() - before}")
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()


def measure(mode: str, cfg: LLMConfig, args: argparse.Namespace) -> list[int]:
    """Peak RSS growth per rank of ``mode``, each rank a fresh process."""
    world = 1 if mode == "1 process" else 2
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "peak")
        mp.spawn(_step, args=(world, mode, cfg, args, os.path.join(tmp, "store"), out), nprocs=world, join=True)
        return [int(Path(f"{out}.{r}").read_text()) for r in range(world)]


def measure_cuda(cfg: LLMConfig, args: argparse.Namespace, precision: str) -> int:
    """Peak bytes the CUDA allocator held over two optimizer steps in one process."""
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    before = torch.cuda.memory_allocated()
    torch.manual_seed(0)
    model = build_llm(cfg, VOCAB).cuda()
    if args.checkpointing:
        checkpoint_layers(model)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    ids = torch.randint(0, VOCAB, (args.batch, args.seq), device="cuda")
    for _ in range(2):
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bf16-mixed"):
            loss = model(input_ids=ids, labels=ids).loss
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated() - before
    del model, opt, loss
    return peak


def main_cuda(cfg: LLMConfig, count, args: argparse.Namespace) -> None:
    print(
        f"LLM {count.params / 1e6:.0f} M parameters, batch {args.batch} x {args.seq} tokens, AdamW, one GPU "
        f"({torch.cuda.get_device_name()}); GiB"
    )
    print(f"{'setting':<32} {'measured':>9} {'planned':>9} {'measured / planned':>19}")
    for precision in ("32-true", "bf16-mixed"):
        for checkpointing in (False, True):
            args.checkpointing = checkpointing
            ddp, _ = plan(count, precision, args.batch, args.seq, 1, checkpointing)
            planned = one_process(ddp)
            peak = measure_cuda(cfg, args, precision)
            name = precision + (", checkpointing" if checkpointing else "")
            print(f"{name:<32} {peak / GIB:>9.2f} {planned / GIB:>9.2f} {peak / planned:>19.2f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hidden", type=int, default=1024)
    parser.add_argument("--layers", type=int, default=22)
    parser.add_argument("--seq", type=int, default=256)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--cuda", action="store_true", help="one process on the GPU, fp32 and bf16-mixed")
    args = parser.parse_args()
    cfg = LLMConfig(
        hidden_size=args.hidden,
        num_layers=args.layers,
        num_heads=16,
        intermediate_size=int(args.hidden * 2.75),
        text_vocab_size=VOCAB,
    )
    count = count_llm(cfg, 0)
    if args.cuda:
        return main_cuda(cfg, count, args)
    print(
        f"LLM {count.params / 1e6:.0f} M parameters, batch {args.batch} x {args.seq} tokens, fp32, AdamW; GiB per rank"
    )
    print(f"{'setting':<30} {'measured (each rank)':>22} {'planned':>9} {'measured / planned':>19}")
    rows = []
    for checkpointing in (False, True):
        args.checkpointing = checkpointing
        ddp, sharded = plan(count, "32-true", args.batch, args.seq, 2, checkpointing)
        single = one_process(ddp)
        for mode, planned in zip(MODES, (single, ddp.total, sharded.total)):
            peaks = measure(mode, cfg, args)
            name = mode + (", checkpointing" if checkpointing else "")
            shown = " / ".join(f"{p / GIB:.2f}" for p in peaks)
            print(f"{name:<30} {shown:>22} {planned / GIB:>9.2f} {max(peaks) / planned:>19.2f}", flush=True)
            rows.append(f"{name} {max(peaks) / GIB:.2f} GiB ({max(peaks) / planned:.2f} of the plan)")
    record(
        [
            Row(
                f"peak RSS a rank of two AdamW steps of a {count.params / 1e6:.0f} M Llama (fp32, {args.batch} x "
                f"{args.seq} tokens) in fresh processes, beside `occtrain plan-memory`'s plan",
                "; ".join(rows),
            )
        ]
    )


if __name__ == "__main__":
    main()

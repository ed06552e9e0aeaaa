"""World-model costs, measured side by side in one run on the quickstart sizes.

    python tools/bench/world_model.py [--data data/quickstart] [--steps 6]

1. Scene codes for a training batch: encoding the clip's frames with the frozen tokenizer
   at every step (and decoding their occupancy from the shard) vs looking them up in the
   code cache the stage builds once (what ``model.cache_codes`` switches).
2. Generating one scene: next-scene prediction (one forward over the query block, OccLLaMA
   Algorithm 1) vs token-by-token decoding with the KV cache (``llm.scene_prediction``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import DataConfig, load_config  # noqa: E402
from occtrain.config.llm import LLMConfig  # noqa: E402
from occtrain.core.scene_encoders import VQSceneEncoder  # noqa: E402
from occtrain.core.tokenizer_exports import build_tokenizer  # noqa: E402
from occtrain.core.vocab import JointVocab  # noqa: E402
from occtrain.data.clips import clips_from_batch  # noqa: E402
from occtrain.data.datamodule import ShardDataModule, ensure_data  # noqa: E402
from occtrain.engine import TEXT_ENTRIES, WorldModelEngine  # noqa: E402
from occtrain.families.occllama import OccLLaMATokenizerConfig, OccLLaMAWorldModel, TaskConfig  # noqa: E402
from occtrain.models.llm import build_llm  # noqa: E402
from occtrain.models.text_tokenizer import train_text_tokenizer  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def engine_for(mode: str, tokenizer: torch.nn.Module) -> WorldModelEngine:
    text = train_text_tokenizer(["a car is parked", "turn left", "go straight"] * 20, 300)
    llm_cfg = LLMConfig(scene_prediction=mode)
    vocab = JointVocab(text, tokenizer.codebook_sizes, tuple(tokenizer.latent_hw), llm_cfg)
    world = OccLLaMAWorldModel(build_llm(llm_cfg, len(vocab)), vocab, tokenizer.codebook, mode)
    engine = WorldModelEngine(
        VQSceneEncoder(tokenizer),
        world.eval(),
        text,
        TaskConfig(context_frames=2, forecast_frames=6),
        family="occllama",
    )
    return engine.default_tasks("pretrain")


def time_batches(engine: WorldModelEngine, data: DataConfig, entries, steps: int) -> float:
    """Seconds per training batch: read + decode the shard sample, scene codes, build the sequences."""
    dm = ShardDataModule(data, "clips", entries={"train": entries})
    it = iter(dm.train_dataloader())
    engine.task_batch(clips_from_batch(b := next(it)), b, 0)  # warm-up
    start = time.perf_counter()
    for step in range(steps):
        batch = next(it)
        engine.task_batch(clips_from_batch(batch), batch, step)
    return (time.perf_counter() - start) / steps


def time_scene(engine: WorldModelEngine, repeats: int) -> float:
    prefix = torch.tensor([engine.vocab.bos_id] + engine.vocab.text_ids("forecast the scene"))
    engine.world.generate_scene(prefix)
    start = time.perf_counter()
    for _ in range(repeats):
        engine.world.generate_scene(prefix)
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(REPO / "configs/data/quickstart.yaml"))
    parser.add_argument("--steps", type=int, default=6)
    args = parser.parse_args()
    torch.manual_seed(0)
    data = load_config(DataConfig, args.data) if args.data.endswith(".yaml") else DataConfig(root=args.data)
    ensure_data(data, verbose=False)
    tok_cfg = OmegaConf.merge(
        OmegaConf.structured(OccLLaMATokenizerConfig),
        OmegaConf.load(REPO / "configs/model/occllama_tokenizer_tiny.yaml")["occllama_tokenizer"],
    )
    tokenizer = build_tokenizer("occllama_tokenizer", tok_cfg).eval()
    tokenizer.export_dir = None
    engine = engine_for("next_scene", tokenizer)

    per_step_encode = time_batches(engine, data, None, args.steps)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        engine.build_scene_cache(data.root, Path(tmp) / "codes.safetensors")
        cache_build = time.perf_counter() - start
    cached = time_batches(engine, data, TEXT_ENTRIES, args.steps)
    print(
        f"scene codes per batch of {data.batch_size} clips: encode every step {per_step_encode * 1e3:.0f} ms, "
        f"code cache {cached * 1e3:.0f} ms -> {per_step_encode / cached:.1f}x faster "
        f"(the cache costs {cache_build:.1f} s once)"
    )

    next_scene = time_scene(engine, 5)
    next_token = time_scene(engine_for("next_token", tokenizer), 2)
    print(
        f"one {engine.vocab.scene_len}-token scene: next-scene {next_scene * 1e3:.0f} ms, "
        f"token by token {next_token * 1e3:.0f} ms -> {next_token / next_scene:.1f}x faster"
    )
    record(
        [
            Row(
                f"scene codes for a training batch of {data.batch_size} clips: encoding the frames with the frozen "
                "tokenizer every step vs the code cache the stage builds once",
                f"{per_step_encode * 1e3:.0f} vs {cached * 1e3:.0f} ms ({per_step_encode / cached:.0f}x; the cache "
                f"costs {cache_build:.1f} s once)",
            ),
            Row(
                f"generating one {engine.vocab.scene_len}-token scene: next-scene prediction (one forward over the "
                "query block) vs token by token with the KV cache",
                f"{next_scene * 1e3:.0f} vs {next_token * 1e3:.0f} ms ({next_token / next_scene:.1f}x)",
            ),
        ]
    )


if __name__ == "__main__":
    main()

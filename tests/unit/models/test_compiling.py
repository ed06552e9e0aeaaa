"""``trainer.compile``: compiled training forwards, eager evaluation, the same losses."""

from __future__ import annotations

import torch
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.config.llm import LoRAConfig
from occtrain.models.compiling import (
    CACHE_ENV,
    OWNER_FILE,
    compile_all,
    decoder_layers,
    trust_cache,
    use_cache_dir,
)
from occtrain.models.llm import apply_lora

TINY_LLAMA = dict(
    vocab_size=64,
    hidden_size=32,
    intermediate_size=64,
    num_hidden_layers=2,
    num_attention_heads=2,
    num_key_value_heads=2,
)


def tiny_llama(seed: int = 0) -> LlamaForCausalLM:
    torch.manual_seed(seed)
    return LlamaForCausalLM(LlamaConfig(**TINY_LLAMA, attn_implementation="sdpa"))


def test_only_training_forwards_go_through_the_compiler_and_the_weights_keep_their_names():
    graphs: list[int] = []

    def counting(gm, example_inputs):  # a backend that runs the captured graph as it is
        graphs.append(len(gm.graph.nodes))
        return gm.forward

    model = tiny_llama()
    names = list(model.state_dict())
    assert compile_all(decoder_layers(model), backend=counting) == 2
    assert compile_all(decoder_layers(model), backend=counting) == 0  # compiled already
    ids = torch.randint(0, 64, (1, 6))
    model(input_ids=ids, labels=ids).loss.backward()
    trained = len(graphs)
    assert trained >= 1
    model.eval()
    with torch.no_grad():
        model(input_ids=ids)  # evaluation: eager, nothing captured
    assert len(graphs) == trained
    assert list(model.state_dict()) == names


def test_decoder_layers_are_found_inside_a_lora_wrapper():
    wrapped = apply_lora(tiny_llama(), LoRAConfig(r=2, alpha=4, target_modules=["q_proj", "v_proj"]))
    layers = decoder_layers(wrapped)
    assert len(layers) == 2 and all(type(layer).__name__ == "LlamaDecoderLayer" for layer in layers)


#: A child process with its system temp dir pointed at an empty folder: the same three
#: AdamW steps eager and compiled (inductor on the CPU, through the callback a stage uses,
#: under the 4D boolean mask and explicit positions the world models train with); it prints
#: both losses.
COMPILED_STEPS = """
import json, sys
from pathlib import Path
from types import SimpleNamespace

import torch
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.models.compiling import decoder_layers
from occtrain.stages.callbacks import CompileBlocks


def tiny_llama():
    torch.manual_seed(0)
    cfg = json.loads(sys.argv[2])
    return LlamaForCausalLM(LlamaConfig(**cfg, attn_implementation="sdpa"))


eager, compiled = tiny_llama(), tiny_llama()
ids = torch.randint(0, 64, (2, 12), generator=torch.Generator().manual_seed(1))
mask = torch.ones(2, 1, 12, 12, dtype=torch.bool).tril()
positions = torch.arange(12).expand(2, 12)


def losses(model):
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    out = []
    for _ in range(3):
        loss = model(input_ids=ids, attention_mask=mask, position_ids=positions, labels=ids).loss
        loss.backward()
        opt.step()
        opt.zero_grad()
        out.append(loss.item())
    return out


fit = SimpleNamespace(is_global_zero=True, world_size=1)
blocks = CompileBlocks(Path(sys.argv[1]))
blocks.on_fit_start(fit, SimpleNamespace(compiled_blocks=lambda: decoder_layers(compiled)))
got = losses(compiled)
blocks.teardown(fit, None, "fit")
print(json.dumps({"eager": losses(eager), "compiled": got}))
"""


def test_compiled_training_steps_give_the_eager_losses_and_write_nothing_outside_the_run(tmp_path):
    """Inductor's kernels, its precompiled C++ headers (about 150 MB, which torch puts in the
    system's temp dir whatever TORCHINDUCTOR_CACHE_DIR says) and the compiler's temporary
    files all go to the run's cache: the temp dir holds no file afterwards (torch's import
    makes its default folder, empty). The process is the point: torch fixes where the
    headers go when it loads."""
    import json
    import os
    import subprocess
    import sys

    temp, cache = tmp_path / "system-temp", tmp_path / "run" / "cache" / "inductor"
    temp.mkdir()
    env = {**os.environ, "TMPDIR": str(temp)}
    env.pop("TORCHINDUCTOR_CACHE_DIR", None)
    res = subprocess.run(
        [sys.executable, "-c", COMPILED_STEPS, str(cache), json.dumps(TINY_LLAMA)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    steps = json.loads(res.stdout.splitlines()[-1])
    torch.testing.assert_close(torch.tensor(steps["compiled"]), torch.tensor(steps["eager"]), rtol=1e-4, atol=1e-5)
    assert steps["eager"][2] < steps["eager"][0]  # the steps trained: equal losses are not equally stuck ones
    assert [p for p in temp.rglob("*") if not p.is_dir()] == []
    assert any(p.suffix == ".gch" for p in (cache / "precompiled_headers").iterdir())


def test_a_compile_cache_is_read_only_where_it_was_made(tmp_path):
    """Inductor unpickles its cache: one that came with a run copied from elsewhere (another
    inode, another place) is emptied before a compile reads it; the one made here is kept."""
    import shutil

    made = tmp_path / "run" / "cache" / "inductor"
    assert trust_cache(made)  # new
    (made / "fxgraph").mkdir()
    (made / "fxgraph" / "entry").write_bytes(b"a pickle")
    assert trust_cache(made) and (made / "fxgraph" / "entry").is_file()
    copied = tmp_path / "copy" / "cache" / "inductor"
    shutil.copytree(made, copied)
    assert not trust_cache(copied)
    assert sorted(p.name for p in copied.iterdir()) == [OWNER_FILE] and trust_cache(copied)
    assert (made / "fxgraph" / "entry").is_file()  # the original is untouched


def test_a_users_own_cache_folder_is_used_as_it_is(tmp_path, monkeypatch):
    mine = tmp_path / "mine"
    (mine / "fxgraph").mkdir(parents=True)
    monkeypatch.setenv(CACHE_ENV, str(mine))
    use = use_cache_dir(tmp_path / "run" / "cache" / "inductor")
    try:
        assert use.folder == mine and not use.emptied and (mine / "fxgraph").is_dir()
    finally:
        use.restore()

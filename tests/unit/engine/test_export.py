"""A world-model export is what the Hugging Face ecosystem loads: plain transformers + peft,
in a process that never imports occtrain, give occtrain's logits on the same ids."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.core.tokenizer_exports import build_tokenizer, save_tokenizer
from occtrain.engine import export_engine, load_world_model, new_world_model
from occtrain.families.occllama import TaskConfig
from occtrain.models.attention import allowed_pairs
from occtrain.models.llm import apply_lora

TINY_TOKENIZER = {
    "num_codes": 16,
    "code_dim": 8,
    "class_embed_dim": 4,
    "base_channels": 4,
    "channel_mult": [1, 1, 1, 1],
    "strides": [2, 2, 5],
    "num_res_blocks": 1,
    "z_channels": 8,
    "latent_attention": False,
}
TINY_LLM = LLMConfig(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, text_vocab_size=300)

#: Runs in a fresh interpreter: transformers and peft only.
PLAIN_HF = r"""
import sys, json, torch, numpy as np
from transformers import AutoModelForCausalLM, AutoTokenizer
llm_dir, ids_file, out_file, adapter = sys.argv[1:5]
model = AutoModelForCausalLM.from_pretrained(llm_dir, dtype=torch.float32)
if adapter == "1":
    from peft import PeftModel
    model = PeftModel.from_pretrained(model, llm_dir + "/adapter")
model.eval()
tok = AutoTokenizer.from_pretrained(llm_dir)
ids = torch.tensor(json.load(open(ids_file)))[None]
with torch.no_grad():
    logits = model(input_ids=ids).logits[0]
np.save(out_file, logits.numpy())
assert not any(m == "occtrain" or m.startswith("occtrain.") for m in sys.modules), "occtrain was imported"
print(json.dumps({"tokenizer_size": len(tok), "model_type": model.config.model_type}))
"""


@pytest.fixture(scope="module")
def tokenizer_export(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    model = build_tokenizer("occworld_vqvae", TINY_TOKENIZER)
    return save_tokenizer(model, "occworld_vqvae", TINY_TOKENIZER, tmp_path_factory.mktemp("tok") / "export")


def occtrain_logits(engine, ids: torch.Tensor) -> torch.Tensor:
    """occtrain's own forward: the joint-vocabulary embedding and its boolean 4D mask."""
    seg = torch.zeros_like(ids)[None]
    allowed = allowed_pairs(seg, torch.ones_like(seg, dtype=torch.bool))[:, None]
    with torch.no_grad():
        logits = engine.world.step(ids[None], allowed, torch.arange(len(ids))[None]).logits
    return logits[0]


@pytest.mark.parametrize("merge", [False, True], ids=["adapter", "merged"])
def test_plain_transformers_and_peft_give_occtrains_logits(tmp_path, synth_dataset, tokenizer_export, merge):
    torch.manual_seed(1)
    engine = new_world_model(
        {"tokenizer": tokenizer_export}, TINY_LLM, TaskConfig(context_frames=2), synth_dataset, family="occllama"
    )
    engine.world.llm = apply_lora(engine.world.llm, LoRAConfig(r=4, alpha=8, dropout=0.0))
    with torch.no_grad():  # LoRA's B starts at zero: make the adapter change the output
        for name, p in engine.world.llm.named_parameters():
            if "lora_B" in name:
                p.normal_(0, 0.5)
    engine.eval()
    export = export_engine(engine, tmp_path / "export", stage="instruct", merge=merge)
    llm_dir = export / "llm"
    assert json.loads((llm_dir / "config.json").read_text())["model_type"] == "llama"
    assert (llm_dir / "generation_config.json").is_file() and (llm_dir / "model.safetensors").is_file()
    assert (llm_dir / "adapter").is_dir() != merge

    vocab = engine.vocab
    text = vocab.text_ids("a car is parked ahead, turn left")
    ids = torch.tensor(
        [vocab.bos_id, *text, vocab.act_open_id, *vocab.action_ids(torch.tensor([[3.0, -1.0]])).tolist(), vocab.eos_id]
    )
    loaded = load_world_model(export).eval()
    ours = occtrain_logits(loaded, ids)
    assert torch.allclose(ours, occtrain_logits(engine, ids), atol=1e-5)  # export -> load is lossless

    (tmp_path / "ids.json").write_text(json.dumps(ids.tolist()))
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            PLAIN_HF,
            str(llm_dir),
            str(tmp_path / "ids.json"),
            str(tmp_path / "hf.npy"),
            "0" if merge else "1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    info = json.loads(out.stdout.strip().splitlines()[-1])
    assert info == {"tokenizer_size": len(vocab), "model_type": "llama"}
    theirs = torch.from_numpy(np.load(tmp_path / "hf.npy"))
    assert (ours - theirs).abs().max().item() <= 1e-5


def test_export_carries_the_task_config(tmp_path, synth_dataset, tokenizer_export):
    """A later stage or ``occtrain eval`` builds prompts exactly as the model trained."""
    torch.manual_seed(2)
    tasks = TaskConfig(weights={"qa": 1.0}, context_frames=2, forecast_frames=3, max_objects=4)
    engine = new_world_model(
        {"tokenizer": tokenizer_export}, TINY_LLM, tasks, synth_dataset, max_new_text_tokens=123, family="occllama"
    )
    loaded = load_world_model(export_engine(engine, tmp_path / "export", stage="pretrain"))
    assert loaded.tasks == tasks and loaded.max_new_text_tokens == 123
    assert loaded.family == "occllama"

"""The LLM: tiny Llama from config, a local HF directory (``llm.path``), LoRA through peft."""

from __future__ import annotations

import pytest
import torch
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.core.builder import collate
from occtrain.core.vocab import JointVocab
from occtrain.errors import ConfigError
from occtrain.families.occllama.world_model import OccLLaMAWorldModel as OccWorldModel
from occtrain.models.llm import apply_lora, build_llm, load_text_tokenizer
from occtrain.models.text_tokenizer import train_text_tokenizer

TEXTS = ["the car turns left", "how many cars are there"] * 10


def test_tiny_llama_from_config():
    cfg = LLMConfig(hidden_size=64, num_layers=2, num_heads=4, intermediate_size=128)
    model = build_llm(cfg, vocab_size=500)
    c = model.config
    assert (c.vocab_size, c.hidden_size, c.num_hidden_layers, c.num_attention_heads) == (500, 64, 2, 4)
    assert model.get_input_embeddings().weight.shape == (500, 64)
    assert model.get_output_embeddings().weight.shape == (500, 64)
    assert c._attn_implementation == "sdpa"


@pytest.fixture()
def saved_llm(tmp_path):
    """A tiny 'pretrained' LLM directory with its tokenizer, as a user would point llm.path at."""
    tok = train_text_tokenizer(TEXTS, 300)
    tok.pad_token = None  # like LLaMA's tokenizer: no pad token
    torch.manual_seed(0)
    cfg = LlamaConfig(
        vocab_size=len(tok),
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=1,
        num_attention_heads=2,
        num_key_value_heads=2,
        tie_word_embeddings=False,
    )
    model = LlamaForCausalLM(cfg)
    model.save_pretrained(str(tmp_path))
    tok.save_pretrained(str(tmp_path))
    return tmp_path, model


def test_from_pretrained_directory(saved_llm):
    path, original = saved_llm
    tok = load_text_tokenizer(path)
    assert tok.pad_token_id == tok.eos_token_id  # padding falls back to eos
    T = len(tok)
    vocab = JointVocab(tok, 8, scene_hw=(2, 2))
    llm = build_llm(LLMConfig(path=str(path)), len(vocab))
    emb = llm.get_input_embeddings().weight
    assert emb.shape == (len(vocab), 32) and llm.get_output_embeddings().weight.shape[0] == len(vocab)
    # The pretrained rows are kept; the new ones are the joint tokens.
    assert torch.equal(emb[:T], original.get_input_embeddings().weight)
    world = OccWorldModel(llm, vocab, torch.randn(8, 4)).eval()
    seq = world.builder().text("the car").scene(torch.tensor([0, 1, 2, 3])).text("turns left", True).build()
    out = world(collate([seq], vocab.pad_id))
    assert torch.isfinite(out.loss)
    assert world.generate_scene(seq.input_ids).shape == (4,)


def test_bad_path_is_one_line_config_error(tmp_path):
    with pytest.raises(ConfigError, match=r"^llm\.path: .*no config\.json") as e:
        build_llm(LLMConfig(path=str(tmp_path / "missing")), 100)
    assert "\n" not in str(e.value)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match=r"^llm\.path: cannot load") as e:
        build_llm(LLMConfig(path=str(tmp_path)), 100)
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match=r"^llm\.path"):
        load_text_tokenizer(tmp_path / "missing")


def test_lora_trains_only_the_adapter():
    tok = train_text_tokenizer(TEXTS, 300)
    vocab = JointVocab(tok, 8, scene_hw=(2, 2))
    torch.manual_seed(0)
    llm = build_llm(LLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64), len(vocab))
    peft_model = apply_lora(llm, LoRAConfig(r=4, alpha=8, dropout=0.0))
    trainable = [n for n, p in peft_model.named_parameters() if p.requires_grad]
    assert trainable and all("lora_" in n for n in trainable)
    assert {n.split(".lora_")[0].rsplit(".", 1)[-1] for n in trainable} == {"q_proj", "v_proj"}
    world = OccWorldModel(peft_model, vocab, torch.randn(8, 4))
    seq = world.builder().scene(torch.tensor([0, 1, 2, 3])).text("turns left", True).build()
    world(collate([seq], vocab.pad_id)).loss.backward()
    assert all(p.grad is not None for n, p in peft_model.named_parameters() if p.requires_grad)
    assert world.export_config()["attn_implementation"] == "sdpa"
    with pytest.raises(ConfigError, match="lora.target_modules"):
        apply_lora(
            build_llm(LLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64), 50),
            LoRAConfig(target_modules=["nope_proj"]),
        )

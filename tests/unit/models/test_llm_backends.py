"""The LLM backend is any Hugging Face causal LM occtrain drives: tiny Llama, Qwen2 and Gemma2
models built from config run a world model's training step, KV-cache and batched decoding,
LoRA, bottleneck adapters and the Hugging Face export alike; OccVLA takes a PaliGemma-style
directory for its vision tower and its LLM; other model types are refused in one line."""

from __future__ import annotations

import collections

import pytest
import torch

from occtrain.config.llm import LLMConfig, LoRAConfig
from occtrain.core.builder import collate
from occtrain.core.decoding import ActionAnswer, TextAnswer
from occtrain.core.tokenizer_exports import build_tokenizer, save_tokenizer
from occtrain.engine import export_engine, load_world_model, new_world_model
from occtrain.errors import ConfigError
from occtrain.families.occllama import TaskConfig
from occtrain.models.adapters import AdapterConfig, add_adapters
from occtrain.models.llm import apply_lora, build_llm
from occtrain.models.text_tokenizer import train_text_tokenizer

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


def tiny_llm(model_type: str) -> LLMConfig:
    return LLMConfig(
        model_type=model_type,
        hidden_size=32,
        num_layers=2,
        num_heads=2,
        intermediate_size=64,
        text_vocab_size=300,
        action_bins=16,
        action_range=[[-10.0, 10.0], [-10.0, 10.0]],
    )


@pytest.fixture(scope="module")
def tokenizer_export(tmp_path_factory):
    torch.manual_seed(0)
    model = build_tokenizer("occworld_vqvae", TINY_TOKENIZER)
    return save_tokenizer(model, "occworld_vqvae", TINY_TOKENIZER, tmp_path_factory.mktemp("tok") / "export")


@pytest.mark.parametrize("model_type", ["llama", "qwen2", "gemma2"])
def test_a_world_model_runs_on_each_backend(model_type, tmp_path, synth_dataset, tokenizer_export):
    torch.manual_seed(0)
    engine = new_world_model(
        {"tokenizer": tokenizer_export},
        tiny_llm(model_type),
        TaskConfig(context_frames=1),
        synth_dataset,
        family="occllama",
    )
    world = engine.world
    assert world.llm.config.model_type == model_type
    v = engine.vocab
    scene = torch.arange(v.scene_len) % 16
    seq = (
        world.builder()
        .text("a car ahead")
        .scene(scene)
        .actions(torch.tensor([[1.0, 0.5]]), True)
        .scene(scene, True)
        .text("turn left", True)
        .build()
    )
    out = world(collate([seq], v.pad_id))
    out.loss.backward()
    assert torch.isfinite(out.loss) and world.occ_proj[1].weight.grad.abs().sum() > 0

    world.eval()
    prompt = world.builder().text("a car ahead").scene(scene).build()
    plan = [TextAnswer(3, stop_at_eos=False), ActionAnswer(2), TextAnswer(2, stop_at_eos=False)]
    cached, recomputed = (world.decoder(prompt.input_ids, use_cache=c) for c in (True, False))
    one = [cached.answer(a) for a in plan]
    assert [str(x) for x in one] == [
        str(recomputed.answer(a)) for a in plan
    ]  # the KV cache is cropped and reused right
    short = world.builder().text("go").build()
    batched = world.generate_batch([prompt.input_ids, short.input_ids], [plan, plan[:1]])
    assert str(batched[0]) == str(one) and str(batched[1]) == str(world.generate(short.input_ids, plan[:1]))

    # LoRA and bottleneck adapters find the backend's projections and decoder layers.
    lora = apply_lora(build_llm(tiny_llm(model_type), 50), LoRAConfig(r=2, alpha=4, dropout=0.0))
    assert any("lora_A" in n for n, _ in lora.named_parameters())
    assert len(add_adapters(world.llm, AdapterConfig(reduction_factor=4))) == 2

    # The export is a plain Hugging Face directory of that type, and reloads to the same logits.
    export = export_engine(engine, tmp_path / "export", stage="pretrain")
    again = load_world_model(export).eval()
    assert again.world.llm.config.model_type == model_type
    batch = collate([seq], v.pad_id)
    torch.testing.assert_close(again.world(batch).logits, world(batch).logits, atol=1e-5, rtol=1e-5)


def test_other_model_types_are_refused_in_one_line(tmp_path):
    with pytest.raises(
        ConfigError,
        match=r"^llm\.model_type: 'gpt2' is not an LLM backend occtrain drives; use one of llama, qwen2, gemma2$",
    ):
        build_llm(LLMConfig(model_type="gpt2"), 100)
    from transformers import GPT2Config, GPT2LMHeadModel

    GPT2LMHeadModel(GPT2Config(n_embd=16, n_layer=1, n_head=2, vocab_size=100)).save_pretrained(str(tmp_path))
    with pytest.raises(
        ConfigError, match=r"model type 'gpt2' is not an LLM backend occtrain drives \(llama, qwen2, gemma2\)"
    ) as err:
        build_llm(LLMConfig(path=str(tmp_path)), 100)
    assert "\n" not in str(err.value) and str(tmp_path) in str(err.value)


def test_a_pickled_checkpoint_is_refused_without_advice_to_unpickle_it(tmp_path):
    """A directory whose weights are pytorch_model.bin: transformers' own refusal repeats
    PyTorch's advice to load it with weights_only=False, which runs what the pickle says."""
    from transformers import LlamaConfig, LlamaForCausalLM

    model = LlamaForCausalLM(
        LlamaConfig(vocab_size=64, hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2)
    )
    model.config.save_pretrained(str(tmp_path))
    # A pickle that names a class besides the tensors (it could name any, and run code through it).
    torch.save({**model.state_dict(), "extra": collections.OrderedDict}, tmp_path / "pytorch_model.bin")
    with pytest.raises(ConfigError) as err:
        build_llm(LLMConfig(path=str(tmp_path)), 64)
    line = str(err.value)
    assert "\n" not in line and f"{tmp_path} holds its weights as pytorch_model.bin, a pickle" in line
    assert "weights_only" not in line


@pytest.fixture(scope="module")
def paligemma_dir(tmp_path_factory):
    """A tiny PaliGemma2-style directory (SigLIP tower + Gemma2 language model + tokenizer), as
    save_pretrained writes it."""
    from transformers import Gemma2Config, PaliGemmaConfig, PaliGemmaForConditionalGeneration, SiglipVisionConfig

    out = tmp_path_factory.mktemp("paligemma")
    tok = train_text_tokenizer(["a car turns left", "how many cars are there", "describe the scene"] * 10, 300)
    text = Gemma2Config(
        vocab_size=len(tok),
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        num_key_value_heads=2,
        head_dim=16,
        query_pre_attn_scalar=16,
        max_position_embeddings=512,
    )
    vision = SiglipVisionConfig(
        hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=32, patch_size=8
    )
    torch.manual_seed(0)
    model = PaliGemmaForConditionalGeneration(
        PaliGemmaConfig(vision_config=vision.to_dict(), text_config=text.to_dict(), projection_dim=32)
    )
    model.save_pretrained(str(out))
    tok.save_pretrained(str(out))
    return out, model


def test_occvla_takes_a_paligemma_directory_for_its_vision_tower_and_llm(
    paligemma_dir, tmp_path, synth_dataset, tokenizer_export
):
    from occtrain.data.clips import Text
    from occtrain.families.occvla import TaskConfig as VLATasks
    from occtrain.families.occvla.parts import Images, Occupancy
    from occtrain.models.camera_encoder import DenseHead, MultiViewEncoder, VisionConfig, export_vision

    path, original = paligemma_dir
    encoder = MultiViewEncoder(VisionConfig(path=str(path)))
    torch.testing.assert_close(
        encoder.tower.state_dict()["embeddings.patch_embedding.weight"],
        original.state_dict()["model.vision_tower.embeddings.patch_embedding.weight"],
    )
    vision = export_vision(tmp_path / "vision", encoder, DenseHead(encoder.hidden_size, encoder.patch_size))
    llm = LLMConfig(path=str(path), action_bins=16)
    engine = new_world_model(
        {"tokenizer": tokenizer_export, "vision": vision},
        llm,
        VLATasks(weights={"qa": 1.0}),
        synth_dataset,
        family="occvla",
    )
    assert engine.world.llm.config.model_type == "gemma2"
    # The language model's own weights came along (the rows of the joint tokens are new).
    text_rows = engine.vocab.text_size
    torch.testing.assert_close(
        engine.world.llm.get_input_embeddings().weight[:text_rows], original.get_input_embeddings().weight[:text_rows]
    )
    engine.prepare_inputs(synth_dataset)
    token = next(iter(engine.data_index.samples()))[1]
    seq = engine.encode_parts(
        [Images(token), Occupancy(token, 1.0), Text("describe the scene"), Text("a car", True)], {}
    )
    out = engine.world(collate([seq], engine.vocab.pad_id))
    assert torch.isfinite(out.loss) and out.scene_loss > 0
    prompt = engine.encode_parts([Images(token), Text("describe the scene")], {})
    text, voxels = engine.world.eval().generate_with_occupancy(
        prompt, [TextAnswer(3, stop_at_eos=False)], occupancy=True
    )
    assert len(text[0]) == 3 and voxels.shape[1] == 18

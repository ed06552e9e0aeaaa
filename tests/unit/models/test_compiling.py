"""``trainer.compile``: compiled training forwards, eager evaluation, the same losses."""

from __future__ import annotations

import copy

import torch
from transformers import LlamaConfig, LlamaForCausalLM

from occtrain.config.llm import LoRAConfig
from occtrain.models.compiling import compile_all, compile_for_training, decoder_layers, is_compiled
from occtrain.models.llm import apply_lora


def tiny_llama(seed: int = 0) -> LlamaForCausalLM:
    torch.manual_seed(seed)
    cfg = LlamaConfig(
        vocab_size=64,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        num_key_value_heads=2,
        attn_implementation="sdpa",
    )
    return LlamaForCausalLM(cfg)


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


def test_compiled_training_steps_give_the_eager_losses_on_cpu():
    # Inductor on the CPU: the same three AdamW steps compiled and eager, under the 4D
    # boolean mask and explicit positions the world models train with.
    eager = tiny_llama()
    compiled = copy.deepcopy(eager)
    for layer in decoder_layers(compiled):
        assert compile_for_training(layer) and is_compiled(layer)
    ids = torch.randint(0, 64, (2, 12), generator=torch.Generator().manual_seed(1))
    mask = torch.ones(2, 1, 12, 12, dtype=torch.bool).tril()
    positions = torch.arange(12).expand(2, 12)

    def losses(model: LlamaForCausalLM) -> list[float]:
        opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
        out = []
        for _ in range(3):
            loss = model(input_ids=ids, attention_mask=mask, position_ids=positions, labels=ids).loss
            loss.backward()
            opt.step()
            opt.zero_grad()
            out.append(loss.item())
        return out

    want, got = losses(eager), losses(compiled)
    torch.testing.assert_close(torch.tensor(got), torch.tensor(want), rtol=1e-4, atol=1e-5)
    assert want[2] < want[0]  # the steps trained: equal losses are not equally stuck ones

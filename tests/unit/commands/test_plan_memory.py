"""`occtrain plan-memory`: exact counts on the meta device, memory terms on hand cases, the
activation estimate against what autograd actually keeps, and the papers' models."""

from __future__ import annotations

import pytest
import torch
from transformers import AutoModelForCausalLM

from conftest import REPO
from occtrain.cli import main
from occtrain.commands.plan_memory import (
    MAX_GPU_GIB,
    MAX_SEQ_LEN,
    ModelCount,
    activation_bytes,
    check_flags,
    count_llm,
    plan,
)
from occtrain.config.llm import LLMConfig, LoRAConfig, check_llm_sizes
from occtrain.errors import ConfigError
from occtrain.models.adapters import AdapterConfig, add_adapters
from occtrain.models.llm import apply_lora, build_llm, tiny_config

TINY = LLMConfig(hidden_size=64, num_layers=2, num_heads=4, intermediate_size=172, text_vocab_size=300)


def _hand_model() -> ModelCount:
    return ModelCount(
        name="hand",
        params=1000,
        trainable=100,
        frozen_beside=0,
        layers=2,
        hidden=4,
        kv_hidden=4,
        intermediate=8,
        heads=2,
        vocab=10,
        layer_params=50,
        attention="sdpa",
    )


def test_memory_terms_on_a_hand_case():
    m = _hand_model()
    # fp32: per token per layer 8*4 + 2*4 + 4*8 = 72 elements; logits 10 + 10 floats.
    ddp, sharded = plan(m, "32-true", batch=1, seq=3, gpus=2, checkpointing=False)
    assert (ddp.weights, ddp.gradients, ddp.optimizer, ddp.extra) == (4000, 400, 800, 400)
    assert ddp.activations == 3 * (2 * 72 * 4 + 80)
    assert ddp.total == 4000 + 400 + 800 + 400 + 1968
    # Sharded: the states split over 2 ranks, two whole layers gathered.
    assert (sharded.weights, sharded.gradients, sharded.optimizer, sharded.extra) == (2000, 200, 400, 2 * 50 * 4)
    assert sharded.activations == ddp.activations
    # bf16-mixed: fp32 states, autocast's 16-bit weight copy, 16-bit activations, float logits.
    ddp, sharded = plan(m, "bf16-mixed", batch=1, seq=3, gpus=2, checkpointing=False)
    assert (ddp.weights, ddp.extra, ddp.activations) == (4000, 400 + 2000, 3 * (2 * 72 * 2 + 10 * 2 + 40 + 40))
    assert sharded.extra == 2 * 50 * 2
    # Checkpointing keeps each layer's input and one layer's activations.
    ddp, _ = plan(m, "32-true", batch=1, seq=3, gpus=2, checkpointing=True)
    assert ddp.activations == 3 * ((2 * 4 + 72) * 4 + 80)
    assert not ddp.fits(0.000001) and ddp.fits(1)
    with pytest.raises(ConfigError, match="trainer.precision: 'fp8' is not one plan-memory knows"):
        plan(m, "fp8", 1, 3, 2, False)


def test_counts_on_the_meta_device_equal_the_built_model():
    extra = 40
    built = build_llm(TINY, TINY.text_vocab_size + extra)
    full = count_llm(TINY, extra)
    assert full.params == full.trainable == sum(p.numel() for p in built.parameters())
    assert full.layer_params == sum(p.numel() for p in built.model.layers[0].parameters())
    lora_cfg = LoRAConfig(r=8, alpha=16, target_modules=["q_proj", "v_proj"])
    built.requires_grad_(False)
    wrapped = apply_lora(built, lora_cfg)
    lora = count_llm(TINY, extra, lora=lora_cfg)
    assert (lora.params, lora.trainable) == (
        sum(p.numel() for p in wrapped.parameters()),
        sum(p.numel() for p in wrapped.parameters() if p.requires_grad),
    )
    plain = build_llm(TINY, TINY.text_vocab_size + extra).requires_grad_(False)
    adapters = add_adapters(plain, AdapterConfig(reduction_factor=4))
    counted = count_llm(TINY, extra, adapter=AdapterConfig(reduction_factor=4))
    assert counted.trainable == sum(p.numel() for a in adapters for p in a.parameters()) > 0
    assert count_llm(TINY, extra, freeze=("llm.",)).trainable == 0
    assert count_llm(TINY, extra, freeze=("llm.model.layers.1.",)).trainable == full.params - full.layer_params


def test_the_activation_estimate_is_within_ten_percent_of_what_autograd_keeps():
    """Every tensor saved for backward in one forward of a tiny Llama, plus the logits its
    output holds, against ``activation_bytes`` (fp32, SDPA)."""
    torch.manual_seed(0)
    cfg = LLMConfig(hidden_size=128, num_layers=3, num_heads=4, intermediate_size=344, text_vocab_size=700)
    model = AutoModelForCausalLM.from_config(tiny_config(cfg, cfg.text_vocab_size))
    weights = {p.data_ptr() for p in model.parameters()}
    kept: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        if t.data_ptr() not in weights:
            kept.setdefault(t.data_ptr(), t.untyped_storage().nbytes())
        return t

    ids = torch.randint(0, cfg.text_vocab_size, (2, 256))
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = model(input_ids=ids, labels=ids)
    kept.setdefault(out.logits.data_ptr(), out.logits.untyped_storage().nbytes())
    measured = sum(kept.values())
    estimate = activation_bytes(count_llm(cfg, 0), 2, 256, 4, False)
    assert 0.9 < estimate / measured < 1.1, (estimate, measured)


def test_plan_memory_plans_the_papers_models(capsys):
    assert (
        main(
            ["plan-memory", str(REPO / "recipes/scale/sparseoccvla_vicuna7b.yaml"), "--gpus", "8", "--gpu-memory", "96"]
        )
        == 0
    )
    out = capsys.readouterr().out
    # Vicuna-7B's 6.738 B and the joint vocabulary's 2 x 256 action-bin rows (in and out).
    assert "stage2 (pretrain): vicuna-7b, 6.743 B parameters, 0.00 M trainable" in out
    assert "stage3 (instruct): vicuna-7b, 7.062 B parameters, 319.82 M trainable" in out
    assert out.count("sharded x8") == 2 and "bf16-mixed" in out and "yes (96 GiB)" in out


def test_plan_memory_refuses_bad_input_in_one_line(tmp_path, capsys):
    recipe = REPO / "recipes/scale/sparseoccvla_vicuna7b.yaml"
    assert main(["plan-memory", str(recipe), "--gpus", "0"]) == 2
    assert (
        capsys.readouterr().err.strip()
        == "error: --gpus 0: plan at least 1 GPU (the ranks a sharded model is split over)"
    )
    assert main(["plan-memory", str(recipe), f"stages.stage2.model.llm.path={tmp_path}"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err == f"error: stages.stage2.model.llm.path: {tmp_path} has no config.json; "
        "plan-memory reads a model's config.json (weights not needed)"
    )
    assert main(["plan-memory", str(REPO / "recipes/vision.yaml")]) == 2
    assert "has no pretrain, instruct or distill stage" in capsys.readouterr().err


def test_run_and_plan_memory_refuse_the_same_llm_sizes():
    """The size checks live in ``validate_llm_config``: building the model for ``run``
    refuses what plan-memory refuses, in the same words."""
    bad = LLMConfig(hidden_size=128, num_heads=3)
    for refuse in (lambda: build_llm(bad, 100), lambda: count_llm(bad, 0)):
        with pytest.raises(
            ConfigError,
            match=r"^llm.num_heads is 3, which does not divide hidden_size 128; "
            r"set num_heads to a divisor of 128 \(e.g. 4\)",
        ):
            refuse()
    with pytest.raises(ConfigError, match=r"^s.model.llm.text_vocab_size is 0; it sizes the model's tensors"):
        count_llm(LLMConfig(text_vocab_size=0), 0, key="s.model.llm")
    # With a path the size keys are not read, so they are not checked either.
    count_llm(LLMConfig(path=str(REPO / "configs/llm/vicuna-7b"), hidden_size=-1), 0)


def test_llm_sizes_are_checked_by_the_names_written():
    check_llm_sizes({"hidden_size": 96, "num_heads": 4}, "x.", "hidden_size", "num_heads")
    for sizes, says in [
        ({"hidden_size": True}, "x.hidden_size is True;"),
        ({"hidden_size": 4.0}, "x.hidden_size is 4.0;"),
        ({"vocab_size": None}, "x.vocab_size is None;"),
        (
            {"hidden_size": 2304, "heads": 8, "kv": 3},
            "x.kv is 3, which does not divide heads 8; set kv to a divisor of 8 (e.g. 4) or heads to a multiple of 3",
        ),
    ]:
        with pytest.raises(ConfigError) as e:
            check_llm_sizes(sizes, "x.", "hidden_size", "heads", "kv")
        assert str(e.value).startswith(says), str(e.value)


def test_flags_take_their_whole_range_and_no_more():
    check_flags(1, 1, None)
    check_flags(8, MAX_SEQ_LEN, MAX_GPU_GIB)
    for gpus, seq, gib, says in [
        (
            1,
            MAX_SEQ_LEN + 1,
            None,
            f"--seq-len {MAX_SEQ_LEN + 1}: tokens per training sequence must be in 1..4194304 (2**22)",
        ),
        (1, 2048, 0.0, "--gpu-memory 0: a GPU's memory in GiB must be above 0"),
        (1, 2048, float("inf"), "--gpu-memory inf:"),
        (-2, 2048, None, "--gpus -2: plan at least 1 GPU"),
    ]:
        with pytest.raises(ConfigError) as e:
            check_flags(gpus, seq, gib)
        assert str(e.value).startswith(says), str(e.value)


def test_a_config_json_with_head_dim_may_have_heads_that_do_not_divide_hidden(tmp_path):
    """Qwen2 sizes q/k/v as heads x head_dim when head_dim is given: 100 wide, 3 heads of 32."""
    (tmp_path / "config.json").write_text(
        '{"model_type": "qwen2", "hidden_size": 100, "num_attention_heads": 3, "num_key_value_heads": 3, "head_dim": '
        "32, "
        '"num_hidden_layers": 1, "intermediate_size": 64, "vocab_size": 50}'
    )
    assert count_llm(LLMConfig(path=str(tmp_path)), 0).kv_hidden == 96


def test_an_override_beside_llm_path_is_refused_in_every_stage_form(capsys):
    recipe = str(REPO / "recipes/scale/occllama_llama8b.yaml")
    for key in (
        "stages.pretrain.model.llm.hidden_size",
        "stages.1.model.llm.hidden_size",
        "stages[1].model.llm.hidden_size",
    ):
        assert main(["plan-memory", recipe, f"{key}=8192"]) == 2
        err = capsys.readouterr().err
        assert err == (
            f"error: {key}: ignored, since stages.pretrain.model.llm.path is set (configs/llm/llama-3.1-8b) and its "
            "config.json "
            "decides the model; drop the override to plan that model, or point stages.pretrain.model.llm.path at a "
            "config.json "
            "with the sizes you want\n"
        )
    # A key the path leaves to the recipe still plans.
    assert main(["plan-memory", recipe, "stages.pretrain.model.llm.action_bins=128"]) == 0

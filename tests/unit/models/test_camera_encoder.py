"""The camera encoder: tiny SigLIP from config or a local HF directory, the dense pretraining
stage with its per-pixel prior baseline, pixel metrics by hand, export -> load."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from safetensors.torch import load_file, save_file
from transformers import LlamaConfig, SiglipVisionConfig, SiglipVisionModel

from occtrain.config.groups import DataConfig, TrainerConfig
from occtrain.config.recipe import OptimConfig, StageSpec
from occtrain.errors import ConfigError, DataError
from occtrain.formats.occ3d import FREE
from occtrain.metrics import DepthAbsRelMetric, PixelSegmentationMetric
from occtrain.models.camera_encoder import (
    DenseHead,
    MultiViewEncoder,
    VisionConfig,
    build_vision_tower,
    load_dense_head,
    load_vision_encoder,
)
from occtrain.stages import get_kind
from occtrain.stages.stage import Stage, StageContext
from occtrain.stages.vision import VisionModelConfig, VisionStage

H, W, N = 72, 128, 6
#: Class -> RGB of the fake renderer: the class is readable from a pixel's colour.
PALETTE = {FREE: (200, 220, 255), 11: (60, 60, 60), 4: (220, 30, 30), 15: (150, 120, 90)}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny models on one thread: on a busy 2-core machine, OpenMP threads of these small
    ops spin against other processes (20 steps took 32 s on 2 threads, 1.1 s on one)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def fake_batch(batch_size: int = 2, seed: int = 0) -> dict:
    """A frames batch of the camera contract: sky above a horizon, road below, a car and a
    building at random places; depth grows towards the horizon, 0 in the sky."""
    g = torch.Generator().manual_seed(seed)
    cls = torch.full((batch_size, N, H, W), 11, dtype=torch.uint8)
    horizon = 30
    cls[:, :, :horizon] = FREE
    for b in range(batch_size):
        for c in range(N):
            x0 = int(torch.randint(0, W - 40, (1,), generator=g))
            cls[b, c, horizon - 10 : horizon + 12, x0 : x0 + 24] = 15
            x1 = int(torch.randint(0, W - 30, (1,), generator=g))
            cls[b, c, horizon + 15 : horizon + 35, x1 : x1 + 30] = 4
    rows = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    depth = (400.0 / (rows - horizon + 8).clamp(min=1)).expand(batch_size, N, H, W).clone()
    depth[cls == FREE] = 0.0
    images = torch.zeros(batch_size, N, H, W, 3, dtype=torch.uint8)
    for k, rgb in PALETTE.items():
        images[cls == k] = torch.tensor(rgb, dtype=torch.uint8)
    noise = torch.randint(-10, 11, images.shape, generator=g)
    images = (images.int() + noise).clamp(0, 255).to(torch.uint8)
    return {
        "images": images,
        "cam_class": cls,
        "cam_depth": depth.float(),
        "intrinsics": torch.eye(3).expand(batch_size, N, 3, 3).clone(),
        "cam_to_ego": torch.eye(4).expand(batch_size, N, 4, 4).clone(),
        "semantics": torch.full((batch_size, 200, 200, 16), FREE, dtype=torch.uint8),
        "mask_camera": torch.ones(batch_size, 200, 200, 16, dtype=torch.bool),
        "token": [f"t{i}" for i in range(batch_size)],
        "meta": [{} for _ in range(batch_size)],
    }


def make_stage(tmp_path: Path, lr: float = 3e-3, **model: object) -> VisionStage:
    torch.manual_seed(0)
    cfg = OmegaConf.structured(VisionModelConfig(**model))
    spec = StageSpec(name="vision", kind="vision", optim=OptimConfig(lr=lr, weight_decay=0.0, schedule="constant"))
    return VisionStage(StageContext(spec, cfg, DataConfig(), TrainerConfig(max_steps=20), tmp_path, {}))


# ----------------------------------------------------------------------------- encoder


def test_tiny_encoder_from_config_shapes_and_camera_embedding():
    torch.manual_seed(0)
    enc = MultiViewEncoder(VisionConfig()).eval()
    assert type(enc.tower).__name__ == "SiglipVisionModel" and enc.grid == (9, 16)
    c = enc.tower.config
    assert (c.hidden_size, c.num_hidden_layers, c.num_attention_heads, c.patch_size) == (64, 2, 2, 8)
    one = fake_batch(1)["images"][:, :1]
    same = one.expand(2, N, H, W, 3).contiguous()  # the same picture in every camera
    with torch.no_grad():
        tokens, grid = enc(same)
    assert tokens.shape == (2, N * 144, 64) and grid == (9, 16)
    per_cam = tokens.view(2, N, 144, 64)
    diff = per_cam - per_cam[:, :1]
    assert torch.allclose(diff, (enc.camera_embed - enc.camera_embed[:1])[None, :, None].expand_as(diff), atol=1e-5)
    assert diff[:, 1:].abs().amax() > 0  # cameras are told apart only by their embedding
    with pytest.raises(DataError, match=r"^images: expected uint8 \(B, 6, 72, 128, 3\)"):
        enc(torch.zeros(1, 5, H, W, 3, dtype=torch.uint8))


def test_non_multiple_image_size_is_resized_to_the_patch_grid():
    head = DenseHead(64, 8)
    enc = MultiViewEncoder(VisionConfig(image_height=70, image_width=100, num_cameras=2))
    assert enc.input_hw == (72, 104) and enc.grid == (9, 13)
    tokens, grid = enc(torch.zeros(1, 2, 70, 100, 3, dtype=torch.uint8))
    logits, log_depth = head(tokens, grid, 2, (70, 100))
    assert logits.shape == (1, 2, 18, 70, 100) and log_depth.shape == (1, 2, 70, 100)


@pytest.fixture()
def saved_siglip(tmp_path) -> tuple[Path, SiglipVisionModel]:
    """A tiny 'pretrained' SigLIP vision model, with its pooling head, saved as a user would."""
    torch.manual_seed(1)
    cfg = SiglipVisionConfig(
        hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=64, patch_size=16
    )
    model = SiglipVisionModel(cfg).eval()
    model.save_pretrained(str(tmp_path / "siglip"))
    return tmp_path / "siglip", model


def test_encoder_from_a_local_hf_directory(saved_siglip):
    path, original = saved_siglip
    enc = MultiViewEncoder(VisionConfig(path=str(path), hidden_size=999)).eval()  # size keys are ignored
    assert (enc.hidden_size, enc.patch_size, enc.grid) == (32, 16, (5, 8))  # 72 -> 80 rows: resized up
    for (name, p), q in zip(enc.tower.named_parameters(), original.parameters()):
        assert torch.equal(p, q), name
    # The pooling head never reaches the patch tokens: frozen, so DDP does not wait on it.
    frozen = {n for n, p in enc.tower.named_parameters() if not p.requires_grad}
    assert frozen and all(n.startswith("head.") for n in frozen)
    tokens, grid = enc(fake_batch(1)["images"])
    assert tokens.shape == (1, N * 40, 32) and grid == (5, 8)


def test_bad_vision_path_is_a_one_line_config_error(tmp_path, saved_siglip):
    with pytest.raises(ConfigError, match=r"^vision\.path: .*no config\.json") as e:
        build_vision_tower(VisionConfig(path=str(tmp_path / "missing")))
    assert "\n" not in str(e.value) and "missing" in str(e.value)
    LlamaConfig(
        vocab_size=10, hidden_size=8, intermediate_size=16, num_hidden_layers=1, num_attention_heads=2
    ).save_pretrained(str(tmp_path))
    with pytest.raises(ConfigError, match=r"^vision\.path: .* holds a 'llama' model, not a vision tower") as e:
        build_vision_tower(VisionConfig(path=str(tmp_path)))
    assert "\n" not in str(e.value)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match=r"^vision\.path: cannot read"):
        build_vision_tower(VisionConfig(path=str(tmp_path)))
    path, _ = saved_siglip  # a tower whose weights lack a tensor would silently start it random
    weights = load_file(str(path / "model.safetensors"))
    save_file(
        {k: v for k, v in weights.items() if k != "post_layernorm.weight"},
        str(path / "model.safetensors"),
        metadata={"format": "pt"},
    )
    with pytest.raises(
        ConfigError,
        match=r"^vision\.path: the weights in .* do not match its config\.json "
        r"\(missing tensor 'post_layernorm\.weight'\)",
    ):
        build_vision_tower(VisionConfig(path=str(path)))
    with pytest.raises(ConfigError, match=r"^vision\.hidden_size: 63 is not divisible"):
        build_vision_tower(VisionConfig(hidden_size=63))


# ----------------------------------------------------------------------------- metrics


def test_pixel_metrics_by_hand():
    seg = PixelSegmentationMetric()
    target = torch.tensor([[4, 4, 11, FREE]])
    pred = torch.tensor([[4, 11, 11, 0]])
    seg.update(pred, target)
    out = seg.compute()
    # car 1/2, road 1/2, free 0/1; class 0 is only predicted: no term of its own.
    assert set(out["per_class"]) == {"car", "driveable_surface", "free"}
    assert float(out["per_class"]["car"]) == pytest.approx(50.0)
    assert float(out["mIoU"]) == pytest.approx(100 / 3)
    absrel = DepthAbsRelMetric()
    absrel.update(torch.tensor([2.0, 5.0, 9.0]), torch.tensor([4.0, 5.0, 0.0]))  # the 0 has no depth
    absrel.update(torch.tensor([3.0]), torch.tensor([2.0]))
    assert float(absrel.compute()) == pytest.approx((0.5 + 0.0 + 0.5) / 3)


# ----------------------------------------------------------------------------- stage


def test_stage_trains_validates_against_the_prior_and_exports(tmp_path):
    kind = get_kind("vision")
    assert (
        kind.module is VisionStage
        and kind.data_kind == "frames"
        and kind.monitor == "val/pixel_mIoU"
        and kind.mode == "max"
    )
    assert VisionStage.reads_cameras and not Stage.reads_cameras
    stage = make_stage(tmp_path)
    batch = fake_batch(2)
    opt = stage.configure_optimizers()["optimizer"]
    stage.train()
    losses = []
    for _ in range(20):
        opt.zero_grad()
        loss, _, _ = stage.losses(batch)
        loss["loss"].backward()
        opt.step()
        losses.append(loss["loss"].item())
    assert losses[-1] < 0.5 * losses[0], losses

    stage.fit_prior([fake_batch(2, seed=s) for s in range(3)])
    stage.eval()
    with torch.no_grad():
        stage.validation_step(fake_batch(2, seed=7), 0)
        stage.validation_step(fake_batch(1, seed=8), 1)
    m = stage.validation_results()
    for key in (
        "val/loss",
        "val/pixel_mIoU",
        "val/depth_absrel",
        "val/baseline_prior_pixel_mIoU",
        "val/baseline_prior_depth_absrel",
    ):
        assert key in m and m[key] == m[key], key  # present, not NaN
    assert {k for k in m if k.startswith("val/pixel_IoU_")} == {
        f"val/pixel_IoU_{c}" for c in ("car", "manmade", "driveable_surface", "free")
    }
    assert m["val/baseline_prior_pixel_mIoU"] < 100 and m["val/baseline_prior_depth_absrel"] < 0.5
    assert stage.report().metrics["params"] > 0

    export = stage.export(tmp_path / "export")
    assert json.loads((export / "vision" / "config.json").read_text())["model_type"] == "siglip_vision_model"
    assert (export / "vision" / "model.safetensors").is_file() and (
        export / "vision" / "preprocessor_config.json"
    ).is_file()
    images = fake_batch(2, seed=9)["images"]
    with torch.no_grad():
        want, _ = stage.encoder(images)
        got, _ = load_vision_encoder(export)(images)
        want_logits = stage(images)[0]
        tokens, grid = stage.encoder(images)
        got_logits = load_dense_head(export)(tokens, grid, N, (H, W))[0]
    assert torch.equal(got, want) and torch.equal(got_logits, want_logits)
    # The tower directory is plain transformers.
    plain = SiglipVisionModel.from_pretrained(str(export / "vision")).eval()
    x = stage.encoder.pixel_values(images)
    with torch.no_grad():
        assert torch.equal(
            plain(pixel_values=x, interpolate_pos_encoding=True).last_hidden_state,
            stage.encoder.tower(pixel_values=x, interpolate_pos_encoding=True).last_hidden_state,
        )
    frozen = load_vision_encoder(export)
    assert not any(p.requires_grad for p in frozen.parameters()) and not frozen.training
    assert all(p.requires_grad for p in load_vision_encoder(export, trainable=True).parameters())


def test_frozen_tower_trains_only_the_embedding_and_head(tmp_path, saved_siglip):
    path, _ = saved_siglip
    stage = make_stage(tmp_path, freeze_tower=True, vision=VisionConfig(path=str(path)))
    trainable = {n for n, p in stage.named_parameters() if p.requires_grad}
    assert trainable == {"encoder.camera_embed", "head.proj.weight", "head.proj.bias"}
    assert not any(k.startswith("encoder.tower.") for k in stage.state_dict())  # checkpoints leave it out
    with pytest.raises(DataError, match=r"frames carry no images, cam_class, cam_depth"):
        stage.losses({"semantics": torch.zeros(1, 200, 200, 16, dtype=torch.uint8)})
    with pytest.raises(ConfigError, match=r"model\.prior_batches"):
        make_stage(tmp_path, prior_batches=-1)


def test_the_tower_checkpointed_gives_the_same_gradients():
    """The vision stage's model.gradient_checkpointing on the tiny SigLIP tower."""
    from occtrain.models.camera_encoder import VisionConfig, build_vision_tower
    from occtrain.models.llm import checkpoint_layers

    grads = []
    for checkpointing in (False, True):
        torch.manual_seed(0)
        tower = build_vision_tower(VisionConfig()).train()
        if checkpointing:
            checkpoint_layers(tower)
        images = torch.randn(2, 3, 72, 128, generator=torch.Generator().manual_seed(1))
        tower(pixel_values=images, interpolate_pos_encoding=True).last_hidden_state.square().mean().backward()
        grads.append({n: p.grad for n, p in tower.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 5
    assert all(torch.allclose(g, grads[1][n], atol=1e-6) for n, g in grads[0].items())
    assert any(getattr(m, "gradient_checkpointing", False) is True for m in tower.modules())

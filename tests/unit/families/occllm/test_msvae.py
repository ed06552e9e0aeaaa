"""Occ-LLM's Motion-Separation VAE: separation and merge on a hand-made grid, the model's
two codebooks, its ablation switches, and training it through the tokenizer stage."""

from __future__ import annotations

import json

import pytest
import torch

from occtrain.core.tokenizer_exports import build_tokenizer, tokenizer_config
from occtrain.errors import ConfigError
from occtrain.families.occllm import MSVAE, merge, separate
from occtrain.formats.occ3d import CLASS_INDEX, FREE, GRID_SHAPE, NUM_CLASSES
from occtrain.models import count_parameters

TINY = dict(
    num_codes=16,
    num_codes_motion=8,
    code_dim=8,
    class_embed_dim=4,
    base_channels=8,
    channel_mult=[1, 1, 1],
    strides=[4, 5],
    num_res_blocks=1,
    latent_attention=False,
    z_channels=8,
)
ROAD, CAR, MANMADE = CLASS_INDEX["driveable_surface"], CLASS_INDEX["car"], CLASS_INDEX["manmade"]


def _road_with_a_car() -> torch.Tensor:
    """A road under the whole grid, a building at one side and a car on the road."""
    sem = torch.full(GRID_SHAPE, FREE, dtype=torch.long)
    sem[..., :2] = ROAD
    sem[:, 180:, 2:10] = MANMADE
    sem[100:110, 95:100, 2:6] = CAR
    return sem[None]


def test_separation_keeps_each_side_and_frees_the_other():
    sem = _road_with_a_car()
    movable = torch.zeros(NUM_CLASSES, dtype=torch.bool)
    movable[CAR] = True
    moving, static = separate(sem, movable)
    assert set(moving.unique().tolist()) == {CAR, FREE} and (moving == CAR).sum() == (sem == CAR).sum()
    assert CAR not in static.unique().tolist() and (static == ROAD).sum() == (sem == ROAD).sum()
    assert (static[0, 100:110, 95:100, 2:6] == FREE).all()  # where the car was, free in the static grid

    def logits(grid):  # perfect branch predictions
        return torch.nn.functional.one_hot(grid, NUM_CLASSES).permute(0, 4, 1, 2, 3).float()

    assert torch.equal(merge(logits(moving), logits(static)).argmax(1), sem)
    # Eq. 7: the motion branch wins only where it predicts non-free.
    wrong_static = static.clone()
    wrong_static[0, 100:110, 95:100, 2:6] = MANMADE
    assert torch.equal(merge(logits(moving), logits(wrong_static)).argmax(1), sem)


def test_the_model_has_two_codebooks_and_says_how_each_is_used():
    torch.manual_seed(0)
    model = build_tokenizer("occllm_msvae", TINY)
    out = model(_road_with_a_car())
    assert out.logits.shape == (1, NUM_CLASSES, *GRID_SHAPE)
    assert out.codes.shape == (1, 2, 10, 10) and model.num_codebooks == 2
    assert int(out.codes[:, 0].max()) < 8 and int(out.codes[:, 1].max()) < 16
    assert {"ce_motion", "ce_static", "vq_motion", "vq_static"} <= set(out.losses)
    assert any(k.startswith("motion_") for k in out.stats) and any(k.startswith("static_") for k in out.stats)
    out.losses["loss"].backward()
    assert model.quantizer_motion.embed.grad is not None and model.pre3d.weight.grad is not None
    model.eval()
    with torch.no_grad():
        codes = model.encode(_road_with_a_car())
        assert torch.equal(codes, model(_road_with_a_car()).codes)
        assert torch.equal(model.decode(codes).argmax(1), model(_road_with_a_car()).logits.argmax(1))


def test_the_ablation_switches():
    one = build_tokenizer("occllm_msvae", {**TINY, "motion_separation": False, "conv3d": False})
    conv = build_tokenizer("occllm_msvae", {**TINY, "motion_separation": False})
    both = build_tokenizer("occllm_msvae", TINY)
    e = TINY["class_embed_dim"]
    assert count_parameters(conv) - count_parameters(one) == 2 * (e * e * 27 + e)  # two light 3D convolutions
    assert count_parameters(both) - count_parameters(conv) == 8 * TINY["code_dim"]  # the motion codebook
    assert one.num_codebooks == 1 and one.encode(_road_with_a_car()).shape == (1, 10, 10)
    with pytest.raises(ConfigError, match=r"movable_classes: 'lorry' is not an Occ3D class"):
        tokenizer_config("occllm_msvae", {**TINY, "movable_classes": ["car", "lorry"]}, "model.occllm_msvae")


def test_the_tokenizer_stage_trains_it_and_reports_each_codebook(tmp_path, hand_dataset):
    from occtrain.core.tokenizer_exports import load_tokenizer
    from occtrain.run.runner import run

    recipe = tmp_path / "msvae.yaml"
    recipe.write_text(f"""
name: msvae
runs_root: {tmp_path / "runs"}
data: {{root: {hand_dataset}, batch_size: 1, samples_per_shard: 4, history: 1, future: 1}}
trainer: {{max_steps: 2, val_check_interval: 2, limit_val_batches: 1, log_every_n_steps: 1}}
stages:
  - name: tokenizer
    kind: tokenizer
    model: {{arch: occllm_msvae, occllm_msvae: {json.dumps(TINY)}}}
""")
    run(recipe)
    stage = tmp_path / "runs" / "msvae" / "tokenizer"
    metrics = json.loads((stage / "metrics.json").read_text())
    assert "val/occworld_mIoU" in metrics
    # Usage over the val split, per codebook: a percentage of its codes, and a perplexity
    # no larger than the codebook.
    for name, size in (("motion", 8), ("static", 16)):
        assert 0 < metrics[f"val/{name}_usage"] <= 100 and 1 <= metrics[f"val/{name}_perplexity"] <= size
    log = (stage / "logs" / "csv" / "metrics.csv").read_text().splitlines()[0]
    assert "train/motion_perplexity" in log and "train/static_perplexity" in log
    assert isinstance(load_tokenizer(stage / "export"), MSVAE)
    page = (tmp_path / "runs" / "msvae" / "dashboard.html").read_text()
    assert "codebook perplexity per train batch" in page


# ----------------------------------------------------------------------------- patches and pre-fusion


@pytest.mark.parametrize("patch", [1, 5, 10, 25])
def test_patchify_round_trips_and_orders_cells_within_a_patch(patch):
    from occtrain.models.patches import patchify, unpatchify

    latents = torch.randn(2, 3, 50, 50)
    tokens = patchify(latents, patch)
    assert tokens.shape == (2, (50 // patch) ** 2, patch * patch * 3)
    assert torch.equal(unpatchify(tokens, patch, (50, 50)), latents)
    # Token 1 is the second patch of the first row; its first cell is latent cell (0, patch).
    if patch < 50:
        assert torch.equal(tokens[0, 1, :3], latents[0, :, 0, patch])


def test_a_patch_size_must_divide_the_grid():
    from occtrain.models.patches import patchify

    with pytest.raises(ConfigError, match="patch size 7 must divide the latent grid 50 x 50"):
        patchify(torch.zeros(1, 1, 50, 50), 7)


def test_the_patch_head_scores_every_cell_in_each_codebook():
    from occtrain.core.patch_layout import PatchEmbedding, PatchHead
    from occtrain.models.patches import patchify

    latents = torch.randn(2, 4, 10, 10)
    tokens = PatchEmbedding(4, 5, 32)(patchify(latents, 5))
    assert tokens.shape == (2, 4, 32)
    motion, static = PatchHead(32, 5, [8, 16])(tokens)
    assert motion.shape == (2, 4, 25, 8) and static.shape == (2, 4, 25, 16)


def test_pre_fusion_starts_as_the_identity_and_learns_a_per_channel_gate():
    from occtrain.families.occllm.scene_tokens import PreFusion

    fuse = PreFusion(action_dim=2, channels=4)
    latents, action = torch.randn(3, 4, 10, 10), torch.randn(3, 2)
    assert torch.equal(fuse(latents, action), latents)  # gate 1 before training
    loss = fuse(latents, action).pow(2).mean()
    loss.backward()
    assert fuse.mlp[-1].weight.grad.abs().sum() > 0  # the action reaches the gate
    with torch.no_grad():
        fuse.mlp[-1].bias.copy_(torch.tensor([10.0, -10.0, 0.0, 0.0]))
    gated = fuse(latents, action)
    assert torch.allclose(gated[:, 0], 2 * latents[:, 0], atol=1e-3) and torch.allclose(
        gated[:, 1], 0 * latents[:, 1], atol=1e-3
    )

"""Scene tokenizers: API shapes, published size, Eq. 8, Lovasz-softmax, quantizer mechanics, overfitting."""

from __future__ import annotations

import math

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from omegaconf import OmegaConf

from conftest import two_ranks
from occtrain.config.tokenizer import latent_hw
from occtrain.core.tokenizer_exports import build_tokenizer
from occtrain.errors import ConfigError, DataError
from occtrain.families.occllama import OccLLaMATokenizerConfig
from occtrain.families.occllama.scene_tokenizer import PillarEncoder, combine_decoupled, decoupled_labels
from occtrain.formats.occ3d import FREE, GRID_SHAPE, NUM_CLASSES
from occtrain.models import count_parameters
from occtrain.models.tokenizers.losses import lovasz_softmax
from occtrain.models.tokenizers.occworld_vqvae import OccWorldVQVAEConfig
from occtrain.models.tokenizers.quantizer import VectorQuantizer
from occtrain.models.tokenizers.swin import shifted_window_mask

TINY = {
    "occworld_vqvae": OccWorldVQVAEConfig(
        class_embed_dim=4, base_channels=8, channel_mult=[1, 1, 2], strides=[4, 5], num_res_blocks=1,
        z_channels=16, code_dim=8, num_codes=32,
    ),
    "occllama_tokenizer": OccLLaMATokenizerConfig(
        class_embed_dim=8, base_channels=8, channel_mult=[1, 2, 2], strides=[4, 5], num_res_blocks=1,
        swin_heads=2, code_dim=16, num_codes=32, voxel_feature_dim=4,
    ),
}  # fmt: skip
ARCHS = list(TINY)


def scene(batch: int = 1) -> torch.Tensor:
    """Ground everywhere, a car and a building block; the rest free."""
    sem = torch.full((batch, *GRID_SHAPE), FREE, dtype=torch.long)
    sem[..., 1] = 11
    sem[:, 40:60, 50:60, 2:5] = 4
    sem[:, 100:150, 0:30, 2:9] = 15
    return sem


# -- configs and construction


def test_default_occworld_matches_published_size():
    model = build_tokenizer("occworld_vqvae", OccWorldVQVAEConfig())
    assert abs(count_parameters(model) - 14.17e6) / 14.17e6 < 0.03
    assert model.latent_hw == (50, 50) and model.num_codes == 512


def test_default_occllama_config_is_the_papers():
    cfg = OccLLaMATokenizerConfig()
    assert (cfg.num_codes, cfg.code_dim, cfg.latent_hw) == (2048, 256, (50, 50))
    assert (cfg.lambda1, cfg.lambda2, cfg.lambda3) == (2.0, 2.0, 0.5)
    node = OmegaConf.merge(OmegaConf.structured(OccLLaMATokenizerConfig), OmegaConf.from_dotlist(["strides=[2,2,5,5]"]))
    assert latent_hw(node) == (2, 2)


def test_build_from_dictconfig_and_dict():
    node = OmegaConf.merge(OmegaConf.structured(OccWorldVQVAEConfig), OmegaConf.create(vars(TINY["occworld_vqvae"])))
    assert build_tokenizer("occworld_vqvae", node).latent_hw == (10, 10)
    assert build_tokenizer("occllama_tokenizer", {"strides": [4, 5], "window_size": 5}).latent_hw == (10, 10)


@pytest.mark.parametrize(
    "arch, override, key",
    [
        ("occworld_vqvae", {"strides": [3, 2]}, "strides"),
        ("occworld_vqvae", {"strides": [2, 2, 2]}, "channel_mult"),
        ("occllama_tokenizer", {"window_size": 3}, "window_size"),
        ("occllama_tokenizer", {"ema_decay": 1.0}, "ema_decay"),
    ],
)
def test_bad_configs_name_the_key(arch, override, key):
    with pytest.raises(ConfigError, match=rf"model\.{arch}\.{key}"):
        build_tokenizer(arch, override)


def test_unknown_arch_and_bad_input():
    with pytest.raises(ConfigError, match="occworld_vqvae"):
        build_tokenizer("occworld", {})
    model = build_tokenizer("occworld_vqvae", TINY["occworld_vqvae"])
    with pytest.raises(DataError, match="200, 200, 16"):
        model.encode(torch.zeros(1, 100, 100, 16, dtype=torch.long))


# -- API shapes and encode/decode consistency


@pytest.mark.parametrize("arch", ARCHS)
def test_api_shapes(arch):
    torch.manual_seed(0)
    model = build_tokenizer(arch, TINY[arch]).eval()
    sem = scene(batch=2)
    with torch.no_grad():
        out = model(sem)
    assert out.logits.shape == (2, NUM_CLASSES, *GRID_SHAPE) and out.logits.dtype == torch.float32
    assert out.codes.shape == (2, 10, 10) and out.codes.dtype == torch.long
    assert "loss" in out.losses and all(v.dim() == 0 for v in out.losses.values())
    assert len(out.losses) > 2
    assert set(out.stats) == {"codebook_usage", "perplexity"} and all(v.dim() == 0 for v in out.stats.values())
    assert model.codebook.shape == (32, TINY[arch].code_dim)
    assert model.num_codes == 32 and model.latent_hw == (10, 10)
    codes = model.encode(sem)
    assert codes.shape == (2, 10, 10) and int(codes.max()) < 32
    assert model.decode(codes).shape == (2, NUM_CLASSES, *GRID_SHAPE)


@pytest.mark.parametrize("arch", ARCHS)
def test_encode_decode_round_trip_equals_forward(arch):
    torch.manual_seed(1)
    model = build_tokenizer(arch, TINY[arch]).eval()
    sem = scene()
    with torch.no_grad():
        out = model(sem)
        codes = model.encode(sem)
        logits = model.decode(codes)
    assert torch.equal(codes, out.codes)
    # forward decodes z + (e - z), equal to e up to float rounding
    torch.testing.assert_close(logits, out.logits, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("arch", ARCHS)
def test_decode_labels_is_the_argmax_of_decode(arch):
    torch.manual_seed(2)
    model = build_tokenizer(arch, TINY[arch]).eval()
    codes = torch.randint(0, 32, (2, 10, 10))
    with torch.no_grad():
        labels = model.decode_labels(codes)
        assert torch.equal(labels, model.decode(codes).argmax(1))
    assert len(labels.unique()) > 1  # not all free: the semantics head was read somewhere


def test_occllama_training_forward_skips_the_combined_scores():
    model = build_tokenizer("occllama_tokenizer", TINY["occllama_tokenizer"]).train()
    out = model(scene())
    assert out.logits is None and out.losses["loss"].requires_grad


def test_decoupled_labels_break_ties_as_the_scores_argmax():
    # Voxel 0: random logits. Voxel 1: status tie (occupied wins, as in the scores) and
    # semantics 2 = 5 exactly. Voxel 2: class 0 one float below class 3; after the
    # log-softmax both round to the same score, so the scores' argmax is 0, not 3.
    torch.manual_seed(0)
    status, sem = torch.randn(1, 2, 3), torch.randn(1, 17, 3)
    status[0, :, 1] = 0.5
    sem[0, :, 1], sem[0, 2, 1], sem[0, 5, 1] = -1.0, 2.0, 2.0
    status[0, :, 2], sem[0, :, 2] = 0.0, 0.0
    sem[0, 3, 2], sem[0, 0, 2] = 0.25, torch.nextafter(torch.tensor(0.25), torch.tensor(0.0))
    expected = combine_decoupled(status, sem).argmax(1)
    assert expected[0, 1] == 2 and expected[0, 2] == 0 and sem.argmax(1)[0, 2] == 3
    assert torch.equal(decoupled_labels(status, sem), expected)


def test_encode_never_updates_the_codebook():
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(OccWorldVQVAEConfig), vars(TINY["occworld_vqvae"])))
    cfg.ema_decay, cfg.restart_threshold = 0.9, 0.5
    model = build_tokenizer("occworld_vqvae", cfg).train()
    before = model.codebook.clone(), model.quantizer.usage.clone()
    model.encode(scene())
    assert torch.equal(model.codebook, before[0]) and torch.equal(model.quantizer.usage, before[1])


# -- OccLLaMA's decoupled decoder and sparse encoder


def test_eq8_combination_by_hand():
    # Voxel 0: status says free (P_free = 0.75). Voxel 1: occupied (P_occ = 0.8), semantics 4 (0.5) > 11 (0.3).
    status = torch.tensor([[0.0, math.log(4.0)], [math.log(3.0), 0.0]]).view(1, 2, 2)
    sem_probs = torch.full((17, 2), 0.2 / 15)
    sem_probs[4], sem_probs[11] = 0.5, 0.3
    sem_probs[:, 0] = torch.softmax(torch.arange(17.0), 0)  # voxel 0: semantics would say class 16
    scores = combine_decoupled(status, sem_probs.log().unsqueeze(0))
    assert scores.shape == (1, NUM_CLASSES, 2)
    assert scores[0, :, 0].argmax() == FREE
    assert scores[0, :, 1].argmax() == 4
    torch.testing.assert_close(scores[0, FREE].exp(), torch.tensor([0.75, 0.2]))
    torch.testing.assert_close(scores[0, 4, 1].exp(), torch.tensor(0.8))
    torch.testing.assert_close(scores[0, 11, 1].exp(), torch.tensor(0.8 * 0.3 / 0.5))
    torch.testing.assert_close(scores[0, 16, 0].exp(), torch.tensor(0.25))


def test_pillar_encoder_pools_points_and_marks_empty_pillars():
    torch.manual_seed(0)
    enc = PillarEncoder(6)
    with torch.no_grad():
        enc.empty.fill_(7.0)
    sem = torch.full((1, 3, 2, GRID_SHAPE[2]), FREE)
    sem[0, 0, 0, 5] = 4
    sem[0, 2, 1, 2], sem[0, 2, 1, 9] = 11, 15
    out = enc(sem)
    point = lambda label, z: enc.point_mlp(enc.label_embed.weight[label] + enc.height_embed.weight[z])  # noqa: E731
    torch.testing.assert_close(out[0, :, 0, 0], point(4, 5))
    torch.testing.assert_close(out[0, :, 2, 1], torch.maximum(point(11, 2), point(15, 9)))
    assert torch.all(out[0, :, 1, 0] == 7.0)


def test_shifted_window_mask_by_hand():
    mask = shifted_window_mask(4, 4, window=2, shift=1)  # 4 windows of 4 tokens
    assert torch.all(mask[0] == 0)  # top-left window lies in one region
    last = mask[3]  # bottom-right window: four tokens from four different regions
    assert torch.all(torch.diagonal(last) == 0) and torch.isinf(last).sum() == 12


# -- Lovasz-softmax


def test_lovasz_of_hard_prediction_is_one_minus_iou():
    gen = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 3, (1, 40), generator=gen)  # class 3 never in the labels
    pred = torch.randint(0, 4, (1, 40), generator=gen)
    probs = torch.nn.functional.one_hot(pred, 4).permute(0, 2, 1).float()
    ious = []
    for c in sorted(set(labels.flatten().tolist())):
        gt = {i for i, v in enumerate(labels.flatten().tolist()) if v == c}
        pr = {i for i, v in enumerate(pred.flatten().tolist()) if v == c}
        ious.append(len(gt & pr) / len(gt | pr))
    expected = 1.0 - sum(ious) / len(ious)
    assert lovasz_softmax(probs, labels).item() == pytest.approx(expected, abs=1e-6)


def brute_force_lovasz(probs: list[list[float]], labels: list[int]) -> float:
    """Lovasz extension of the Jaccard loss, from the set function Delta(M) = |M| / |F_c u M|."""
    losses = []
    for c in sorted(set(labels)):
        fg = {i for i, y in enumerate(labels) if y == c}
        errors = [abs((y == c) - p[c]) for p, y in zip(probs, labels)]
        order = sorted(range(len(labels)), key=lambda i: -errors[i])

        def delta(m: set[int], fg: set[int] = fg) -> float:
            return len(m) / len(fg | m) if m else 0.0

        total, mistakes = 0.0, set()
        for i in order:
            before = delta(mistakes)
            mistakes = mistakes | {i}
            total += errors[i] * (delta(mistakes) - before)
        losses.append(total)
    return sum(losses) / len(losses)


def test_lovasz_of_soft_prediction_matches_brute_force():
    gen = torch.Generator().manual_seed(3)
    probs = torch.rand(1, 4, 12, generator=gen).softmax(1)
    labels = torch.randint(0, 4, (1, 12), generator=gen)
    valid = torch.rand(1, 12, generator=gen) > 0.3
    rows = probs[0].t().tolist()
    expected = brute_force_lovasz(rows, labels[0].tolist())
    assert lovasz_softmax(probs, labels).item() == pytest.approx(expected, abs=1e-6)
    keep = valid[0].tolist()
    expected_valid = brute_force_lovasz(
        [r for r, k in zip(rows, keep) if k], [y for y, k in zip(labels[0].tolist(), keep) if k]
    )
    assert lovasz_softmax(probs, labels, valid).item() == pytest.approx(expected_valid, abs=1e-6)


# -- quantizer


def set_codebook(vq: VectorQuantizer, vectors: list[list[float]]) -> None:
    with torch.no_grad():
        vq.embed.copy_(torch.tensor(vectors, dtype=torch.float32))
        if vq.ema_decay > 0:
            vq.ema_sum.copy_(vq.embed)


def as_latent(vectors: list[list[float]]) -> torch.Tensor:
    """N vectors of dimension D as a (1, D, 1, N) latent map."""
    return torch.tensor(vectors, dtype=torch.float32).t().reshape(1, -1, 1, len(vectors))


def test_quantizer_straight_through_and_codebook_gradients():
    vq = VectorQuantizer(3, 2, beta=0.25)
    set_codebook(vq, [[0, 0], [1, 0], [0, 1]])
    z = as_latent([[0.9, 0.1], [0.1, 0.2]]).requires_grad_(True)
    out = vq(z)
    assert out.codes.tolist() == [[[1, 0]]]
    torch.testing.assert_close(out.z_q.detach(), as_latent([[1, 0], [0, 0]]))
    weights = torch.randn_like(z)
    (out.z_q * weights).sum().backward(retain_graph=True)
    torch.testing.assert_close(z.grad, weights)  # identity through the quantizer
    z.grad = None
    out.loss.backward()
    # loss = mean((e - sg z)^2) + beta mean((z - sg e)^2) over 4 numbers
    torch.testing.assert_close(z.grad, 0.25 * 2 * (z.detach() - as_latent([[1, 0], [0, 0]])) / 4)
    torch.testing.assert_close(vq.embed.grad, torch.tensor([[-0.05, -0.1], [0.05, -0.05], [0.0, 0.0]]))


def test_quantizer_usage_and_perplexity():
    vq = VectorQuantizer(4, 1)
    set_codebook(vq, [[0], [10], [20], [30]])
    stats = vq(as_latent([[1], [-1], [9]])).stats
    assert stats["codebook_usage"].item() == pytest.approx(0.5)
    p = torch.tensor([2 / 3, 1 / 3])
    assert stats["perplexity"].item() == pytest.approx(math.exp(-(p * p.log()).sum().item()), rel=1e-5)


def test_quantizer_ema_update_by_hand():
    vq = VectorQuantizer(2, 1, beta=1.0, ema_decay=0.5)
    set_codebook(vq, [[0], [10]])
    out = vq(as_latent([[1], [3], [9]]))
    assert out.loss.item() == pytest.approx((1 + 9 + 1) / 3)  # commitment only
    # counts [2, 1], sums [4, 9]: N = 0.5 * 1 + 0.5 * counts, m = 0.5 * e + 0.5 * sums
    torch.testing.assert_close(vq.ema_count, torch.tensor([1.5, 1.0]))
    torch.testing.assert_close(vq.codebook, torch.tensor([[2.0 / 1.5], [9.5]]))
    vq.eval()
    vq(as_latent([[100], [100]]))
    torch.testing.assert_close(vq.codebook, torch.tensor([[2.0 / 1.5], [9.5]]))  # no update in eval


def test_quantizer_trains_under_bf16_autocast_with_float32_state():
    """An encoder under bf16-mixed precision hands the quantizer bf16 latents: its EMA
    update and dead-code restart stay float32, and the result equals float32 inputs'."""
    reference = VectorQuantizer(2, 1, beta=1.0, ema_decay=0.5, restart_threshold=0.01)
    set_codebook(reference, [[0], [10]])
    mixed = VectorQuantizer(2, 1, beta=1.0, ema_decay=0.5, restart_threshold=0.01)
    set_codebook(mixed, [[0], [10]])
    latent = as_latent([[1], [3], [9]])  # exact in bf16
    expected = reference(latent)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = mixed(latent.bfloat16())
    assert mixed.codebook.dtype == mixed.ema_sum.dtype == torch.float32
    torch.testing.assert_close(mixed.codebook, reference.codebook)
    assert torch.equal(out.codes, expected.codes) and out.loss.item() == pytest.approx(expected.loss.item())


def run_restart(seed: int) -> tuple[list[torch.Tensor], VectorQuantizer, list[torch.Tensor]]:
    torch.manual_seed(seed)
    vq = VectorQuantizer(4, 2, restart_threshold=0.3, usage_decay=0.5)
    set_codebook(vq, [[0, 0], [100, 100], [200, 200], [300, 300]])
    batches = [torch.randn(1, 2, 2, 3) * 0.1 for _ in range(3)]
    snapshots = []
    for z in batches:
        vq(z)
        snapshots.append(vq.codebook.detach().clone())
    return batches, vq, snapshots


def test_dead_code_restart():
    batches, vq, snaps = run_restart(0)
    # usage of codes 1-3 is 1 -> 0.5 -> 0.25: still alive at the second batch, dead at the third
    assert torch.equal(snaps[1][1:], torch.tensor([[100.0, 100.0], [200.0, 200.0], [300.0, 300.0]]))
    rows = batches[2].permute(0, 2, 3, 1).reshape(-1, 2)
    for k in (1, 2, 3):
        assert (rows == snaps[2][k]).all(1).any(), f"code {k} was not moved onto an encoder output"
    assert torch.equal(snaps[2][0], torch.zeros(2))
    counts = torch.bincount(vq.nearest(batches[2]).flatten(), minlength=4).float()
    torch.testing.assert_close(vq.usage[1:], 0.5 + 0.5 * counts[1:])
    _, _, again = run_restart(0)
    assert torch.equal(again[2], snaps[2])  # deterministic given torch's RNG


def _ddp_restart_worker(rank: int, init_file: str, results: dict) -> None:
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=2)
    torch.manual_seed(rank)  # different RNG and data on each rank
    vq = VectorQuantizer(4, 2, ema_decay=0.5, restart_threshold=0.6, usage_decay=0.5)
    set_codebook(vq, [[0, 0], [100, 100], [200, 200], [300, 300]])
    for _ in range(3):
        vq(torch.randn(1, 2, 2, 3) * 0.1)
    results[rank] = (vq.codebook.clone(), vq.usage.clone(), vq.ema_count.clone())
    dist.destroy_process_group()


def test_ddp_restart_and_ema_stay_identical_across_ranks(tmp_path):
    results = mp.Manager().dict()
    two_ranks(_ddp_restart_worker, str(tmp_path / "init"), results)
    for a, b in zip(results[0], results[1]):
        assert torch.equal(a, b)
    assert not torch.equal(results[0][0][1:], torch.tensor([[100.0, 100.0], [200.0, 200.0], [300.0, 300.0]]))


# -- training signal


# Steps with a margin: seeded, the loss halves by step 6 and 9 and ends at 0.33 and 0.31 of its first.
@pytest.mark.parametrize("arch, steps", [("occworld_vqvae", 8), ("occllama_tokenizer", 12)])
def test_tiny_model_overfits_one_sample(arch, steps):
    torch.manual_seed(0)
    model = build_tokenizer(arch, TINY[arch])
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    sem = scene()
    losses = []
    for _ in range(steps):
        loss = model(sem).losses["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses


def test_class_balance_weighs_a_rare_class_up_among_the_occupied_and_is_the_plain_loss_at_zero():
    from occtrain.models.tokenizers.losses import ce_lovasz, class_balance_weights

    # 90 free voxels, 8 road (class 11), 2 car (class 4).
    labels = torch.full((1, 10, 10, 1), FREE, dtype=torch.long)
    labels.view(-1)[:8] = 11
    labels.view(-1)[8:10] = 4
    assert class_balance_weights(labels, 0.0) is None
    w = class_balance_weights(labels, 0.5).view(-1)
    # Among the 10 occupied: road 0.8 ** -0.5 = 1.1180, car 0.2 ** -0.5 = 2.2361, mean 1.3416.
    assert float(w[0]) == pytest.approx(1.1180 / 1.3416, rel=1e-4) and float(w[9]) == pytest.approx(
        2.2361 / 1.3416, rel=1e-4
    )
    assert float(w[9] / w[0]) == pytest.approx(2.0)  # (0.2 / 0.8) ** -0.5
    assert torch.all(w[10:] == 1.0)  # free voxels are not among the balanced classes
    assert float(w[:10].sum()) == pytest.approx(10.0)  # occupied keep their unweighted total: 10 of 100
    logits = torch.randn(1, NUM_CLASSES, 10, 10, 1, generator=torch.Generator().manual_seed(0))
    plain, _ = ce_lovasz(logits, labels)
    ones, _ = ce_lovasz(logits, labels, weights=torch.ones_like(labels, dtype=torch.float32))
    assert float(plain) == pytest.approx(float(ones))
    nll = torch.nn.functional.cross_entropy(logits, labels, reduction="none").view(-1)
    weighted, _ = ce_lovasz(logits, labels, weights=w.view(labels.shape))
    assert float(weighted) == pytest.approx(float((nll * w).sum() / w.sum()), rel=1e-5)


def test_a_class_balanced_loss_predicts_the_true_occupied_share():
    """The weighted cross-entropy's optimum for a model with one logit per class (no input):
    p(class) = its share of the total weight. Free keeps its share of the voxels, 90 %, so
    the predicted occupied share is the true one, 10 %. (Counting free among the balanced
    classes gave 31 %: a free voxel weighed 3.4 times less than a road one, 6.7 than a car.)"""
    from occtrain.models.tokenizers.losses import ce_lovasz, class_balance_weights

    labels = torch.full((1, 10, 10, 1), FREE, dtype=torch.long)
    labels.view(-1)[:8] = 11
    labels.view(-1)[8:10] = 4
    bias = torch.zeros(NUM_CLASSES, requires_grad=True)
    opt = torch.optim.Adam([bias], lr=0.1)
    weights = class_balance_weights(labels, 0.5)
    for _ in range(400):
        logits = bias.view(1, -1, 1, 1, 1).expand(1, NUM_CLASSES, 10, 10, 1)
        loss, _ = ce_lovasz(logits, labels, weights=weights)
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = bias.detach().softmax(0)
    assert float(1 - p[FREE]) == pytest.approx(0.10, abs=0.005)
    assert float(p[4] / p[11]) == pytest.approx(2 * 2.2361 / (8 * 1.1180), rel=0.02)  # the cars weighed up

"""The camera encoder: a Hugging Face vision tower over the six cameras, with a learned
per-camera embedding, producing multi-view image tokens; a dense per-pixel head (class and
depth) to pretrain it; a per-pixel prior as its trivial baseline; its export and loader.

The tower is a tiny SigLIP built from config (no download) or any local Hugging Face
vision model directory (``vision.path``: SigLIP, CLIP, ...). An export holds the tower as
a standard Hugging Face directory (``vision/``) beside occtrain's own parts.
"""

from __future__ import annotations

import inspect
import json
import math
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occtrain.errors import ConfigError, DataError
from occtrain.formats.exports import check_section, load_state_strict, read_export, write_export
from occtrain.formats.io import parse_json
from occtrain.formats.occ3d import NUM_CLASSES
from occtrain.models.patches import unpatchify

if TYPE_CHECKING:  # transformers loads with the first tower built
    from transformers import PreTrainedModel

#: The export's Hugging Face vision-model directory.
TOWER_DIR = "vision"
PREPROCESSOR_FILE = "preprocessor_config.json"
#: SigLIP's normalisation (pixels to [-1, 1]); a loaded model's own preprocessor config wins.
SIGLIP_MEAN = (0.5, 0.5, 0.5)
SIGLIP_STD = (0.5, 0.5, 0.5)
VISION_KIND = "vision"


@dataclass
class VisionConfig:
    """The vision tower and the images it reads.

    With ``path`` empty a tiny SigLIP vision tower is built from the size keys (random
    init, no download); with ``path`` set the model in that local Hugging Face directory
    loads and the size keys are ignored. Image sides that are not multiples of the patch
    size are resized up to the next multiple before the tower.
    """

    #: A local Hugging Face vision model directory (config.json + weights); empty = tiny SigLIP.
    path: str = ""
    hidden_size: int = 64
    num_layers: int = 2
    num_heads: int = 2
    intermediate_size: int = 128
    patch_size: int = 8
    #: Camera image size (the dataset's: nuScenes 900x1600 scaled by 0.08).
    image_height: int = 72
    image_width: int = 128
    num_cameras: int = 6


def validate_vision_config(cfg: Any, key: str = "vision") -> None:
    """One line naming the key when a value of ``cfg`` cannot work."""
    sizes = ["image_height", "image_width", "num_cameras"]
    if not cfg.path:
        sizes += ["hidden_size", "num_layers", "num_heads", "intermediate_size", "patch_size"]
    for name in sizes:
        if getattr(cfg, name) < 1:
            raise ConfigError(f"{key}.{name}: {getattr(cfg, name)} must be at least 1")
    if not cfg.path and cfg.hidden_size % cfg.num_heads:
        raise ConfigError(f"{key}.hidden_size: {cfg.hidden_size} is not divisible by num_heads {cfg.num_heads}")


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def _square(value: Any, what: str, path: str) -> int:
    if isinstance(value, (list, tuple)):
        if len(set(value)) != 1:
            raise ConfigError(
                f"vision.path: {path} has a non-square {what} {list(value)}; occtrain reads square patches only"
            )
        value = value[0]
    return int(value)


def _input_hw(cfg: Any, patch: int) -> tuple[int, int]:
    return (math.ceil(cfg.image_height / patch) * patch, math.ceil(cfg.image_width / patch) * patch)


def build_vision_tower(cfg: Any) -> PreTrainedModel:
    """The tiny SigLIP vision tower of ``cfg`` (``cfg.path`` empty), or the model in ``cfg.path``.

    The tiny tower's position table is square (SigLIP's layout) over the longer image side
    and is interpolated to the image grid each forward (``interpolate_pos_encoding``).
    """
    validate_vision_config(cfg)
    if not cfg.path:
        from transformers import SiglipVisionConfig, SiglipVisionModel

        config = SiglipVisionConfig(
            hidden_size=cfg.hidden_size,
            intermediate_size=cfg.intermediate_size,
            num_hidden_layers=cfg.num_layers,
            num_attention_heads=cfg.num_heads,
            patch_size=cfg.patch_size,
            image_size=max(_input_hw(cfg, cfg.patch_size)),
            # The attention-pooling head makes one vector per image; occtrain reads the
            # patch tokens, and an unused head would stall DDP waiting for its gradients.
            vision_use_head=False,
        )
        return SiglipVisionModel(config)
    return _load_tower(cfg.path)


def _load_tower(path: str) -> PreTrainedModel:
    from transformers import AutoConfig
    from transformers.models.auto.modeling_auto import MODEL_MAPPING

    from occtrain.models.llm import load_pretrained_strict

    if not (Path(path) / "config.json").is_file():
        raise ConfigError(
            f"vision.path: {path} is not a local Hugging Face model directory (no config.json); fix the path or leave "
            "it empty for the tiny SigLIP"
        )
    try:
        config = AutoConfig.from_pretrained(path, local_files_only=True)
    except (OSError, ValueError, KeyError) as e:
        raise ConfigError(
            f"vision.path: cannot read the model config in {path} ({_first_line(e)}); point it at a Hugging Face "
            "vision model directory"
        ) from None
    if config.model_type == "paligemma":  # a VLM directory: its SigLIP tower, its language model left out
        return _vlm_tower(path)
    # A full image-text model (SigLIP, CLIP) carries its tower's config inside.
    vision_cfg = getattr(config, "vision_config", None) or config
    if not all(hasattr(vision_cfg, k) for k in ("hidden_size", "patch_size")) or type(vision_cfg) not in MODEL_MAPPING:
        raise ConfigError(
            f"vision.path: {path} holds a '{config.model_type}' model, not a vision tower (no hidden_size/patch_size); "
            "point it at a SigLIP or CLIP vision model directory"
        )
    # A full image-text model's text weights are left out on purpose (allowed as unexpected);
    # a tower-only directory, which an export's is, must match its config both ways.
    return load_pretrained_strict(
        MODEL_MAPPING[type(vision_cfg)],
        path,
        "vision.path",
        "point it at a vision model directory whose weights match its config",
        allow_unexpected=vision_cfg is not config,
        dtype=torch.float32,
    )


def _vlm_tower(path: str) -> nn.Module:
    """The vision tower of a vision-language model directory (PaliGemma: SigLIP + Gemma)."""
    from transformers import AutoModelForImageTextToText

    from occtrain.models.llm import load_pretrained_strict

    full = load_pretrained_strict(
        AutoModelForImageTextToText,
        path,
        "vision.path",
        "point it at a vision-language model directory whose weights match its config",
        dtype=torch.float32,
    )
    return full.model.vision_tower


def _preprocessor_stats(path: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(mean, std) of a model directory's image preprocessor, SigLIP's when it has none."""
    file = Path(path) / PREPROCESSOR_FILE if path else None
    if file is None or not file.is_file():
        return SIGLIP_MEAN, SIGLIP_STD
    try:
        pre = parse_json(file.read_text())
        return tuple(float(x) for x in pre["image_mean"]), tuple(float(x) for x in pre["image_std"])
    except (ValueError, KeyError, TypeError, OSError) as e:
        raise ConfigError(f"vision.path: {file} has no usable image_mean/image_std ({_first_line(e)})") from None


class MultiViewEncoder(nn.Module):
    """uint8 images (B, N, H, W, 3) -> image tokens (B, N*P, D) and the patch grid (h', w').

    Each camera's image goes through the tower on its own; its P patch tokens (row-major
    over the grid, cameras in the dataset's order) get that camera's learned embedding.
    """

    #: The vision export it was loaded from (a world-model export copies it), None if built here.
    export_dir: Path | None = None
    #: (1, 3, 1, 1): the tower's input normalisation.
    pixel_mean: Tensor
    pixel_std: Tensor

    def __init__(
        self, cfg: Any, image_mean: tuple[float, ...] | None = None, image_std: tuple[float, ...] | None = None
    ):
        super().__init__()
        self.cfg = VisionConfig(**{k: getattr(cfg, k) for k in VisionConfig.__dataclass_fields__})
        self.tower = build_vision_tower(self.cfg)
        tower_cfg = self.tower.config
        self.hidden_size = int(tower_cfg.hidden_size)
        self.patch_size = _square(tower_cfg.patch_size, "patch_size", self.cfg.path)
        self.input_hw = _input_hw(self.cfg, self.patch_size)
        self.grid = (self.input_hw[0] // self.patch_size, self.input_hw[1] // self.patch_size)
        if image_mean is None or image_std is None:
            image_mean, image_std = _preprocessor_stats(self.cfg.path)
        self.register_buffer(
            "pixel_mean", torch.tensor(image_mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False
        )
        self.register_buffer(
            "pixel_std", torch.tensor(image_std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False
        )
        self._interpolates = "interpolate_pos_encoding" in inspect.signature(self.tower.forward).parameters
        self.camera_embed = nn.Parameter(torch.randn(self.cfg.num_cameras, self.hidden_size) * 0.02)
        if self.cfg.path:
            self._freeze_unused()

    @property
    def num_patches(self) -> int:
        return self.grid[0] * self.grid[1]

    def _freeze_unused(self) -> None:
        """Freeze what never reaches the patch tokens (pooling heads, a CLS-only norm) of a
        loaded tower: DDP would otherwise wait for gradients that never come."""
        probe = torch.zeros(1, self.cfg.num_cameras, self.cfg.image_height, self.cfg.image_width, 3, dtype=torch.uint8)
        self.zero_grad(set_to_none=True)
        # A forked RNG: a dropout in the probe draws none of training's random numbers.
        with torch.random.fork_rng(devices=[]), torch.enable_grad():
            self(probe)[0].sum().backward()
        for p in self.tower.parameters():
            if p.grad is None:
                p.requires_grad_(False)
        self.zero_grad(set_to_none=True)

    def pixel_values(self, images: Tensor) -> Tensor:
        """uint8 (B, N, H, W, 3) -> normalised float (B*N, 3, H', W') at the tower's input size."""
        c = self.cfg
        want = (c.num_cameras, c.image_height, c.image_width, 3)
        if images.dim() != 5 or tuple(images.shape[1:]) != want or images.dtype != torch.uint8:
            raise DataError(
                f"images: expected uint8 (B, {', '.join(map(str, want))}), got {images.dtype} {tuple(images.shape)}; "
                "set vision.image_height/image_width/num_cameras to the dataset's"
            )
        x = images.reshape(-1, *images.shape[2:]).permute(0, 3, 1, 2).float().div(255.0)
        x = (x - self.pixel_mean) / self.pixel_std
        if tuple(x.shape[-2:]) != self.input_hw:
            x = F.interpolate(x, size=self.input_hw, mode="bilinear", align_corners=False)
        return x

    def forward(self, images: Tensor) -> tuple[Tensor, tuple[int, int]]:
        b, n = images.shape[:2]
        x = self.pixel_values(images).to(self.camera_embed.dtype)
        kwargs = {"interpolate_pos_encoding": True} if self._interpolates else {}
        hidden = self.tower(pixel_values=x, **kwargs).last_hidden_state
        # Patch tokens come last: a CLS token (CLIP) comes first, SigLIP has none.
        tokens = hidden[:, -self.num_patches :].reshape(b, n, self.num_patches, self.hidden_size)
        tokens = tokens + self.camera_embed[None, :, None].to(tokens.dtype)
        return tokens.reshape(b, n * self.num_patches, self.hidden_size), self.grid


def pool_views(tokens: Tensor, grid: tuple[int, int], num_cameras: int, out_hw: tuple[int, int]) -> Tensor:
    """Each camera's patch tokens (B, N*P, D) average-pooled over its grid to ``out_hw``:
    (B, N * rows * cols, D), cameras in order, row-major within each."""
    b, _, d = tokens.shape
    x = tokens.reshape(b * num_cameras, grid[0], grid[1], d).permute(0, 3, 1, 2)
    x = F.adaptive_avg_pool2d(x, (out_hw[0], out_hw[1]))
    return x.permute(0, 2, 3, 1).reshape(b, num_cameras * out_hw[0] * out_hw[1], d)


class DenseHead(nn.Module):
    """Per patch token, a linear map to ``patch^2 x (classes + 1)`` values, pixel-shuffled
    back to the image: class logits and log-depth (metres) at every pixel."""

    def __init__(self, hidden_size: int, patch_size: int, num_classes: int = NUM_CLASSES):
        super().__init__()
        self.patch_size, self.num_classes = patch_size, num_classes
        self.proj = nn.Linear(hidden_size, patch_size * patch_size * (num_classes + 1))
        with torch.no_grad():  # log-depth starts at ~10 m, a typical distance, not at 1 m
            self.proj.bias.view(patch_size * patch_size, num_classes + 1)[:, -1].fill_(math.log(10.0))

    def forward(
        self, tokens: Tensor, grid: tuple[int, int], num_cameras: int, image_hw: tuple[int, int]
    ) -> tuple[Tensor, Tensor]:
        """(B, N*P, D) -> class logits (B, N, C, H, W) and log-depth (B, N, H, W)."""
        b, p = tokens.shape[0], self.patch_size
        gh, gw = grid
        x = self.proj(tokens).view(b * num_cameras, gh * gw, -1)
        x = unpatchify(x, p, (gh * p, gw * p))  # (B*N, classes + 1, H', W')
        if (gh * p, gw * p) != tuple(image_hw):
            x = F.interpolate(x, size=tuple(image_hw), mode="bilinear", align_corners=False)
        x = x.view(b, num_cameras, self.num_classes + 1, *image_hw)
        return x[:, :, :-1], x[:, :, -1]


def pixel_losses(logits: Tensor, log_depth: Tensor, cam_class: Tensor, cam_depth: Tensor) -> tuple[Tensor, Tensor]:
    """A dense head's two losses against the renderer's per-pixel targets: cross-entropy of
    the class logits (B, V, C, H, W) against ``cam_class`` (B, V, H, W), and L1 of the
    log-depth (B, V, H, W) against log ``cam_depth`` over the pixels with a surface (0 with
    the graph kept for an all-sky batch, so DDP's gradients stay in step)."""
    class_loss = F.cross_entropy(logits.flatten(0, 1), cam_class.long().flatten(0, 1))
    depth = cam_depth.float()
    surface = depth > 0
    if surface.any():
        depth_loss = (log_depth[surface] - depth[surface].log()).abs().mean()
    else:
        depth_loss = log_depth.sum() * 0.0
    return class_loss, depth_loss


class PixelPrior(nn.Module):
    """The trivial baseline of dense camera targets: at each pixel of each camera, the most
    frequent class and the geometric mean depth seen in training frames (sums kept for DDP
    reduction). Geometric, not arithmetic: a pixel near the horizon sees the road 30 m away
    in one frame and 300 m in the next, and a plain mean would make the baseline a straw man."""

    #: (N, H, W, C) class counts, (N, H, W) log-depth sums and pixels with depth.
    class_counts: Tensor
    log_depth_sum: Tensor
    depth_pixels: Tensor

    def __init__(self, num_cameras: int, height: int, width: int, num_classes: int = NUM_CLASSES):
        super().__init__()
        self.num_classes = num_classes
        shape = (num_cameras, height, width)
        self.register_buffer("class_counts", torch.zeros(*shape, num_classes, dtype=torch.long), persistent=False)
        self.register_buffer("log_depth_sum", torch.zeros(shape, dtype=torch.float64), persistent=False)
        self.register_buffer("depth_pixels", torch.zeros(shape, dtype=torch.long), persistent=False)

    @property
    def fitted(self) -> bool:
        return bool(self.class_counts.sum() > 0)

    def reset(self) -> None:
        for buf in self.buffers():
            buf.zero_()

    @torch.no_grad()
    def update(self, cam_class: Tensor, cam_depth: Tensor) -> None:
        """Count one batch: classes (B, N, H, W) and depths (B, N, H, W), 0 = no depth."""
        dev = self.class_counts.device
        cam_class, cam_depth = cam_class.to(dev).long(), cam_depth.to(dev).double()
        self.class_counts += F.one_hot(cam_class, self.num_classes).sum(0)
        has = cam_depth > 0
        self.log_depth_sum += torch.where(has, cam_depth.clamp(min=1e-6).log(), 0.0).sum(0)
        self.depth_pixels += has.sum(0)

    def reduce(self, sum_fn: Callable[[Tensor], Tensor]) -> None:
        """Replace the sums by ``sum_fn`` of them (a sum over DDP ranks)."""
        for buf in self.buffers():
            buf.copy_(sum_fn(buf))

    def predict(self, batch_size: int) -> tuple[Tensor, Tensor]:
        """Classes (B, N, H, W) and depths (B, N, H, W); a pixel never seen with depth gets the mean over all."""
        classes = self.class_counts.argmax(-1)
        overall = self.log_depth_sum.sum() / self.depth_pixels.sum().clamp(min=1)
        depth = (
            torch.where(self.depth_pixels > 0, self.log_depth_sum / self.depth_pixels.clamp(min=1), overall)
            .exp()
            .float()
        )
        return classes.expand(batch_size, *classes.shape), depth.expand(batch_size, *depth.shape)


# ----------------------------------------------------------------------------- export


def _tower_dir(encoder: MultiViewEncoder, out: Path) -> Path:
    """The tower as a standard Hugging Face directory, with its image preprocessor config."""
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()  # a bar per save says nothing in a run's log
    encoder.tower.save_pretrained(str(out), safe_serialization=True)
    source = Path(encoder.cfg.path) / PREPROCESSOR_FILE if encoder.cfg.path else None
    if source is not None and source.is_file():
        shutil.copy2(source, out / PREPROCESSOR_FILE)
    else:
        h, w = encoder.input_hw
        pre = {
            "image_processor_type": "SiglipImageProcessor",
            "do_resize": True,
            "size": {"height": h, "width": w},
            "resample": 3,
            "do_rescale": True,
            "rescale_factor": 1 / 255,
            "do_normalize": True,
            "image_mean": encoder.pixel_mean.flatten().tolist(),
            "image_std": encoder.pixel_std.flatten().tolist(),
        }
        (out / PREPROCESSOR_FILE).write_text(json.dumps(pre, indent=2) + "\n")
    return out


def export_vision(export_dir: Path, encoder: MultiViewEncoder, head: DenseHead, info: dict | None = None) -> Path:
    """Write ``vision/`` (the tower, a Hugging Face directory) and ``model.safetensors`` +
    ``config.json`` (camera embedding, dense head, the VisionConfig, ``info``)."""
    state = {f"encoder.{k}": v for k, v in encoder.state_dict().items() if not k.startswith("tower.")}
    state.update({f"head.{k}": v for k, v in head.state_dict().items()})
    config = {
        "stage_kind": VISION_KIND,
        "vision": asdict(encoder.cfg),
        "tower": {
            "model_type": encoder.tower.config.model_type,
            "hidden_size": encoder.hidden_size,
            "patch_size": encoder.patch_size,
            "grid": list(encoder.grid),
            "input_hw": list(encoder.input_hw),
        },
        "image_mean": encoder.pixel_mean.flatten().tolist(),
        "image_std": encoder.pixel_std.flatten().tolist(),
        "num_classes": head.num_classes,
        **(info or {}),
    }
    with tempfile.TemporaryDirectory() as tmp:
        tower = _tower_dir(encoder, Path(tmp) / TOWER_DIR)
        return write_export(Path(export_dir), state, config, {TOWER_DIR: tower})


def _read_vision_export(export_dir: Path) -> tuple[dict[str, Tensor], dict]:
    state, config = read_export(export_dir)
    if config.get("stage_kind") != VISION_KIND:
        raise ConfigError(
            f"{export_dir}: not a vision export (stage kind '{config.get('stage_kind')}'); consume a vision stage"
        )
    return state, config


def load_vision_encoder(export_dir: Path, trainable: bool = False) -> MultiViewEncoder:
    """The encoder of a vision stage's export: frozen in eval mode, or trainable."""
    export_dir = Path(export_dir)
    state, config = _read_vision_export(export_dir)
    check_section(VisionConfig, config["vision"], "vision", export_dir)
    cfg = VisionConfig(**{**config["vision"], "path": str(export_dir / TOWER_DIR)})
    encoder = MultiViewEncoder(cfg, tuple(config["image_mean"]), tuple(config["image_std"]))
    own = {k[len("encoder.") :]: v for k, v in state.items() if k.startswith("encoder.")}
    load_state_strict(encoder, own, ("tower.",), str(export_dir))
    encoder.export_dir = export_dir  # a world-model export copies it from here
    if not trainable:
        encoder.requires_grad_(False).eval()
    return encoder


def load_dense_head(export_dir: Path) -> DenseHead:
    """The dense head of a vision stage's export, in eval mode."""
    state, config = _read_vision_export(export_dir)
    tower = config["tower"]
    head = DenseHead(tower["hidden_size"], tower["patch_size"], config["num_classes"])
    load_state_strict(
        head, {k[len("head.") :]: v for k, v in state.items() if k.startswith("head.")}, (), str(export_dir)
    )
    return head.eval()

"""The joint occupancy-language-action vocabulary (OccLLaMA Sec. III-B): the one owner of
the id layout.

Ids, in order::

    [0, T)                 the text tokenizer's own tokens (T = its size, specials included)
    [T, T+S)               the scene tokens (see below)
    [.., +B)               <bin_x_0> ... : action bins of the x axis (forward)
    [.., +B)               <bin_y_0> ... : action bins of the y axis (left)
    4 specials             <occ> </occ> <act> </act>
    [.., +Q)               <scene_q_0> ...: learnable scene queries, one per scene token
    (+1)                   <image>: an image token's placeholder (vision-language models only)
    [.., +E)               a family's own tokens, by name (SparseOccVLA's global scene
                           queries and ego-state token), whose embeddings it computes

Scene tokens come in two layouts. Codes (OccLLaMA, ``patch=0``): one token per latent cell
and codebook, ``<occ_k>`` for code k of the first codebook, ``<occ{i}_k>`` for codebook i
(Occ-LLM's MS-VAE has two), so S = the codebooks' sizes summed and a scene is
``num_codebooks * h * w`` tokens, codebook-major. Patches (Occ-LLM, ``patch=p``): one
token ``<patch_j>`` per p x p patch of the latent grid, S = Q = (h/p)(w/p); the codes of a
patch ride beside the ids (the world model embeds them), so the id only says which patch.

Occupancy tokens are numbered from 0 like the codebook rows (the paper counts from 1).
Separate x and y bin ranges let generation alternate the two axes by id range alone. All
new tokens are added to the Hugging Face tokenizer as special tokens with exactly these
ids, so ``decode`` shows them and ``skip_special_tokens`` hides them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from occtrain.config.llm import LLMConfig, validate_llm_config
from occtrain.errors import ConfigError
from occtrain.models.actions import ActionQuantizer

OCC_OPEN, OCC_CLOSE, ACT_OPEN, ACT_CLOSE = "<occ>", "</occ>", "<act>", "</act>"
IMAGE = "<image>"


def scene_length(codebook_sizes: Sequence[int], scene_hw: Sequence[int], patch: int = 0) -> int:
    """Tokens one frame of scene takes (the module docstring's layouts): one per p x p patch
    of the latent grid, or one per cell and codebook."""
    h, w = (int(v) for v in scene_hw)
    if patch:
        return (h // patch) * (w // patch)
    return len(codebook_sizes) * h * w


class JointVocab:
    """Id ranges and conversions between codes / waypoints / text and token ids."""

    def __init__(
        self,
        text_tokenizer: Any,
        codebook_sizes: int | Sequence[int],
        scene_hw: tuple[int, int],
        llm_cfg: LLMConfig | None = None,
        text_size: int | None = None,
        patch: int = 0,
        image: bool = False,
        extra: Sequence[str] = (),
        action_grid: str = "zero",
    ):
        """``codebook_sizes``: the scene tokenizer's codebooks (an int for one); ``patch``: 0
        for the codes layout, else the patch side of the patches layout (module docstring).
        ``text_size`` is T of the layout; by default the tokenizer's size before any of
        the joint tokens are added (give it when the tokenizer already holds them).
        ``image``: add one ``<image>`` token last, the placeholder of an image token whose
        embedding a vision-language model computes from its payload (OccVLA). ``extra``: a
        family's own tokens (``<global_0>``, ...), laid out last in this order.
        ``action_grid``: how the action bins lie (``models.actions.ACTION_GRIDS``)."""
        cfg = llm_cfg or LLMConfig()
        validate_llm_config(cfg)
        self.tokenizer = text_tokenizer
        sizes = [int(codebook_sizes)] if isinstance(codebook_sizes, int) else [int(k) for k in codebook_sizes]
        self.codebook_sizes = sizes
        self.num_codebooks = len(sizes)
        self.scene_hw = (int(scene_hw[0]), int(scene_hw[1]))
        self.cells = self.scene_hw[0] * self.scene_hw[1]
        self.patch = int(patch)
        if self.patch and (self.scene_hw[0] % self.patch or self.scene_hw[1] % self.patch):
            raise ConfigError(
                f"patch size {self.patch} must divide the latent grid {self.scene_hw[0]}x{self.scene_hw[1]}"
            )
        self.scene_len = scene_length(sizes, self.scene_hw, self.patch)
        self.num_codes = self.scene_len if self.patch else sum(sizes)  # the <patch_j> tokens, or every codebook's codes
        #: Where each codebook's tokens start inside the scene-token range (codes layout).
        self.codebook_starts = [sum(sizes[:i]) for i in range(len(sizes))]
        self.bins = int(cfg.action_bins)
        (xl, xh), (yl, yh) = cfg.action_range
        self.quantizer = ActionQuantizer(self.bins, (float(xl), float(yl)), (float(xh), float(yh)), action_grid)
        self.action_encoding, self.action_decoding = cfg.action_encoding, cfg.action_decoding
        self.text_size = len(text_tokenizer) if text_size is None else int(text_size)
        self.image = bool(image)
        self.extra = tuple(str(name) for name in extra)
        self._lay_out_ids()
        self._register_tokens()

        self.eos_id = int(text_tokenizer.eos_token_id)
        self.bos_id = int(text_tokenizer.bos_token_id if text_tokenizer.bos_token_id is not None else self.eos_id)
        pad = text_tokenizer.pad_token_id
        self.pad_id = int(pad if pad is not None else self.eos_id)

    def _lay_out_ids(self) -> None:
        """The id ranges after the text tokens, in the order of the module docstring."""
        self.occ_start = self.text_size
        self.act_x_start = self.occ_start + self.num_codes
        self.act_y_start = self.act_x_start + self.bins
        self.occ_open_id = self.act_y_start + self.bins
        self.occ_close_id = self.occ_open_id + 1
        self.act_open_id = self.occ_open_id + 2
        self.act_close_id = self.occ_open_id + 3
        self.query_start = self.occ_open_id + 4
        self.image_id = self.query_start + self.scene_len if self.image else -1
        self.extra_start = self.query_start + self.scene_len + int(self.image)
        self.size = self.extra_start + len(self.extra)

    def _scene_token_names(self) -> list[str]:
        if self.patch:
            return [f"<patch_{j}>" for j in range(self.scene_len)]
        return [f"<occ{i or ''}_{k}>" for i, size in enumerate(self.codebook_sizes) for k in range(size)]

    def _register_tokens(self) -> None:
        names = (
            self._scene_token_names()
            + [f"<bin_x_{b}>" for b in range(self.bins)]
            + [f"<bin_y_{b}>" for b in range(self.bins)]
            + [OCC_OPEN, OCC_CLOSE, ACT_OPEN, ACT_CLOSE]
            + [f"<scene_q_{j}>" for j in range(self.scene_len)]
            + ([IMAGE] if self.image else [])
            + list(self.extra)
        )
        if len(self.tokenizer) == self.text_size:
            self.tokenizer.add_tokens(names, special_tokens=True)
        got = self.tokenizer.convert_tokens_to_ids(names)
        if len(self.tokenizer) != self.size or got != list(range(self.text_size, self.size)):
            raise ConfigError(
                f"text tokenizer: its {len(self.tokenizer)} tokens do not match the joint vocabulary layout "
                f"({self.text_size} text + {self.size - self.text_size} joint tokens); use the tokenizer saved with "
                "this vocabulary"
            )

    def __len__(self) -> int:
        return self.size

    # -- id ranges, [low, high)
    @property
    def text_range(self) -> tuple[int, int]:
        return 0, self.text_size

    @property
    def occ_range(self) -> tuple[int, int]:
        return self.occ_start, self.act_x_start

    @property
    def act_x_range(self) -> tuple[int, int]:
        return self.act_x_start, self.act_y_start

    @property
    def act_y_range(self) -> tuple[int, int]:
        return self.act_y_start, self.occ_open_id

    @property
    def query_range(self) -> tuple[int, int]:
        return self.query_start, self.query_start + self.scene_len

    # -- conversions
    def text_ids(self, text: str) -> list[int]:
        """Token ids of ``text`` alone (no bos/eos added)."""
        return list(self.tokenizer(text, add_special_tokens=False)["input_ids"])

    def decode_text(self, ids: torch.Tensor | list[int]) -> str:
        """Text of ``ids``, joint and text-special tokens dropped."""
        ids = ids.tolist() if torch.is_tensor(ids) else list(ids)
        return self.tokenizer.decode(ids, skip_special_tokens=True)

    def scene_token_range(self, j: int) -> tuple[int, int]:
        """[low, high) of the ids scene token ``j`` may take: its codebook's range (codes
        layout) or its own ``<patch_j>`` (patches layout)."""
        if self.patch:
            return self.occ_start + j, self.occ_start + j + 1
        i = j // self.cells
        lo = self.occ_start + self.codebook_starts[i]
        return lo, lo + self.codebook_sizes[i]

    def _offsets(self, device: torch.device | None = None) -> torch.Tensor:
        """Long[scene_len]: the id of code 0 at each position of a scene (codes layout)."""
        starts = torch.tensor(self.codebook_starts, dtype=torch.long, device=device)
        return self.occ_start + starts.repeat_interleave(self.cells)

    def occ_ids(self, codes: torch.Tensor) -> torch.Tensor:
        """A scene's codes, flat and codebook-major (``scene_len``,) -> its token ids."""
        codes = codes.reshape(-1).long()
        if codes.numel() != self.scene_len or self.patch:
            raise ValueError(
                f"occ_ids takes the {self.scene_len} codes of one scene in the codes layout, got {codes.numel()}"
            )
        sizes = torch.tensor(self.codebook_sizes, device=codes.device).repeat_interleave(self.cells)
        if bool(((codes < 0) | (codes >= sizes)).any()):
            raise ValueError(f"scene codes must lie in [0, K) of their codebook (sizes {self.codebook_sizes})")
        return codes + self._offsets(codes.device)

    def codes_from_ids(self, ids: torch.Tensor) -> torch.Tensor:
        """A scene's token ids (``scene_len``,) -> its codes, flat and codebook-major."""
        ids = ids.reshape(-1).long()
        if not bool(self.is_occ(ids).all()) or ids.numel() != self.scene_len:
            raise ValueError("codes_from_ids takes the token ids of one whole scene")
        return ids - self._offsets(ids.device)

    def pick_scene(self, logits: torch.Tensor) -> torch.Tensor:
        """The greedy scene token ids from the query outputs Float[scene_len, V], each
        position choosing within its own codebook's range (codes layout)."""
        picks = []
        for i, size in enumerate(self.codebook_sizes):
            lo = self.occ_start + self.codebook_starts[i]
            rows = logits[i * self.cells : (i + 1) * self.cells, lo : lo + size]
            picks.append(rows.argmax(-1) + lo)
        return torch.cat(picks)

    def action_ids(self, xy: torch.Tensor) -> torch.Tensor:
        """One block's waypoints Float[N, 2] (metres) -> Long[2N] ids, x bin then y bin per
        waypoint: their positions, or with ``action_encoding`` "delta" their moves.
        Out-of-range values clamp to the edge bins (see ``ActionQuantizer``)."""
        xy = xy.reshape(-1, 2)
        bins = self.quantizer.encode_moves(xy) if self.action_encoding == "delta" else self.quantizer.encode(xy)
        offsets = torch.tensor([self.act_x_start, self.act_y_start], device=bins.device)
        return (bins + offsets).reshape(-1)

    def actions_from_ids(self, ids: torch.Tensor) -> torch.Tensor:
        """One block's Long[2N] ids (x bin, y bin, ...) -> Float[N, 2] positions in metres
        (bin centres, or with "delta" the moves' centres summed)."""
        pairs = ids.long().reshape(-1, 2)
        offsets = torch.tensor([self.act_x_start, self.act_y_start], device=ids.device)
        bins = pairs - offsets
        if bool(((bins < 0) | (bins >= self.bins)).any()):
            raise ValueError("actions_from_ids expects alternating x-bin and y-bin ids")
        return self.quantizer.decode_moves(bins) if self.action_encoding == "delta" else self.quantizer.decode(bins)

    def pick_action(self, logits: torch.Tensor, axis: int) -> int:
        """The id of the next bin of ``axis`` (0: x, 1: y) from the output logits over the
        whole vocabulary: the likeliest, or with ``action_decoding`` "expected" the one
        holding the expected value."""
        lo, hi = self.act_x_range if axis == 0 else self.act_y_range
        if self.action_decoding == "expected":
            return lo + self.quantizer.expected_bin(logits[lo:hi], axis)
        return lo + int(logits[lo:hi].argmax())

    def query_ids(self) -> torch.Tensor:
        """The Q scene-query ids, one per scene token (latent cell and codebook, or patch), in order."""
        return torch.arange(*self.query_range)

    # -- masks
    def is_text(self, ids: torch.Tensor) -> torch.Tensor:
        return ids < self.text_size

    def is_occ(self, ids: torch.Tensor) -> torch.Tensor:
        return (ids >= self.occ_start) & (ids < self.act_x_start)

    def is_action(self, ids: torch.Tensor) -> torch.Tensor:
        return (ids >= self.act_x_start) & (ids < self.occ_open_id)

    def is_query(self, ids: torch.Tensor) -> torch.Tensor:
        return (ids >= self.query_start) & (ids < self.query_start + self.scene_len)

    def is_image(self, ids: torch.Tensor) -> torch.Tensor:
        return ids == self.image_id

    def extra_id(self, name: str) -> int:
        """The id of the family's own token ``name`` (see ``extra``)."""
        return self.extra_start + self.extra.index(name)

    def is_extra(self, ids: torch.Tensor) -> torch.Tensor:
        return ids >= self.extra_start

    # -- export
    def to_json(self) -> dict:
        """What ``from_json`` needs besides the (saved) text tokenizer."""
        return {
            "text_size": self.text_size,
            "codebook_sizes": list(self.codebook_sizes),
            "patch": self.patch,
            "image": self.image,
            "extra": list(self.extra),
            "scene_hw": list(self.scene_hw),
            "action_bins": self.bins,
            "action_range": [
                [float(lo), float(hi)] for lo, hi in zip(self.quantizer.low.tolist(), self.quantizer.high.tolist())
            ],
            "action_grid": self.quantizer.grid,
            "action_encoding": self.action_encoding,
            "action_decoding": self.action_decoding,
        }

    @classmethod
    def from_json(cls, data: dict, text_tokenizer: Any) -> JointVocab:
        """Rebuild from ``to_json`` and a text tokenizer, with or without the joint tokens."""
        cfg = LLMConfig(
            action_bins=int(data["action_bins"]),
            action_range=[list(r) for r in data["action_range"]],
            action_encoding=str(data.get("action_encoding", "absolute")),
            action_decoding=str(data.get("action_decoding", "greedy")),
        )  # exports from before the two switches hold the papers' rules
        sizes = data.get("codebook_sizes", [data.get("num_codes", 0)])  # exports before multi-codebook vocabularies
        return cls(
            text_tokenizer,
            sizes,
            tuple(data["scene_hw"]),
            cfg,
            text_size=data["text_size"],
            patch=int(data.get("patch", 0)),
            image=bool(data.get("image", False)),
            extra=tuple(data.get("extra", ())),
            action_grid=str(data.get("action_grid", "range")),  # exports before the zero grid
        )

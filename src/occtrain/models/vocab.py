"""The joint occupancy-language-action vocabulary (OccLLaMA Sec. III-B): the one owner of
the id layout.

Ids, in order::

    [0, T)                 the text tokenizer's own tokens (T = its size, specials included)
    [T, T+K)               <occ_0> ... <occ_{K-1}>: codebook index k of the scene tokenizer
    [.., +B)               <bin_x_0> ... : action bins of the x axis (forward)
    [.., +B)               <bin_y_0> ... : action bins of the y axis (left)
    4 specials             <occ> </occ> <act> </act>
    [.., +Q)               <scene_q_0> ...: learnable scene queries, Q = h*w latent cells

Occupancy tokens are numbered from 0 like the codebook rows (the paper counts from 1).
Separate x and y bin ranges let generation alternate the two axes by id range alone. All
new tokens are added to the Hugging Face tokenizer as special tokens with exactly these
ids, so ``decode`` shows them and ``skip_special_tokens`` hides them.
"""

from __future__ import annotations

from typing import Any

import torch

from occtrain.config.llm import LLMConfig, validate_llm_config
from occtrain.errors import ConfigError
from occtrain.models.actions import ActionQuantizer

OCC_OPEN, OCC_CLOSE, ACT_OPEN, ACT_CLOSE = "<occ>", "</occ>", "<act>", "</act>"


class JointVocab:
    """Id ranges and conversions between codes / waypoints / text and token ids."""

    def __init__(
        self,
        text_tokenizer: Any,
        num_codes: int,
        scene_hw: tuple[int, int],
        llm_cfg: LLMConfig | None = None,
        text_size: int | None = None,
    ):
        """``text_size`` is T of the layout; by default the tokenizer's size before any of
        the joint tokens are added (give it when the tokenizer already holds them)."""
        cfg = llm_cfg or LLMConfig()
        validate_llm_config(cfg)
        self.tokenizer = text_tokenizer
        self.num_codes = int(num_codes)
        self.scene_hw = (int(scene_hw[0]), int(scene_hw[1]))
        self.scene_len = self.scene_hw[0] * self.scene_hw[1]
        self.bins = int(cfg.action_bins)
        (xl, xh), (yl, yh) = cfg.action_range
        self.quantizer = ActionQuantizer(self.bins, (float(xl), float(yl)), (float(xh), float(yh)))
        self.text_size = len(text_tokenizer) if text_size is None else int(text_size)

        self.occ_start = self.text_size
        self.act_x_start = self.occ_start + self.num_codes
        self.act_y_start = self.act_x_start + self.bins
        self.occ_open_id = self.act_y_start + self.bins
        self.occ_close_id = self.occ_open_id + 1
        self.act_open_id = self.occ_open_id + 2
        self.act_close_id = self.occ_open_id + 3
        self.query_start = self.occ_open_id + 4
        self.size = self.query_start + self.scene_len
        self._register_tokens()

        self.eos_id = int(text_tokenizer.eos_token_id)
        self.bos_id = int(text_tokenizer.bos_token_id if text_tokenizer.bos_token_id is not None else self.eos_id)
        pad = text_tokenizer.pad_token_id
        self.pad_id = int(pad if pad is not None else self.eos_id)

    def _register_tokens(self) -> None:
        names = (
            [f"<occ_{k}>" for k in range(self.num_codes)]
            + [f"<bin_x_{b}>" for b in range(self.bins)]
            + [f"<bin_y_{b}>" for b in range(self.bins)]
            + [OCC_OPEN, OCC_CLOSE, ACT_OPEN, ACT_CLOSE]
            + [f"<scene_q_{j}>" for j in range(self.scene_len)]
        )
        if len(self.tokenizer) == self.text_size:
            self.tokenizer.add_tokens(names, special_tokens=True)
        got = self.tokenizer.convert_tokens_to_ids(names)
        if len(self.tokenizer) != self.size or got != list(range(self.text_size, self.size)):
            raise ConfigError(
                f"text tokenizer: its {len(self.tokenizer)} tokens do not match the joint vocabulary layout "
                f"({self.text_size} text + {self.size - self.text_size} joint tokens); use the tokenizer saved with this vocabulary"
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
        return self.query_start, self.size

    # -- conversions
    def text_ids(self, text: str) -> list[int]:
        """Token ids of ``text`` alone (no bos/eos added)."""
        return list(self.tokenizer(text, add_special_tokens=False)["input_ids"])

    def decode_text(self, ids: torch.Tensor | list[int]) -> str:
        """Text of ``ids``, joint and text-special tokens dropped."""
        ids = ids.tolist() if torch.is_tensor(ids) else list(ids)
        return self.tokenizer.decode(ids, skip_special_tokens=True)

    def occ_ids(self, codes: torch.Tensor) -> torch.Tensor:
        """Codebook indices (any shape) -> occupancy token ids."""
        if codes.numel() and (codes.min() < 0 or codes.max() >= self.num_codes):
            raise ValueError(f"scene codes must lie in [0, {self.num_codes})")
        return codes.long() + self.occ_start

    def codes_from_ids(self, ids: torch.Tensor) -> torch.Tensor:
        """Occupancy token ids -> codebook indices."""
        if not bool(self.is_occ(ids).all()):
            raise ValueError("codes_from_ids got ids outside the occupancy range")
        return ids.long() - self.occ_start

    def action_ids(self, xy: torch.Tensor) -> torch.Tensor:
        """Waypoints Float[N, 2] (metres) -> Long[2N] ids, x bin then y bin per waypoint.
        Out-of-range values clamp to the edge bins (see ``ActionQuantizer``)."""
        bins = self.quantizer.encode(xy.reshape(-1, 2))
        offsets = torch.tensor([self.act_x_start, self.act_y_start], device=bins.device)
        return (bins + offsets).reshape(-1)

    def actions_from_ids(self, ids: torch.Tensor) -> torch.Tensor:
        """Long[2N] ids (x bin, y bin, ...) -> Float[N, 2] bin centres in metres."""
        pairs = ids.long().reshape(-1, 2)
        offsets = torch.tensor([self.act_x_start, self.act_y_start], device=ids.device)
        bins = pairs - offsets
        if bool(((bins < 0) | (bins >= self.bins)).any()):
            raise ValueError("actions_from_ids expects alternating x-bin and y-bin ids")
        return self.quantizer.decode(bins)

    def query_ids(self) -> torch.Tensor:
        """The Q scene-query ids, one per latent cell in row-major order."""
        return torch.arange(self.query_start, self.size)

    # -- masks
    def is_text(self, ids: torch.Tensor) -> torch.Tensor:
        return ids < self.text_size

    def is_occ(self, ids: torch.Tensor) -> torch.Tensor:
        return (ids >= self.occ_start) & (ids < self.act_x_start)

    def is_action(self, ids: torch.Tensor) -> torch.Tensor:
        return (ids >= self.act_x_start) & (ids < self.occ_open_id)

    def is_query(self, ids: torch.Tensor) -> torch.Tensor:
        return ids >= self.query_start

    # -- export
    def to_json(self) -> dict:
        """What ``from_json`` needs besides the (saved) text tokenizer."""
        return {
            "text_size": self.text_size,
            "num_codes": self.num_codes,
            "scene_hw": list(self.scene_hw),
            "action_bins": self.bins,
            "action_range": [[float(lo), float(hi)] for lo, hi in zip(self.quantizer.low.tolist(), self.quantizer.high.tolist())],
        }

    @classmethod
    def from_json(cls, data: dict, text_tokenizer: Any) -> JointVocab:
        """Rebuild from ``to_json`` and a text tokenizer, with or without the joint tokens."""
        cfg = LLMConfig(action_bins=int(data["action_bins"]), action_range=[list(r) for r in data["action_range"]])
        return cls(text_tokenizer, data["num_codes"], tuple(data["scene_hw"]), cfg, text_size=data["text_size"])

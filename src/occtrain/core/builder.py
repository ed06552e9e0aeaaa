"""Laying parts out as token sequences, and collating them into a model batch.

Sequence layout. A sequence starts with ``bos``; then parts, each laid out as

- text: its tokens, then ``eos`` (every text part ends with it, so generated text, which
  stops at ``eos``, re-encodes to the same tokens when it becomes context);
- actions: ``<act> x_1 y_1 ... x_N y_N </act>`` (an x bin then a y bin per waypoint);
- a context scene (codes layout): ``<occ> c_1 ... c_S </occ>`` with its S code tokens
  forming one bidirectional segment ("next_scene" mode) or plain causal tokens
  ("next_token" mode);
- a supervised scene in "next_scene" mode: ``<occ> q_1 ... q_S c_1 ... c_S </occ>``. The
  query block q (the learnable ``<scene_q_j>`` tokens, or what the world model's
  ``scene_query_ids`` makes of the scenes before it and the ego's moves since them,
  ``core.ego_steps``) is bidirectional, sees everything
  before it, is seen by nothing after it, and its output at ``q_j`` is trained to give
  token ``c_j``: all of the scene from one forward pass. The code block c repeats the
  scene's tokens at the same positions (RoPE) as the queries, and is what later tokens
  attend to. Generation does exactly that with the KV cache (the query keys are cropped
  off and the chosen tokens fed instead).

A family lays out its own parts (images, slots that carry continuous features, ...)
through the public extension point :meth:`SequenceBuilder.add` (and ``next_block`` for a
bidirectional block of its own), overriding the part methods it lays out differently.

Labels. ``labels[t]`` is the target of the output at position ``t`` (already shifted;
-100 where none): the next kept token when that token is supervised, and for a query
token its scene token. Every token of a supervised part is supervised except the code
block behind a query block (the queries predict it).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from occtrain.config.llm import SCENE_PREDICTION_MODES
from occtrain.core.ego_steps import SceneContext, SceneTrack
from occtrain.core.forecast_targets import ForecastTarget
from occtrain.core.protocols import PromptInputs
from occtrain.core.sequence import IGNORE, PayloadSpec, TokenSequence, cat_payload, empty_payload
from occtrain.core.vocab import JointVocab
from occtrain.data.clips import Actions, Branch, Part, Scene, Text
from occtrain.models.attention import allowed_pairs


class SequenceBuilder:
    """Lays parts out in the joint vocabulary (see the module docstring).

    ``scene_prediction``, ``payload_spec``, ``scene_queries`` (the query block's ids
    from the ``SceneContext`` of the scene) and ``forecast_target`` (what a predicted scene
    is trained to give) must be the model's (``world.builder()`` gets them right).
    """

    def __init__(
        self,
        vocab: JointVocab,
        scene_prediction: str = "next_scene",
        payload_spec: PayloadSpec | None = None,
        scene_queries: Callable[[SceneContext], torch.Tensor] | None = None,
        forecast_target: Callable[[SceneContext, torch.Tensor], ForecastTarget] | None = None,
    ):
        if scene_prediction not in SCENE_PREDICTION_MODES:
            raise ValueError(f"scene_prediction must be one of {SCENE_PREDICTION_MODES}")
        self.vocab = vocab
        self.next_scene = scene_prediction == "next_scene"
        self.payload_spec = payload_spec or {}
        self.scene_queries = scene_queries or (lambda context: vocab.query_ids())
        #: What a predicted scene is trained to give (``core.forecast_targets``): as it is by default.
        self.forecast_target = forecast_target or (lambda context, codes: ForecastTarget(codes, None))
        self._track = SceneTrack()  # the scenes laid out so far and where the ego stands
        #: Per-sequence targets (see ``TokenSequence.targets``), set by a family's parts.
        self.targets: dict[str, torch.Tensor] = {}
        self._payload: list[dict[str, torch.Tensor]] = []
        self._ids: list[torch.Tensor] = []
        self._sup: list[torch.Tensor] = []
        self._seg: list[torch.Tensor] = []
        self._query_target: list[torch.Tensor] = []
        self._pos: list[torch.Tensor] = []
        self._branch: list[torch.Tensor] = []
        self._kept = 0  # tokens laid out so far, query blocks not counted
        self._blocks = 0
        self._branches = 0
        self._trunk_end: int | None = None  # the position where every branch starts
        self._branch_open = False  # the current branch has no token yet
        self.add(torch.tensor([vocab.bos_id]), False)

    # -- the extension point
    def add(
        self,
        ids: torch.Tensor,
        supervise: bool,
        seg: int = 0,
        query_target: torch.Tensor | None = None,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Append a run of tokens. ``seg`` > 0: a bidirectional block (``next_block``); < 0:
        a query block that takes the positions of what follows it and is seen by nothing
        after it; ``query_target``: the token each query output is trained to give;
        ``payload``: what the tokens carry beside their ids (the model's payload spec)."""
        n = ids.shape[0]
        self._payload.append(payload if payload is not None else empty_payload(self.payload_spec, n))
        if self._branch_open and supervise:
            # The trunk's last token cannot predict the first token of every branch at once.
            raise ValueError("a branch must start with a prompt part, not a supervised one")
        self._branch_open = False
        self._branch.append(torch.full((n,), self._branches, dtype=torch.long))
        self._ids.append(ids.long())
        self._sup.append(torch.full((n,), bool(supervise)))
        self._seg.append(torch.full((n,), seg, dtype=torch.long))
        self._query_target.append(
            query_target if query_target is not None else torch.full((n,), IGNORE, dtype=torch.long)
        )
        # A query block takes the positions of the code block that follows it (and replaces it in generation).
        self._pos.append(torch.arange(self._kept, self._kept + n))
        if seg >= 0:
            self._kept += n

    def next_block(self) -> int:
        """The segment number of a new bidirectional block (its query block takes minus it)."""
        self._blocks += 1
        return self._blocks

    def last_payload(self) -> dict[str, torch.Tensor]:
        """The payload of the last run added (a family may set a target on its last token)."""
        return self._payload[-1]

    # -- parts
    def lay(self, part: Part, inputs: PromptInputs, scenes: dict[int, torch.Tensor]) -> SequenceBuilder:
        """Lay one part out: text, a scene (its row in ``scenes``, by clip frame), actions,
        a branch. A family's builder lays its own kinds of part (images, occupancy queries,
        ...) from ``inputs``: the per-sample inputs its family registers, read by name."""
        if isinstance(part, Text):
            return self.text(part.text, part.supervise)
        if isinstance(part, Scene):
            return self.scene(scenes[part.frame], part.supervise)
        if isinstance(part, Actions):
            return self.actions(torch.tensor(part.xy, dtype=torch.float32), part.supervise, part.base)
        if isinstance(part, Branch):
            return self.branch()
        raise TypeError(
            f"{type(self).__name__} cannot lay out a {type(part).__name__} part; its world model's builder must"
        )

    def branch(self) -> SequenceBuilder:
        """Start a branch: the parts after it (up to the next branch) see what came before
        the first branch and themselves, not other branches, and their positions start
        where the trunk ends. Packs several prompts about one context into one sequence."""
        if self._trunk_end is None:
            self._trunk_end = self._kept
        self._kept = self._trunk_end
        self._branches += 1
        self._branch_open = True
        return self

    def text(self, text: str, supervise: bool = False) -> SequenceBuilder:
        self.add(torch.tensor(self.vocab.text_ids(text) + [self.vocab.eos_id]), supervise)
        return self

    def actions(
        self, xy: torch.Tensor, supervise: bool = False, base: tuple[tuple[float, float], ...] | None = None
    ) -> SequenceBuilder:
        """Waypoints ``xy`` (N, 2), written as their offsets from ``base`` when given."""
        v = self.vocab
        xy = torch.as_tensor(xy, dtype=torch.float32).cpu()
        self._track.planned(xy)
        written = xy if base is None else xy - torch.as_tensor(base, dtype=torch.float32).reshape(xy.shape)
        ids = torch.cat(
            [
                torch.tensor([v.act_open_id]),
                v.action_ids(written),
                torch.tensor([v.act_close_id]),
            ]
        )
        self.add(ids, supervise)
        return self

    def scene(self, codes: torch.Tensor, supervise: bool = False) -> SequenceBuilder:
        """A scene in the codes layout (see the module docstring)."""
        v = self.vocab
        codes = torch.as_tensor(codes).reshape(-1).long().cpu()
        if codes.numel() != v.scene_len:
            raise ValueError(f"a scene has {v.scene_len} codes, got {codes.numel()}")
        code_ids = v.occ_ids(codes)
        self.add(torch.tensor([v.occ_open_id]), supervise)
        if not self.next_scene:
            self.add(code_ids, supervise)
        else:
            block = self.next_block()
            if supervise:
                context = self._track.context()
                target = v.occ_ids(self.forecast_target(context, codes).codes)
                self.add(self.scene_queries(context), False, seg=-block, query_target=target)
            self.add(code_ids, False, seg=block)
        self.add(torch.tensor([v.occ_close_id]), supervise)
        self._track.scene(code_ids, predicted=supervise)
        return self

    def build(self) -> TokenSequence:
        ids, sup, seg = torch.cat(self._ids), torch.cat(self._sup), torch.cat(self._seg)
        branch = torch.cat(self._branch)
        query_target = torch.cat(self._query_target)
        is_query = seg < 0
        kept = (~is_query).nonzero().squeeze(1)
        labels = query_target.clone()
        # Each token predicts the next one of its own branch: the last token of a branch
        # has no target (its successor is another branch's first, unsupervised, token).
        same = branch[kept[1:]] == branch[kept[:-1]]
        labels[kept[:-1]] = torch.where(sup[kept[1:]] & same, ids[kept[1:]], IGNORE)
        return TokenSequence(
            ids,
            labels,
            seg,
            torch.cat(self._pos),
            self.vocab.is_occ(labels),
            branch,
            cat_payload(self._payload),
            dict(self.targets),
        )


def batch_payload(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The payload fields of a collated batch, by name."""
    return {k.removeprefix("payload_"): v for k, v in batch.items() if k.startswith("payload_")}


def _stack_targets(seqs: list[TokenSequence]) -> dict[str, torch.Tensor]:
    """Each per-sequence target stacked over the batch; zeros for a sequence without it."""
    out = {}
    for name in sorted({n for s in seqs for n in s.targets}):
        given = next(s.targets[name] for s in seqs if name in s.targets)
        out[name] = torch.stack([torch.as_tensor(s.targets.get(name, torch.zeros_like(given))) for s in seqs])
    return out


def collate(seqs: list[TokenSequence], pad_id: int, rows: list[list[int]] | None = None) -> dict[str, torch.Tensor]:
    """Lay sequences into a right-padded batch, one to a row or, packed, several.

    ``rows``: the sequences (indices into ``seqs``) each row holds, joined in that order
    (``core.packing.pack_rows``); by default one row each, in order. Returns ``input_ids``,
    ``labels`` (shifted targets, -100 on padding), ``segment_ids``, ``position_ids``,
    ``pad_mask`` (True on real tokens), ``scene_target_mask`` and ``attention_mask``:
    Bool[B, 1, L, L], True where attention is allowed (the model turns it into what its
    attention implementation takes), which keeps each packed sequence to itself;
    ``sample_index`` Long[B, L], the sequence of each token (-1 on padding) and
    ``sample_row`` Long[N], the row of each sequence, for per-sequence losses;
    ``payload_<name>`` per payload field and each per-sequence target by its name (only
    unpacked: a target belongs to a row).
    """
    rows = [[i] for i in range(len(seqs))] if rows is None else rows
    if sorted(i for row in rows for i in row) != list(range(len(seqs))):
        raise ValueError(f"rows {rows} do not hold each of the {len(seqs)} sequences once")
    packed = any(len(row) > 1 for row in rows)
    if packed and any(s.targets for s in seqs):
        raise ValueError("sequences with per-sequence targets cannot be packed: each target belongs to its row")
    lengths = [sum(len(seqs[i]) for i in row) for row in rows]
    L = max(lengths)

    def join(name: str, value: int) -> torch.Tensor:
        return torch.stack(
            [
                F.pad(torch.cat([getattr(seqs[i], name) for i in row]), (0, L - n), value=value)
                for row, n in zip(rows, lengths)
            ]
        )

    pad_mask = torch.stack([torch.arange(L) < n for n in lengths])
    sample_index, sample_row = _sample_indices(seqs, rows, L)
    segment_ids = join("segment_ids", 0)
    branch_ids = join("branch_ids", 0)
    payload = {}
    first = seqs[0].payload
    for name in first:  # padding rows are zeros: pad_mask keeps them out of every loss
        field_rows = torch.zeros((len(rows), L, *first[name].shape[1:]), dtype=first[name].dtype)
        for r, (row, n) in enumerate(zip(rows, lengths)):
            field_rows[r, :n] = torch.cat([seqs[i].payload[name] for i in row])
        payload[f"payload_{name}"] = field_rows
    return {
        **payload,
        "input_ids": join("input_ids", pad_id),
        "labels": join("labels", IGNORE),
        "segment_ids": segment_ids,
        "position_ids": join("position_ids", 0),
        "pad_mask": pad_mask,
        "scene_target_mask": join("scene_target", False),
        "attention_mask": allowed_pairs(segment_ids, pad_mask, branch_ids, sample_index if packed else None)[:, None],
        "sample_index": sample_index,
        "sample_row": sample_row,
        **_stack_targets([seqs[row[0]] for row in rows]),
    }


def _sample_indices(seqs: list[TokenSequence], rows: list[list[int]], length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each token's sequence, Long[B, length] (-1 on padding), and each sequence's row, Long[N]."""
    per_row = [torch.cat([torch.full((len(seqs[i]),), i) for i in row]) for row in rows]
    index = torch.stack([F.pad(ids, (0, length - len(ids)), value=-1) for ids in per_row])
    row_of = torch.empty(len(seqs), dtype=torch.long)
    for r, row in enumerate(rows):
        row_of[row] = r
    return index, row_of


def sample_means(sums: torch.Tensor, counts: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """Float[N]: each sequence's mean of a per-token quantity, packed or not: ``sums`` and
    ``counts`` are per token (B, L) (a loss summed at a position, the targets it holds)."""
    index, n = batch["sample_index"].to(sums.device), batch["sample_row"].shape[0]
    real = (index >= 0).to(sums.dtype)  # padding adds zero to sequence 0: no boolean indexing, no device sync
    at = index.clamp(min=0).flatten()
    total = sums.new_zeros(n).index_add(0, at, (sums * real).flatten())
    count = sums.new_zeros(n).index_add(0, at, (counts.to(sums.dtype) * real).flatten())
    return total / count.clamp(min=1)

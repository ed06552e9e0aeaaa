"""Greedy decoding with the KV cache: one program, two drivers.

The *program* says, answer after answer, which tokens to feed and what to choose from the
outputs: text one token at a time up to end-of-text, an ``<act>`` block of x/y bin pairs,
a scene (in "next_scene" mode one forward of a query block, whose outputs the world
model's scene writer turns into the scene's tokens; in "next_token" mode token by
token), a query block whose outputs are the answer and that nothing after it sees, or
more prompt tokens. Every choice is restricted to the id range of its kind, and chosen
tokens are fed lazily, with the next forward.

Two *drivers* run it: :class:`Decoder` one sequence at a time (its cache cropped after a
query block; ``use_cache=False`` recomputes the whole sequence at each forward, the
reference in tests), and :func:`decode_batch` many sequences at once (one batched forward
per step, padding masked, finished sequences dropped from the cache, prompts grouped by
length and a feed much longer than the others held back, so that padding never costs
more than batching saves). A world model supplies ``vocab``, ``payload_spec``,
``scene_prediction``, ``frame_separation``, ``scene_writer`` and ``step``.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import torch

from occtrain.core.ego_steps import SceneContext, SceneTrack
from occtrain.core.sequence import PayloadSpec, Step, TokenSequence, cat_payload, empty_payload, prompt_of, rows
from occtrain.core.vocab import JointVocab
from occtrain.models.attention import allowed_pairs, chunk_allowed, scene_segments

if TYPE_CHECKING:
    from transformers import Cache


class TextAnswer(NamedTuple):
    """Text up to end-of-text (with ``stop_at_eos``), at most ``max_new_tokens`` tokens."""

    max_new_tokens: int
    stop_at_eos: bool = True


class ActionAnswer(NamedTuple):
    """An ``<act>`` block of ``steps`` waypoints, read as offsets from ``base`` (steps, 2) when given."""

    steps: int
    base: tuple | None = None


class SceneAnswer(NamedTuple):
    """One scene (between ``<occ>`` and ``</occ>`` with frame separation)."""


class QueryBlock(NamedTuple):
    """``ids`` run as a query block after what is queued: its outputs (a :class:`Step`)
    are the answer, and nothing fed later sees it (OccVLA's occupancy queries)."""

    ids: torch.Tensor


class Feed(NamedTuple):
    """More prompt tokens (a laid-out sequence, with its payload), fed with the next forward."""

    tokens: TokenSequence


class Flush(NamedTuple):
    """Feed what is queued now (a forward of its own), before what follows."""


Answer = TextAnswer | ActionAnswer | SceneAnswer | QueryBlock | Feed | Flush


class SceneWriter(Protocol):
    """How a family writes a generated scene: from a query block's outputs at once or token
    by token, each giving the scene's ids so far and the extra payload they carry."""

    def from_queries(
        self, logits: torch.Tensor, hidden: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]: ...

    def next_token(
        self, logits: torch.Tensor, hidden: torch.Tensor | None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]: ...

    def codes(self) -> torch.Tensor: ...


class DecodingModel(Protocol):
    """What the decoder drives, one forward at a time (``core.lm_world_model.LMWorldModel``
    is one; the decoder sits below it and so names only this)."""

    vocab: JointVocab
    payload_spec: PayloadSpec
    frame_separation: bool
    scene_prediction: str

    @property
    def device(self) -> torch.device: ...

    def scene_query_ids(self, context: SceneContext) -> torch.Tensor: ...

    def scene_query_payload(self, context: SceneContext) -> dict[str, torch.Tensor] | None: ...

    def tracked_scene(self, ids: torch.Tensor, payload: dict[str, torch.Tensor]) -> torch.Tensor: ...

    def scene_writer(self, recent: torch.Tensor, waypoint: torch.Tensor | None = None) -> SceneWriter: ...

    def query_scene_writer(
        self, recent: torch.Tensor, queries: dict[str, torch.Tensor] | None, waypoint: torch.Tensor | None = None
    ) -> SceneWriter: ...

    def step(
        self,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        position_ids: torch.Tensor,
        past_key_values: Cache | None = None,
        use_cache: bool = False,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> Step: ...


class CodeScene:
    """How a generated scene is written in the joint vocabulary's codes layout: each
    position's code chosen within its codebook's id range, from the query block at once
    or token by token."""

    def __init__(self, vocab: JointVocab):
        self.vocab = vocab
        self.picked: list[torch.Tensor] = []

    def from_queries(self, logits: torch.Tensor, hidden: torch.Tensor | None) -> tuple[torch.Tensor, dict]:
        """The scene's ids (and payload) from the outputs at its Q query tokens."""
        self.picked = [self.vocab.pick_scene(logits)]
        return self.picked[0], {}

    def next_token(self, logits: torch.Tensor, hidden: torch.Tensor | None) -> tuple[torch.Tensor, dict]:
        """The next scene token (and its payload) from the output before it."""
        lo, hi = self.vocab.scene_token_range(sum(len(p) for p in self.picked))
        self.picked.append((logits[lo:hi].argmax(-1) + lo).reshape(1))
        return self.picked[-1], {}

    def codes(self) -> torch.Tensor:
        """The chosen scene's codes, flat and codebook-major."""
        return self.vocab.codes_from_ids(torch.cat(self.picked))


@dataclass
class Forward:
    """Tokens a program asks to feed (with their payload); the last ``transient`` are not kept."""

    ids: torch.Tensor
    seg: torch.Tensor
    payload: dict[str, torch.Tensor]
    transient: int = 0


Program = Generator[Forward, Step, Any]


class _State:
    """One sequence's decoding state: what is queued to feed, the last ids, the last output."""

    def __init__(self, world: DecodingModel, prefix: torch.Tensor | TokenSequence, device: torch.device):
        self.world, self.vocab, self.spec, self.device = world, world.vocab, world.payload_spec, device
        ids, payload = prompt_of(self.spec, prefix)
        ids = ids.to(device)
        self.next_scene = world.scene_prediction == "next_scene"
        seg = scene_segments(self.vocab.is_occ(ids)) if self.next_scene else torch.zeros_like(ids)
        self.queued: list[tuple[torch.Tensor, torch.Tensor, dict]] = [
            (ids, seg, {k: t.to(device) for k, t in payload.items()})
        ]
        self.next_segment = int(seg.max()) + 1 if seg.numel() else 1
        self.recent = ids[-3:]
        self.last: Step | None = None  # the output at the last kept token
        #: The scenes fed and generated and where the ego stands (what
        #: ``world.scene_query_ids`` reads), tracked as the sequence builder tracks them.
        self.track = SceneTrack()
        self.see_prompt(ids, payload)

    def see_prompt(self, ids: torch.Tensor, payload: dict[str, torch.Tensor]) -> None:
        """Prompt tokens were fed: their last whole scene, if any, is observed."""
        n = self.vocab.scene_len
        at = self.vocab.is_occ(ids).nonzero().squeeze(1)
        if n and at.numel() >= n:
            last = at[-n:]
            held = {k: v.to(self.device)[last] for k, v in payload.items()}
            self.track.scene(self.world.tracked_scene(ids[last], held), predicted=False)

    def queue(
        self, ids: list[int] | torch.Tensor, segment: int | torch.Tensor = 0, payload: dict | None = None
    ) -> None:
        ids = torch.as_tensor(ids, dtype=torch.long, device=self.device).reshape(-1)
        seg = segment.to(self.device) if torch.is_tensor(segment) else torch.full_like(ids, segment)
        extra = payload or empty_payload(self.spec, ids.numel(), self.device)
        self.queued.append((ids, seg, {k: v.to(self.device) for k, v in extra.items()}))
        self.recent = torch.cat([self.recent, ids])[-3:]

    def take(self) -> tuple[torch.Tensor, torch.Tensor, dict]:
        ids, segs, extras = zip(*self.queued)
        self.queued.clear()
        return torch.cat(ids), torch.cat(segs), cat_payload(list(extras))

    def output(self) -> Generator[Forward, Step, Step]:
        """The output at the last token, feeding what is queued first."""
        if self.queued or self.last is None:
            step = yield Forward(*self.take())
            self.last = Step(step.logits[-1], None, rows(step.hidden, -1))
        return self.last

    def pick(self, id_range: tuple[int, int]) -> Generator[Forward, Step, int]:
        """The greedy next id within ``id_range``."""
        lo, hi = id_range
        return int((yield from self.output()).logits[lo:hi].argmax()) + lo

    def pick_action(self, axis: int) -> Generator[Forward, Step, int]:
        """The next action bin of ``axis``, by the vocabulary's decoding rule."""
        return self.vocab.pick_action((yield from self.output()).logits, axis)


def _text(s: _State, answer: TextAnswer) -> Program:
    out: list[int] = []
    for _ in range(answer.max_new_tokens):
        tok = yield from s.pick(s.vocab.text_range)
        if answer.stop_at_eos and tok == s.vocab.eos_id:
            break
        out.append(tok)
        s.queue([tok])
    s.queue([s.vocab.eos_id])
    return out


def _actions(s: _State, answer: ActionAnswer) -> Program:
    v = s.vocab
    if int(s.recent[-1]) != v.act_open_id:
        s.queue([v.act_open_id])
    ids = []
    for _ in range(answer.steps):
        for axis in (0, 1):
            ids.append((yield from s.pick_action(axis)))
            s.queue(ids[-1:])
    s.queue([v.act_close_id])
    xy = v.actions_from_ids(torch.tensor(ids, dtype=torch.long)).reshape(answer.steps, 2)
    if answer.base is not None:
        xy = xy + torch.tensor(answer.base, dtype=xy.dtype).reshape(answer.steps, 2)
    s.track.planned(xy)
    return xy


def _query_block(s: _State, ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> Program:
    """Feed what is queued and then ``ids`` (with their ``payload``, by default the fill
    values) as a transient query block; its outputs."""
    queued, segs, extras = (
        s.take() if s.queued else (ids[:0].to(s.device), ids[:0].to(s.device), empty_payload(s.spec, 0, s.device))
    )
    ids = ids.to(s.device)
    n = len(ids)
    given = empty_payload(s.spec, n, s.device) if payload is None else {k: v.to(s.device) for k, v in payload.items()}
    extras = cat_payload([extras, given])
    step = yield Forward(torch.cat([queued, ids]), torch.cat([segs, torch.full_like(ids, -1)]), extras, n)
    s.last = None  # the kept tokens' last output is not needed again: what follows is fed
    return Step(step.logits[-n:], None, rows(step.hidden, slice(-n, None)))


def _scene(s: _State) -> Program:
    v, world = s.vocab, s.world
    recent = s.recent  # the ids before the scene (what its writer may read), before <occ>
    if world.frame_separation and int(s.recent[-1]) != v.occ_open_id:
        s.queue([v.occ_open_id])
    written: list[tuple[torch.Tensor, dict]] = []
    writer: SceneWriter
    if s.next_scene:
        # The query block the sequence builder lays out for the same context.
        context = s.track.context()
        queries = world.scene_query_payload(context)
        writer = world.query_scene_writer(recent, queries, s.track.waypoint)
        out = yield from _query_block(s, world.scene_query_ids(context), queries)
        scene_ids, extra = writer.from_queries(out.logits, out.hidden)
        s.queue(scene_ids, s.next_segment, extra)
        s.next_segment += 1
        written.append((scene_ids, extra))
    else:
        writer = world.scene_writer(recent, s.track.waypoint)
        for _ in range(v.scene_len):
            out = yield from s.output()
            scene_ids, extra = writer.next_token(out.logits, out.hidden)
            s.queue(scene_ids, 0, extra)
            written.append((scene_ids, extra))
    if world.frame_separation:
        s.queue([v.occ_close_id])
    ids, extras = zip(*written)
    s.track.scene(world.tracked_scene(torch.cat(ids), cat_payload(list(extras))), predicted=True)
    return writer.codes().cpu()


def answer_program(s: _State, answer: Answer) -> Program:
    """The program of one answer: text ids (list[int]), waypoints Float[steps, 2], a
    scene's codes (flat), a query block's outputs, or None (a feed or a flush)."""
    if isinstance(answer, TextAnswer):
        return (yield from _text(s, answer))
    if isinstance(answer, ActionAnswer):
        return (yield from _actions(s, answer))
    if isinstance(answer, SceneAnswer):
        return (yield from _scene(s))
    if isinstance(answer, QueryBlock):
        return (yield from _query_block(s, answer.ids))
    if isinstance(answer, Feed):
        ids, payload = prompt_of(s.spec, answer.tokens)
        s.queue(ids, 0, payload)
        s.see_prompt(ids.to(s.device), payload)
        return None
    if isinstance(answer, Flush):
        if s.queued:
            step = yield Forward(*s.take())
            s.last = Step(step.logits[-1], None, rows(step.hidden, -1))
        return None
    raise TypeError(f"not an answer kind: {answer!r}")


def program(
    world: DecodingModel, prefix: torch.Tensor | TokenSequence, answers: list[Answer], device: torch.device
) -> Program:
    """One sequence's whole decoding: its answers in order, each after the ones before."""
    state = _State(world, prefix, device)
    results = []
    for answer in answers:
        results.append((yield from answer_program(state, answer)))
    return results


class Decoder:
    """Drives the program for one sequence, answer by answer, with the KV cache (or, with
    ``use_cache=False``, recomputing the whole sequence at each forward)."""

    def __init__(self, world: DecodingModel, prefix: torch.Tensor | TokenSequence, use_cache: bool = True):
        self.world = world
        self.vocab: JointVocab = world.vocab
        self.use_cache = use_cache
        self.device = world.device
        self.state = _State(world, prefix, self.device)
        self.ids = torch.zeros(0, dtype=torch.long, device=self.device)
        self.seg = torch.zeros(0, dtype=torch.long, device=self.device)
        self.payload = empty_payload(world.payload_spec, 0, self.device)
        self.cache: Cache | None = None

    @property
    def last(self) -> Step | None:
        """The output at the last token fed (its logits, and hidden states where kept)."""
        return self.state.last

    def _forward(self, f: Forward) -> Step:
        """Feed ``f``'s tokens; its transient ones are cropped off the cache afterwards."""
        past, n, keep = self.ids.shape[0], f.ids.shape[0], f.ids.shape[0] - f.transient
        positions = torch.arange(past, past + n, device=self.device)[None]
        if self.use_cache:
            step = self.world.step(
                f.ids[None],
                chunk_allowed(f.seg, past)[:, None],
                positions,
                self.cache,
                True,
                {k: v[None] for k, v in f.payload.items()},
            )
            self.cache = step.cache
            if n > keep and self.cache is not None:
                self.cache.crop(-(n - keep))
        else:
            all_ids, all_seg = torch.cat([self.ids, f.ids]), torch.cat([self.seg, f.seg])
            payload = {k: torch.cat([self.payload[k], v])[None] for k, v in f.payload.items()}
            allowed = allowed_pairs(all_seg[None], torch.ones_like(all_seg[None], dtype=torch.bool))
            step = self.world.step(
                all_ids[None], allowed[:, None], torch.arange(past + n, device=self.device)[None], payload=payload
            )
            step = Step(step.logits[:, past:], None, rows(step.hidden, slice(None), slice(past, None)))
        self.ids, self.seg = torch.cat([self.ids, f.ids[:keep]]), torch.cat([self.seg, f.seg[:keep]])
        self.payload = cat_payload([self.payload, {k: v[:keep] for k, v in f.payload.items()}])
        return Step(step.logits[0], step.cache, rows(step.hidden, 0))

    @torch.no_grad()
    def answer(self, answer: Answer) -> Any:
        """Run one answer of the program (see :func:`answer_program`)."""
        prog = answer_program(self.state, answer)
        try:
            forward = next(prog)
            while True:
                forward = prog.send(self._forward(forward))
        except StopIteration as stop:
            return stop.value

    def text(self, max_new_tokens: int = 64, stop_at_eos: bool = True) -> list[int]:
        return self.answer(TextAnswer(max_new_tokens, stop_at_eos))

    def actions(self, steps: int = 6) -> torch.Tensor:
        return self.answer(ActionAnswer(steps))

    def scene(self) -> torch.Tensor:
        return self.answer(SceneAnswer())

    def flush(self) -> torch.Tensor:
        """Feed what is queued; the whole token stream so far, Long[n]."""
        self.answer(Flush())
        return self.ids


@torch.no_grad()
def decode(
    world: DecodingModel, prefix: torch.Tensor | TokenSequence, answers: list[Answer], use_cache: bool = True
) -> list:
    """Greedy answers after one prompt, in order (see :func:`answer_program`)."""
    decoder = Decoder(world, prefix, use_cache)
    return [decoder.answer(a) for a in answers]


def _nothing(f: Forward) -> Forward:
    """An empty feed: the row waits this step (all padding, nothing kept)."""
    return Forward(f.ids[:0], f.seg[:0], {k: v[:0] for k, v in f.payload.items()})


def _batched_forward(
    world: DecodingModel, feeds: list[Forward], cache: Any, alive: torch.Tensor, kept: torch.Tensor
) -> tuple[Step, torch.Tensor]:
    """One forward of every running sequence's feed, right-padded; the mask of the kept ones."""
    device = alive.device
    B, n = len(feeds), max(len(f.ids) for f in feeds)
    ids = torch.full((B, n), world.vocab.pad_id, dtype=torch.long, device=device)
    seg = torch.zeros(B, n, dtype=torch.long, device=device)
    real = torch.zeros(B, n, dtype=torch.bool, device=device)
    keep = torch.zeros(B, n, dtype=torch.bool, device=device)
    payload = {
        k: t.unsqueeze(0).repeat(B, *([1] * t.dim())) for k, t in empty_payload(world.payload_spec, n, device).items()
    }
    for i, f in enumerate(feeds):
        m = len(f.ids)
        ids[i, :m], seg[i, :m], real[i, :m] = f.ids, f.seg, True
        keep[i, : m - f.transient] = True
        for k, t in f.payload.items():
            payload[k][i, :m] = t
    positions = kept[:, None] + torch.arange(n, device=device)[None]
    inner = allowed_pairs(seg, real)
    mask = torch.cat([alive[:, None, :].expand(B, n, alive.shape[1]) & real[:, :, None], inner], dim=2)
    return world.step(ids, mask[:, None], positions, cache, use_cache=True, payload=payload), keep


#: A feed this many times longer than the shortest one waits (see :func:`_decode_group`).
WAIT_FACTOR = 2
#: Sequences share a batch while the longest prompt is at most this times the shortest.
PROMPT_SPREAD = 1.25


@torch.no_grad()
def decode_batch(world: DecodingModel, prefixes: list, answers: list[list[Answer]]) -> list[list]:
    """Greedy answers for every sequence of the batch: ``prefixes[b]`` (ids Long[L_b], or a
    laid-out sequence with its payload) is its prompt, ``answers[b]`` what to generate after
    it, in order. Returns, per sequence, a list with one entry per answer. A query block's
    keys stay in the batch's cache, masked for everything after it.

    Prompts of very different lengths decode in separate groups (by length): every row pays
    for the longest prompt of its batch, which could cost more than the batch saves."""
    lengths = [len(prompt_of(world.payload_spec, p)[0]) for p in prefixes]
    order = sorted(range(len(prefixes)), key=lengths.__getitem__)
    results: list[list | None] = [None] * len(prefixes)
    start = 0
    while start < len(order):
        end = start + 1
        while end < len(order) and lengths[order[end]] <= PROMPT_SPREAD * max(lengths[order[start]], 1):
            end += 1
        group = order[start:end]
        for b, out in zip(group, _decode_group(world, [prefixes[b] for b in group], [answers[b] for b in group])):
            results[b] = out
        start = end
    return _all_decoded(results)


def _all_decoded(results: list[list | None]) -> list[list]:
    """The answers of every prompt; a prompt left without one is a bug of the decoder."""
    missing = [b for b, r in enumerate(results) if r is None]
    if missing:
        raise RuntimeError(f"the decoder left prompts {missing} without an answer")
    return [r for r in results if r is not None]


def _decode_group(world: DecodingModel, prefixes: list, answers: list[list[Answer]]) -> list[list]:
    """:func:`decode_batch` on prompts of similar lengths. A step pads every row to the
    longest feed, so a feed much longer than the shortest (a query block beside one-token
    steps, once texts of different lengths put rows out of step) waits, fed as nothing,
    until the rows beside it catch up or finish."""
    device = world.device
    programs = [program(world, p, a, device) for p, a in zip(prefixes, answers)]
    first: list[Forward | None] = []
    results: list[list | None] = [None] * len(programs)
    for b, prog in enumerate(programs):
        try:
            first.append(next(prog))
        except StopIteration as stop:  # nothing to generate
            first.append(None)
            results[b] = stop.value
    #: The programs still running, by row of the cache; finished ones leave the batch.
    running_rows = [b for b, f in enumerate(first) if f is not None]
    feeds = [f for f in first if f is not None]
    kept = torch.zeros(len(feeds), dtype=torch.long, device=device)  # tokens kept so far: the next position
    alive = torch.zeros(len(feeds), 0, dtype=torch.bool, device=device)
    cache: Cache | None = None
    while running_rows:
        limit = WAIT_FACTOR * max(min(len(f.ids) for f in feeds), 1)
        waits = [len(f.ids) > limit for f in feeds]
        fed = [_nothing(f) if w else f for f, w in zip(feeds, waits)]
        step, keep = _batched_forward(world, fed, cache, alive, kept)
        cache = step.cache
        alive = torch.cat([alive, keep], dim=1)
        kept += keep.sum(1)
        sent: list[Forward | None] = list(feeds)
        for i, f in enumerate(fed):
            if waits[i]:
                continue
            try:
                sent[i] = programs[running_rows[i]].send(
                    Step(step.logits[i, : len(f.ids)], None, rows(step.hidden, i, slice(None, len(f.ids))))
                )
            except StopIteration as stop:
                sent[i] = None
                results[running_rows[i]] = stop.value
        running = [i for i, f in enumerate(sent) if f is not None]
        if len(running) < len(sent) and running and cache is not None:  # drop finished sequences from the cache
            index = torch.tensor(running, device=device)
            cache.batch_select_indices(index)
            alive, kept = alive[index], kept[index]
        running_rows, feeds = [running_rows[i] for i in running], [f for f in sent if f is not None]
    return _all_decoded(results)

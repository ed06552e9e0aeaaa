"""Greedy decoding of a whole batch at once, with the KV cache and the spatial-temporal mask.

Each sequence runs its own small program (a generator): it asks for tokens to be fed and
picks its next token from the logits it gets back, exactly as :class:`GreedyDecoder`
does for one sequence (tokens are queued and fed lazily with the next forward, a scene
in "next_scene" mode is one forward over the query block). :func:`decode_batch` steps all
programs in lockstep, one batched forward per step. Tokens carry the world model's per-token payload
(``tokens.PayloadSpec``; none for OccLLaMA) beside their ids, padded like them.

Sequences differ in length and in what they feed at a step (one text token here, a query
block of a whole scene's tokens there), so every forward is padded on the right and the padding is
masked out rather than shifted: a boolean ``alive`` row per sequence marks the cache
slots later tokens may attend to (real, kept tokens), and each sequence carries its own
position ids. Padding slots and the transient query blocks are never alive, which is
what cropping them off the cache does for a single sequence. A sequence that is done
leaves the batch (its cache rows are dropped), so long answers do not drag short ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generator, Union

import torch

from occtrain.families.occllama.tokens import Step, cat_payload, empty_payload, prompt_of
from occtrain.families.occllama.tokens import rows as hidden_rows  # `rows` names the cache rows below
from occtrain.models.attention import allowed_pairs, scene_segments


@dataclass(frozen=True)
class TextAnswer:
    """Text up to end-of-text, at most ``max_new_tokens`` tokens."""

    max_new_tokens: int


@dataclass(frozen=True)
class ActionAnswer:
    """An ``<act>`` block of ``steps`` waypoints."""

    steps: int


@dataclass(frozen=True)
class SceneAnswer:
    """One ``<occ>`` scene."""


Answer = Union[TextAnswer, ActionAnswer, SceneAnswer]


@dataclass
class _Feed:
    """Tokens a program asks to feed (with their payload); the last ``transient`` are not kept."""

    ids: torch.Tensor
    seg: torch.Tensor
    payload: dict[str, torch.Tensor]
    transient: int = 0


Program = Generator[_Feed, Step, list]


def _program(world, prefix, answers: list[Answer], device: torch.device) -> Program:
    """One sequence's greedy decoding (mirrors ``GreedyDecoder``); returns its answers:
    text ids (list[int]), waypoints Float[steps, 2] or scene codes (flat)."""
    v = world.vocab
    spec = world.payload_spec
    prefix, payload = prompt_of(spec, prefix)
    prefix = prefix.to(device)
    next_scene = world.scene_prediction == "next_scene"
    seg = scene_segments(v.is_occ(prefix)) if next_scene else torch.zeros_like(prefix)
    queued: list[tuple[torch.Tensor, torch.Tensor, dict]] = [(prefix, seg, {k: t.to(device) for k, t in payload.items()})]
    next_segment = int(seg.max()) + 1 if seg.numel() else 1
    recent = prefix[-3:]
    last: Step | None = None

    def queue(ids, segment: int = 0, extra: dict | None = None) -> None:
        nonlocal recent
        ids = torch.as_tensor(ids, dtype=torch.long, device=device).reshape(-1)
        queued.append((ids, torch.full_like(ids, segment), extra or empty_payload(spec, ids.numel(), device)))
        recent = torch.cat([recent, ids])[-3:]

    def take() -> tuple[torch.Tensor, torch.Tensor, dict]:
        ids, segs, extras = zip(*queued)
        queued.clear()
        return torch.cat(ids), torch.cat(segs), cat_payload(list(extras))

    def output() -> Generator[_Feed, Step, Step]:
        """The output at the last token, feeding what is queued first."""
        nonlocal last
        if queued or last is None:
            step = yield _Feed(*take())
            last = Step(step.logits[-1], None, hidden_rows(step.hidden, -1))
        return last

    def pick(id_range: tuple[int, int]) -> Generator[_Feed, Step, int]:
        """The greedy next id within ``id_range``."""
        lo, hi = id_range
        return int((yield from output()).logits[lo:hi].argmax()) + lo

    results: list = []
    for answer in answers:
        if isinstance(answer, TextAnswer):
            out: list[int] = []
            for _ in range(answer.max_new_tokens):
                tok = yield from pick(v.text_range)
                if tok == v.eos_id:
                    break
                out.append(tok)
                queue([tok])
            queue([v.eos_id])
            results.append(out)
        elif isinstance(answer, ActionAnswer):
            if int(recent[-1]) != v.act_open_id:
                queue([v.act_open_id])
            ids = []
            for _ in range(answer.steps):
                for id_range in (v.act_x_range, v.act_y_range):
                    ids.append((yield from pick(id_range)))
                    queue(ids[-1:])
            queue([v.act_close_id])
            results.append(v.actions_from_ids(torch.tensor(ids, dtype=torch.long)).reshape(answer.steps, 2))
        else:
            writer = world.scene_writer(recent)
            if world.frame_separation and int(recent[-1]) != v.occ_open_id:
                queue([v.occ_open_id])
            if next_scene:
                ids, segs, extras = take()
                queries = v.query_ids().to(device)
                n = len(queries)
                extras = cat_payload([extras, empty_payload(spec, n, device)])
                step = yield _Feed(torch.cat([ids, queries]), torch.cat([segs, torch.full_like(queries, -1)]), extras, n)
                last = None  # the kept tokens' last output is not needed again: a scene follows
                scene_ids, extra = writer.from_queries(step.logits[-n:], hidden_rows(step.hidden, slice(-n, None)))
                queue(scene_ids, next_segment, extra)
                next_segment += 1
            else:
                for _ in range(v.scene_len):
                    out_step = yield from output()
                    scene_ids, extra = writer.next_token(out_step.logits, out_step.hidden)
                    queue(scene_ids, 0, extra)
            if world.frame_separation:
                queue([v.occ_close_id])
            results.append(writer.codes().cpu())
    return results


@torch.no_grad()
def decode_batch(world, prefixes: list, answers: list[list[Answer]]) -> list[list]:
    """Greedy answers for every sequence of the batch: ``prefixes[b]`` (ids Long[L_b], or a
    laid-out sequence with its payload) is its prompt, ``answers[b]`` what to generate after
    it, in order. Returns, per sequence, a list with one entry per answer (see ``_program``)."""
    device = world.codebook.device
    programs = [_program(world, p, a, device) for p, a in zip(prefixes, answers)]
    feeds: list[_Feed | None] = []
    results: list[list | None] = [None] * len(programs)
    for b, prog in enumerate(programs):
        try:
            feeds.append(next(prog))
        except StopIteration as stop:  # nothing to generate
            feeds.append(None)
            results[b] = stop.value
    #: The programs still running, by row of the cache; finished ones leave the batch.
    rows = [b for b, f in enumerate(feeds) if f is not None]
    feeds = [feeds[b] for b in rows]
    B = len(rows)
    kept = torch.zeros(B, dtype=torch.long, device=device)  # tokens kept so far: the next position
    alive = torch.zeros(B, 0, dtype=torch.bool, device=device)
    cache = None
    pad = world.vocab.pad_id
    while rows:
        n = max(len(f.ids) for f in feeds)
        ids = torch.full((B, n), pad, dtype=torch.long, device=device)
        seg = torch.zeros(B, n, dtype=torch.long, device=device)
        real = torch.zeros(B, n, dtype=torch.bool, device=device)
        keep = torch.zeros(B, n, dtype=torch.bool, device=device)
        payload = {k: t.unsqueeze(0).repeat(B, *([1] * t.dim())) for k, t in empty_payload(world.payload_spec, n, device).items()}
        for i, f in enumerate(feeds):
            m = len(f.ids)
            ids[i, :m], seg[i, :m], real[i, :m] = f.ids, f.seg, True
            keep[i, : m - f.transient] = True
            for k, t in f.payload.items():
                payload[k][i, :m] = t
        positions = kept[:, None] + torch.arange(n, device=device)[None]
        inner = allowed_pairs(seg, real)
        mask = torch.cat([alive[:, None, :].expand(B, n, alive.shape[1]) & real[:, :, None], inner], dim=2)
        step = world.step(ids, mask[:, None], positions, cache, use_cache=True, payload=payload)
        cache = step.cache
        alive = torch.cat([alive, keep], dim=1)
        kept += keep.sum(1)
        for i, f in enumerate(feeds):
            try:
                feeds[i] = programs[rows[i]].send(Step(step.logits[i, : len(f.ids)], None, hidden_rows(step.hidden, i, slice(None, len(f.ids)))))
            except StopIteration as stop:
                feeds[i] = None
                results[rows[i]] = stop.value
        running = [i for i, f in enumerate(feeds) if f is not None]
        if len(running) < B and running:  # drop finished sequences from the cache
            index = torch.tensor(running, device=device)
            cache.batch_select_indices(index)
            alive, kept = alive[index], kept[index]
        rows, feeds, B = [rows[i] for i in running], [feeds[i] for i in running], len(running)
    return results

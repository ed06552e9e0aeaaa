"""OccLLaMA's unified world model: a causal LM over the joint vocabulary with
spatial-temporal attention and next-token-or-scene prediction (Sec. III-B, Algorithm 1).

Sequence layout. A sequence starts with ``bos``; then parts, each laid out as

- text: its tokens, then ``eos`` (every text part ends with it, so generated text, which
  stops at ``eos``, re-encodes to the same tokens when it becomes context);
- actions: ``<act> x_1 y_1 ... x_N y_N </act>`` (an x bin then a y bin per waypoint);
- a context scene: ``<occ> c_1 ... c_S </occ>`` with its S = h*w code tokens forming one
  bidirectional segment ("next_scene" mode) or plain causal tokens ("next_token" mode);
- a supervised scene in "next_scene" mode: ``<occ> q_1 ... q_S c_1 ... c_S </occ>``. The
  query block q (the learnable ``<scene_q_j>`` tokens) is bidirectional, sees everything
  before it, is seen by nothing after it, and its output at ``q_j`` is trained to give code
  ``c_j``: all of the scene from one forward pass. The code block c repeats the scene's
  real codes at the same positions (RoPE) as the queries, and is what later tokens attend
  to. This is Algorithm 1 at training time: there, the queries are appended after
  ``<occ>``, their outputs become the scene, and the scene then replaces the queries in
  the context. Generation does exactly that with the KV cache (the query keys are cropped
  off and the chosen codes fed instead).

Labels. ``labels[t]`` is the target of the output at position ``t`` (already shifted;
-100 where none): the next kept token when that token is supervised, and for a query
token its scene code. The model computes its own loss, so the HF ``labels`` convention is
never used. Every token of a supervised part is supervised except the code block behind a
query block (the queries predict it).

Occupancy inputs. The input embedding of ``<occ_k>`` is ``occ_proj(codebook[k])``, a
LayerNorm + two-layer GELU MLP (LLaVA-style projector) of the frozen scene tokenizer's
codebook vector, instead of the embedding-table row; the lm-head keeps one row per code.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.config.llm import SCENE_PREDICTION_MODES
from occtrain.families.occllama.batch_decoding import ActionAnswer, Answer, TextAnswer, decode_batch
from occtrain.models.attention import additive, allowed_pairs, chunk_allowed, scene_segments
from occtrain.families.occllama.tokens import IGNORE, PayloadSpec, Step, TokenSequence, cat_payload, empty_payload, prompt_of, rows
from occtrain.models.vocab import JointVocab

class SequenceBuilder:
    """Lays parts out in the joint vocabulary (see the module docstring).

    ``scene_prediction`` and ``payload_spec`` must be the model's (``world.builder()``
    gets them right).
    """

    def __init__(self, vocab: JointVocab, scene_prediction: str = "next_scene", payload_spec: PayloadSpec | None = None):
        if scene_prediction not in SCENE_PREDICTION_MODES:
            raise ValueError(f"scene_prediction must be one of {SCENE_PREDICTION_MODES}")
        self.vocab = vocab
        self.next_scene = scene_prediction == "next_scene"
        self.payload_spec = payload_spec or {}
        self._payload: list[dict[str, torch.Tensor]] = []
        self._ids: list[torch.Tensor] = []
        self._sup: list[torch.Tensor] = []
        self._seg: list[torch.Tensor] = []
        self._query_target: list[torch.Tensor] = []
        self._pos: list[torch.Tensor] = []
        self._branch: list[torch.Tensor] = []
        self._kept = 0  # tokens laid out so far, query blocks not counted
        self._scenes = 0
        self._branches = 0
        self._trunk_end: int | None = None  # the position where every branch starts
        self._branch_open = False  # the current branch has no token yet
        self._add(torch.tensor([vocab.bos_id]), False)

    def _add(
        self, ids: torch.Tensor, supervise: bool, seg: int = 0, query_target: torch.Tensor | None = None,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> None:
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
        self._query_target.append(query_target if query_target is not None else torch.full((n,), IGNORE, dtype=torch.long))
        # A query block takes the positions of the code block that follows it (and replaces it in generation).
        self._pos.append(torch.arange(self._kept, self._kept + n))
        if seg >= 0:
            self._kept += n

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
        self._add(torch.tensor(self.vocab.text_ids(text) + [self.vocab.eos_id]), supervise)
        return self

    def actions(self, xy: torch.Tensor, supervise: bool = False) -> SequenceBuilder:
        v = self.vocab
        ids = torch.cat([torch.tensor([v.act_open_id]), v.action_ids(torch.as_tensor(xy, dtype=torch.float32).cpu()), torch.tensor([v.act_close_id])])
        self._add(ids, supervise)
        return self

    def scene(self, codes: torch.Tensor, supervise: bool = False) -> SequenceBuilder:
        v = self.vocab
        codes = torch.as_tensor(codes).reshape(-1).long().cpu()
        if codes.numel() != v.scene_len:
            raise ValueError(f"a scene has {v.scene_len} codes (latent {v.scene_hw}), got {codes.numel()}")
        code_ids = v.occ_ids(codes)
        self._add(torch.tensor([v.occ_open_id]), supervise)
        if not self.next_scene:
            self._add(code_ids, supervise)
        else:
            self._scenes += 1
            if supervise:
                self._add(v.query_ids(), False, seg=-self._scenes, query_target=code_ids)
            self._add(code_ids, False, seg=self._scenes)
        self._add(torch.tensor([v.occ_close_id]), supervise)
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
        return TokenSequence(ids, labels, seg, torch.cat(self._pos), self.vocab.is_occ(labels), branch, cat_payload(self._payload))


def batch_payload(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The payload fields of a collated batch, by name."""
    return {k.removeprefix("payload_"): v for k, v in batch.items() if k.startswith("payload_")}


def _voxel_targets(seqs: list[TokenSequence]) -> dict[str, torch.Tensor]:
    """``voxels`` uint8 (B, X, Y, Z) and ``voxel_weight`` (B,), 0 for a sequence without
    occupancy queries; nothing when no sequence has them."""
    given = [s.voxels for s in seqs if s.voxels is not None]
    if not given:
        return {}
    zeros = torch.zeros_like(given[0])
    return {
        "voxels": torch.stack([s.voxels if s.voxels is not None else zeros for s in seqs]),
        "voxel_weight": torch.tensor([s.voxel_weight if s.voxels is not None else 0.0 for s in seqs]),
    }


def collate(seqs: list[TokenSequence], pad_id: int) -> dict[str, torch.Tensor]:
    """Right-pad sequences into a batch.

    Returns ``input_ids``, ``labels`` (shifted targets, -100 on padding), ``segment_ids``,
    ``position_ids``, ``pad_mask`` (True on real tokens), ``scene_target_mask`` and
    ``attention_mask``: Bool[B, 1, L, L], True where attention is allowed (the model turns
    it into what its attention implementation takes); ``voxels`` and ``voxel_weight`` when
    a sequence has occupancy queries (``_voxel_targets``).
    """
    L = max(len(s) for s in seqs)

    def pad(name: str, value) -> torch.Tensor:
        return torch.stack([F.pad(getattr(s, name), (0, L - len(s)), value=value) for s in seqs])

    pad_mask = torch.stack([torch.arange(L) < len(s) for s in seqs])
    segment_ids = pad("segment_ids", 0)
    branch_ids = pad("branch_ids", 0)
    payload = {}
    for name in seqs[0].payload:  # padding rows are zeros: pad_mask keeps them out of every loss
        rows = torch.zeros((len(seqs), L, *seqs[0].payload[name].shape[1:]), dtype=seqs[0].payload[name].dtype)
        for b, s in enumerate(seqs):
            rows[b, : len(s)] = s.payload[name]
        payload[f"payload_{name}"] = rows
    return {
        **payload,
        "input_ids": pad("input_ids", pad_id),
        "labels": pad("labels", IGNORE),
        "segment_ids": segment_ids,
        "position_ids": pad("position_ids", 0),
        "pad_mask": pad_mask,
        "scene_target_mask": pad("scene_target", False),
        "attention_mask": allowed_pairs(segment_ids, pad_mask, branch_ids)[:, None],
        **_voxel_targets(seqs),
    }


class CodeScene:
    """How a generated scene is written in the codes layout: each position's code chosen
    within its codebook's id range, from the query block at once or token by token."""

    def __init__(self, vocab: JointVocab):
        self.vocab = vocab
        self.picked: list[torch.Tensor] = []

    def from_queries(self, logits: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """The scene's ids (and payload) from the outputs at its Q query tokens."""
        self.picked = [self.vocab.pick_scene(logits)]
        return self.picked[0], {}

    def next_token(self, logits: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """The next scene token (and its payload) from the output before it."""
        lo, hi = self.vocab.scene_token_range(sum(len(p) for p in self.picked))
        self.picked.append((logits[lo:hi].argmax(-1) + lo).reshape(1))
        return self.picked[-1], {}

    def codes(self) -> torch.Tensor:
        """The chosen scene's codes, flat and codebook-major."""
        return self.vocab.codes_from_ids(torch.cat(self.picked))


@dataclass
class WorldModelOutput:
    loss: torch.Tensor
    text_loss: torch.Tensor
    scene_loss: torch.Tensor
    logits: torch.Tensor
    #: Last-layer hidden states (B, L, hidden), when asked for (feature distillation).
    hidden: torch.Tensor | None = None
    #: Mean cross-entropy of each sequence over its own targets, (B,).
    sample_loss: torch.Tensor | None = None


class OccWorldModel(nn.Module):
    """The LLM, the joint vocabulary and the occupancy input projection.

    ``codebook`` Float[K, code_dim] is the frozen scene tokenizer's codebook (its codebooks
    stacked, in the vocabulary's order, when it has several); it is a non-persistent buffer (the tokenizer's export owns it), the projection is trained.
    """

    #: Per-token extras beside the ids (see ``PayloadSpec``): none here.
    payload_spec: PayloadSpec = {}
    #: Scenes are wrapped in ``<occ>`` ... ``</occ>`` (Occ-LLM's frame separation can drop them).
    frame_separation = True

    def __init__(self, llm: nn.Module, vocab: JointVocab, codebook: torch.Tensor, scene_prediction: str = "next_scene"):
        super().__init__()
        if scene_prediction not in SCENE_PREDICTION_MODES:
            raise ValueError(f"scene_prediction must be one of {SCENE_PREDICTION_MODES}")
        if codebook.shape[0] != vocab.num_codes:
            raise ValueError(f"codebook has {codebook.shape[0]} codes, the vocabulary {vocab.num_codes}")
        self.llm = llm
        self.vocab = vocab
        self.scene_prediction = scene_prediction
        self.register_buffer("codebook", codebook.detach().float().clone(), persistent=False)
        hidden = llm.get_input_embeddings().embedding_dim
        dim = codebook.shape[1]
        self.occ_proj = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden))

    # -- building blocks
    def builder(self) -> SequenceBuilder:
        return SequenceBuilder(self.vocab, self.scene_prediction, self.payload_spec)

    def scene_writer(self, recent: torch.Tensor) -> CodeScene:
        """What writes the next generated scene; ``recent`` are the last ids before it."""
        return CodeScene(self.vocab)

    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Input embeddings; occupancy tokens through the codebook projection (the codebooks
        stacked in the vocabulary's order, so a token's offset is its row)."""
        emb = self.llm.get_input_embeddings()(input_ids)
        table = self.occ_proj(self.codebook).to(emb.dtype)
        codes = (input_ids - self.vocab.occ_start).clamp(0, self.vocab.num_codes - 1)
        # F.embedding, not table[codes]: indexing's backward accumulates rows with
        # index_put_, whose order across CPU threads varies run to run, so a resumed run
        # would drift from an uninterrupted one in the last bits.
        return torch.where(self.vocab.is_occ(input_ids)[..., None], F.embedding(codes, table), emb)

    def _mask(self, allowed: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """Bool[B, 1, Lq, Lk] -> what the attention implementation takes: torch SDPA takes
        the boolean mask for any compute dtype (bf16 autocast included); eager adds a float one."""
        impl = getattr(self.llm.config, "_attn_implementation", "sdpa")
        return allowed if impl == "sdpa" else additive(allowed[:, 0], dtype)

    def _run(self, input_ids, attention_mask, position_ids, past_key_values=None, use_cache=False, hidden=False, payload=None):
        emb = self.embed(input_ids, payload)
        return self.llm(
            inputs_embeds=emb,
            attention_mask=self._mask(attention_mask, emb.dtype),
            position_ids=position_ids,
            past_key_values=past_key_values,
            use_cache=use_cache,
            output_hidden_states=hidden,
        )

    def step(self, input_ids, attention_mask, position_ids, past_key_values=None, use_cache=False, payload=None) -> Step:
        """The LLM's output for ``input_ids`` (and their payload) under a boolean 4D mask."""
        # Only a model with a payload emits scenes from hidden states: the others skip keeping every layer's.
        hidden = bool(self.payload_spec)
        out = self._run(input_ids, attention_mask, position_ids, past_key_values, use_cache, hidden=hidden, payload=payload)
        return Step(out.logits, out.past_key_values, out.hidden_states[-1] if hidden else None)

    def forward(self, batch: dict[str, torch.Tensor], output_hidden_states: bool = False) -> WorldModelOutput:
        """Cross-entropy over all targets (one uniform loss, as in the paper); the text
        (text + action + marker) and scene parts are reported apart."""
        out = self._run(batch["input_ids"], batch["attention_mask"], batch["position_ids"], hidden=output_hidden_states, payload=batch_payload(batch))
        logits = out.logits
        labels = batch["labels"]
        ce = F.cross_entropy(logits.flatten(0, 1).float(), labels.flatten(), ignore_index=IGNORE, reduction="none").view_as(labels)
        valid = labels != IGNORE
        scene = batch["scene_target_mask"] & valid
        text = valid & ~scene

        def mean(sel: torch.Tensor) -> torch.Tensor:
            return (ce * sel).sum() / sel.sum().clamp(min=1)

        hidden = out.hidden_states[-1] if output_hidden_states else None
        per_sample = (ce * valid).sum(1) / valid.sum(1).clamp(min=1)
        return WorldModelOutput(mean(valid), mean(text), mean(scene), logits, hidden, per_sample)

    @staticmethod
    def token_accuracy(logits: torch.Tensor, labels: torch.Tensor, select: torch.Tensor | None = None) -> torch.Tensor:
        """Fraction of targets (``labels`` != -100, and ``select``) whose argmax is right."""
        valid = labels != IGNORE
        if select is not None:
            valid = valid & select
        hits = (logits.argmax(-1) == labels) & valid
        return hits.sum().float() / valid.sum().clamp(min=1)

    # -- generation
    def decoder(self, prefix: torch.Tensor | TokenSequence, use_cache: bool = True) -> GreedyDecoder:
        """A greedy decoder after ``prefix``: ids, or a laid-out sequence with its payload."""
        return GreedyDecoder(self, prefix, use_cache)

    @torch.no_grad()
    def generate_batch(self, prefixes: list[torch.Tensor | TokenSequence], answers: list[list]) -> list[list]:
        """Greedy answers for a batch of prompts at once (see ``batch_decoding``)."""
        return decode_batch(self, prefixes, answers)

    @torch.no_grad()
    def generate_text(self, prefix_ids: torch.Tensor, max_new_tokens: int = 64, eos: int | None = None) -> str:
        """Greedy text after ``prefix_ids`` (Long[L]), up to ``eos``."""
        return self.vocab.decode_text(self.decoder(prefix_ids).text(max_new_tokens, eos))

    @torch.no_grad()
    def generate_actions(self, prefix_ids: torch.Tensor, steps: int = 6) -> torch.Tensor:
        """Greedy ``<act>`` block after ``prefix_ids``: Float[steps, 2] waypoints (metres)."""
        return self.decoder(prefix_ids).actions(steps)

    @torch.no_grad()
    def generate_scene(self, prefix_ids: torch.Tensor) -> torch.Tensor:
        """Greedy ``<occ>`` scene after ``prefix_ids``: its codes, flat and codebook-major."""
        return self.decoder(prefix_ids).scene()

    @property
    def hidden_size(self) -> int:
        return self.llm.get_input_embeddings().embedding_dim

    # -- export
    def _base_llm(self) -> nn.Module:
        return self.llm.get_base_model() if hasattr(self.llm, "get_base_model") else self.llm

    def export_config(self) -> dict:
        """JSON-able settings from which ``from_export`` rebuilds the model around its LLM."""
        base = self._base_llm()
        return {
            "attn_implementation": getattr(base.config, "_attn_implementation", "sdpa"),
            "scene_prediction": self.scene_prediction,
            "code_dim": int(self.codebook.shape[1]),
        }

    @classmethod
    def create(cls, llm: nn.Module, vocab: JointVocab, scene_tokenizer: nn.Module, scene_prediction: str, world_cfg=None) -> OccWorldModel:
        """A fresh model around ``llm`` over a frozen scene tokenizer (pretraining's start)."""
        return cls(llm, vocab, torch.cat(scene_tokenizer.codebooks), scene_prediction)

    @staticmethod
    def vocab_patch(world_cfg=None) -> int:
        """The vocabulary's patch side: 0, one token per latent cell and codebook."""
        return 0

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, scene_tokenizer: nn.Module) -> OccWorldModel:
        """The exported architecture around ``llm`` (loaded from the export's Hugging Face
        directory); load the export's own weights next."""
        return cls(llm, vocab, torch.cat(scene_tokenizer.codebooks), data["scene_prediction"])

    def scene_token_rows(self) -> torch.Tensor:
        """What the scene tokens' input embeddings are (their rows of an exported LLM's
        embedding table, so plain transformers reads them too)."""
        return self.occ_proj(self.codebook)


class GreedyDecoder:
    """Greedy decoding of one sequence with the KV cache, part after part.

    The prefix's scenes are found as runs of scene tokens. Chosen tokens are fed lazily,
    with the next forward, so a part costs: text one forward per token; actions two per
    waypoint; a scene one forward in "next_scene" mode (``<occ>`` + the query block; the
    query keys are then cropped off the cache and the chosen tokens fed with the next call)
    and one per scene token in "next_token" mode. Every choice is restricted to the id
    range of its kind; the world model's scene writer chooses scene tokens (and their
    payload). ``use_cache=False`` recomputes the whole sequence at each forward (for testing).
    """

    def __init__(self, world: OccWorldModel, prefix: torch.Tensor | TokenSequence, use_cache: bool = True):
        self.world = world
        self.vocab = world.vocab
        self.use_cache = use_cache
        self.device = world.codebook.device
        prefix, payload = prompt_of(world.payload_spec, prefix)
        prefix = prefix.to(self.device)
        seg = scene_segments(self.vocab.is_occ(prefix)) if world.scene_prediction == "next_scene" else torch.zeros_like(prefix)
        self.ids, self.seg, self.payload = prefix[:0], seg[:0], {k: v[:0].to(self.device) for k, v in payload.items()}
        self.pending_ids, self.pending_seg = prefix, seg
        self.pending_payload = {k: v.to(self.device) for k, v in payload.items()}
        self.next_segment = int(seg.max()) + 1 if seg.numel() else 1
        self.cache = None
        self.last: Step | None = None  # the output at the last kept token

    def _queue(self, ids: list[int] | torch.Tensor, seg: int | torch.Tensor = 0, payload: dict | None = None) -> None:
        ids = torch.as_tensor(ids, dtype=torch.long, device=self.device).reshape(-1)
        seg = seg if torch.is_tensor(seg) else torch.full_like(ids, seg)
        self.pending_ids = torch.cat([self.pending_ids, ids])
        self.pending_seg = torch.cat([self.pending_seg, seg.to(self.device)])
        extra = payload or empty_payload(self.world.payload_spec, ids.numel(), self.device)
        self.pending_payload = cat_payload([self.pending_payload, {k: v.to(self.device) for k, v in extra.items()}])

    def _recent(self) -> torch.Tensor:
        return torch.cat([self.ids, self.pending_ids])[-3:]

    def _advance(self, transient: torch.Tensor | None = None, transient_seg: int = -1) -> Step:
        """Feed the pending tokens, then ``transient`` ones that are not kept; outputs of all fed."""
        ids, seg, payload = self.pending_ids, self.pending_seg, self.pending_payload
        keep = ids.shape[0]
        if transient is not None:
            transient = transient.to(self.device)
            ids = torch.cat([ids, transient])
            seg = torch.cat([seg, torch.full_like(transient, transient_seg)])
            payload = cat_payload([payload, empty_payload(self.world.payload_spec, transient.numel(), self.device)])
        past = self.ids.shape[0]
        n = ids.shape[0]
        positions = torch.arange(past, past + n, device=self.device)[None]
        batch_payload = {k: v[None] for k, v in payload.items()}
        if self.use_cache:
            step = self.world.step(ids[None], chunk_allowed(seg, past)[:, None], positions, self.cache, True, batch_payload)
            self.cache = step.cache
            if n > keep:
                self.cache.crop(-(n - keep))
        else:
            all_ids, all_seg = torch.cat([self.ids, ids]), torch.cat([self.seg, seg])
            full_payload = {k: torch.cat([self.payload[k], v])[None] for k, v in payload.items()}
            allowed = allowed_pairs(all_seg[None], torch.ones_like(all_seg[None], dtype=torch.bool))
            full = torch.arange(past + n, device=self.device)[None]
            step = self.world.step(all_ids[None], allowed[:, None], full, payload=full_payload)
            step = Step(step.logits[:, past:], None, rows(step.hidden, slice(None), slice(past, None)))
        step = Step(step.logits[0], step.cache, rows(step.hidden, 0))
        self.ids, self.seg = torch.cat([self.ids, ids[:keep]]), torch.cat([self.seg, seg[:keep]])
        self.payload = cat_payload([self.payload, {k: v[:keep] for k, v in payload.items()}])
        self.pending_ids, self.pending_seg = ids[:0], seg[:0]
        self.pending_payload = {k: v[:0] for k, v in payload.items()}
        if keep:
            self.last = Step(step.logits[keep - 1], None, rows(step.hidden, keep - 1))
        return step

    def feed(self, ids: torch.Tensor, payload: dict | None = None) -> None:
        """Queue more prompt tokens (with their payload), fed with the next forward."""
        self._queue(ids, 0, payload)

    def side_block(self, ids: torch.Tensor) -> Step:
        """Feed what is queued, then ``ids`` as a query block (segment -1) that is cropped
        off the cache afterwards, so nothing fed later sees it; the outputs of all fed."""
        return self._advance(ids, transient_seg=-1)

    def flush(self) -> torch.Tensor:
        """Feed what is queued; the whole token stream so far, Long[n]."""
        if self.pending_ids.numel():
            self._advance()
        return self.ids

    def _output(self) -> Step:
        """The output at the last token, feeding what is queued first."""
        if self.pending_ids.numel() or self.last is None:
            self._advance()
        return self.last

    def _pick(self, lo_hi: tuple[int, int]) -> torch.Tensor:
        lo, hi = lo_hi
        return self._output().logits[lo:hi].argmax(-1) + lo

    def answer(self, answer: Answer) -> list[int] | torch.Tensor:
        """One answer of a task: text ids, waypoints Float[steps, 2] or scene codes (flat)."""
        if isinstance(answer, TextAnswer):
            return self.text(answer.max_new_tokens)
        if isinstance(answer, ActionAnswer):
            return self.actions(answer.steps)
        return self.scene()

    @torch.no_grad()
    def text(self, max_new_tokens: int = 64, eos: int | None = None) -> list[int]:
        """Text token ids up to ``eos`` (excluded); ``eos`` is queued after them either way."""
        eos = self.vocab.eos_id if eos is None else eos
        out: list[int] = []
        for _ in range(max_new_tokens):
            tok = int(self._pick(self.vocab.text_range))
            if tok == eos:
                break
            out.append(tok)
            self._queue([tok])
        self._queue([eos])
        return out

    @torch.no_grad()
    def actions(self, steps: int = 6) -> torch.Tensor:
        """``<act>`` (unless the sequence ends with it), ``steps`` x/y bin pairs, ``</act>``."""
        v = self.vocab
        if int(self._recent()[-1]) != v.act_open_id:
            self._queue([v.act_open_id])
        ids = []
        for _ in range(steps):
            for rng in (v.act_x_range, v.act_y_range):
                ids.append(int(self._pick(rng)))
                self._queue(ids[-1:])
        self._queue([v.act_close_id])
        return v.actions_from_ids(torch.tensor(ids, dtype=torch.long)).reshape(steps, 2)

    @torch.no_grad()
    def scene(self) -> torch.Tensor:
        """``<occ>`` (unless the sequence ends with it), one scene, ``</occ>`` (markers only
        with frame separation); the scene's codes, flat and codebook-major."""
        v = self.vocab
        writer = self.world.scene_writer(self._recent())
        separate = self.world.frame_separation
        if separate and int(self._recent()[-1]) != v.occ_open_id:
            self._queue([v.occ_open_id])
        if self.world.scene_prediction == "next_scene":
            queries = v.query_ids()
            step = self._advance(queries, transient_seg=-1)
            ids, payload = writer.from_queries(step.logits[-len(queries):], rows(step.hidden, slice(-len(queries), None)))
            self._queue(ids, torch.full_like(ids, self.next_segment), payload)
            self.next_segment += 1
        else:
            for _ in range(v.scene_len):
                out = self._output()
                ids, payload = writer.next_token(out.logits, out.hidden)
                self._queue(ids, 0, payload)
        if separate:
            self._queue([v.occ_close_id])
        return writer.codes().cpu()

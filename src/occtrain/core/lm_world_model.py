"""The base of every family's world model: a causal LM over the joint vocabulary.

:class:`LMWorldModel` holds the LLM (any Hugging Face causal LM the backend drives), the
joint vocabulary and the scene-prediction mode; it runs the LLM under the boolean 4D
attention masks the sequences carry, computes the one cross-entropy over every target,
and generates through the decoding program (``core.decoding``). A family subclasses it,
calls its ``__init__`` and adds what its own tokens need: how they are embedded
(``embed``), laid out (``builder``), written when generated (``scene_writer``), what a
predicted scene's query block holds (``scene_query_ids``, ``scene_query_payload``), what they
carry beside their ids (``payload_spec``), extra loss terms (``forward``), and how it is
rebuilt from an export (``create``, ``from_export``, ``export_config``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import nn
from transformers import PreTrainedModel

from occtrain.config.llm import SCENE_PREDICTION_MODES
from occtrain.core.builder import SequenceBuilder, batch_payload, sample_means
from occtrain.core.decoding import (
    ActionAnswer,
    Answer,
    Decoder,
    SceneAnswer,
    SceneWriter,
    TextAnswer,
    decode,
    decode_batch,
)
from occtrain.core.ego_steps import SceneContext, query_source
from occtrain.core.forecast_targets import ForecastTarget, canonical_codes, mover_cells
from occtrain.core.protocols import SceneMover
from occtrain.core.sequence import IGNORE, PayloadSpec, Step, TokenSequence
from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig
from occtrain.core.vocab import JointVocab
from occtrain.models import without_peft
from occtrain.models.attention import additive

if TYPE_CHECKING:
    from transformers import Cache
    from transformers.modeling_outputs import CausalLMOutputWithPast


def token_ce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Per-token cross-entropy (B, L) of ``logits`` (B, L, V) against ``labels`` (0 where IGNORE)."""
    return F.cross_entropy(
        logits.flatten(0, 1).float(), labels.flatten(), ignore_index=IGNORE, reduction="none"
    ).view_as(labels)


@dataclass
class WorldInputs:
    """The frozen models a world model is built over: its scene encoder (a
    ``core.protocols.SceneEncoder``, None when its prompts hold no scenes) and the camera
    encoder of a model that reads the cameras (None otherwise)."""

    scene: Any = None
    vision: Any = None


@dataclass
class WorldModelOutput:
    loss: torch.Tensor
    text_loss: torch.Tensor
    scene_loss: torch.Tensor
    logits: torch.Tensor
    #: Last-layer hidden states (B, L, hidden), when asked for (feature distillation).
    hidden: torch.Tensor | None = None
    #: Mean cross-entropy of each sequence over its own targets, (N,) in the order the
    #: sequences were collated (a packed row holds several).
    sample_loss: torch.Tensor | None = None


class LMWorldModel(nn.Module):
    """An LLM over the joint vocabulary (see the module docstring)."""

    #: Per-token extras beside the ids (see ``PayloadSpec``): none by default.
    payload_spec: PayloadSpec = {}
    #: Scenes are wrapped in ``<occ>`` ... ``</occ>``.
    frame_separation = True
    #: Its prompts hold scenes (through the engine's scene encoder): the engine caches them.
    reads_scenes = True
    #: Its training sequences may share a batch row (``core.packing``): every loss term is
    #: per token. Not for a model whose sequences carry per-sequence ``targets``, read by row.
    packs_sequences = True
    #: Under a LoRA adapter its own parts (everything but the LLM) train too; by default
    #: only the adapter does.
    trains_own_parts_with_lora = False
    #: Moves a scene by the ego through the frozen scene encoder (``SceneMover``),
    #: for query blocks that read it; the engine that holds the encoder sets it.
    scene_mover: SceneMover | None = None
    #: What a predicted scene's query block carries (``core.ego_steps.SCENE_QUERIES``).
    scene_queries: str = "learned"
    #: The causal LM (a transformers model, LoRA-wrapped by peft or not).
    llm: PreTrainedModel
    _device_probe: torch.Tensor

    def __init__(self, llm: PreTrainedModel, vocab: JointVocab, scene_prediction: str = "next_scene"):
        super().__init__()
        if scene_prediction not in SCENE_PREDICTION_MODES:
            raise ValueError(f"scene_prediction must be one of {SCENE_PREDICTION_MODES}")
        self.llm = llm
        self.vocab = vocab
        self.scene_prediction = scene_prediction
        # Follows the model across devices: the decoders put their tensors where it is.
        self.register_buffer("_device_probe", torch.zeros(0), persistent=False)

    @property
    def device(self) -> torch.device:
        return self._device_probe.device

    @property
    def hidden_size(self) -> int:
        embeddings = self.llm.get_input_embeddings()
        assert isinstance(embeddings, nn.Embedding)
        return embeddings.embedding_dim

    # -- what a family overrides
    def builder(self) -> SequenceBuilder:
        return SequenceBuilder(
            self.vocab, self.scene_prediction, self.payload_spec, self.scene_query_ids, self.forecast_target
        )

    def scene_query_ids(self, context: SceneContext) -> torch.Tensor:
        """The query block of a scene predicted at once ("next_scene" mode), given what came
        before it (``core.ego_steps.SceneContext``: the scene before, the last observed
        scene, the ego's moves since them): the learnable ``<scene_q_j>`` tokens. Training
        and generation both ask here."""
        return self.vocab.query_ids()

    def scene_query_payload(self, context: SceneContext) -> dict[str, torch.Tensor] | None:
        """What the query block of ``scene_query_ids`` carries beside its ids (the patches
        layout: the cells of a scene it holds, ``core.patch_layout``), or None: every payload
        field at its fill value. Training and generation both ask here."""
        return None

    def raw_codes(self, tracked: torch.Tensor) -> torch.Tensor:
        """A scene as ``tracked_scene`` keeps it -> its raw codes (flat, codebook-major)."""
        return self.vocab.codes_from_ids(tracked.detach().cpu())

    def forecast_target(self, context: SceneContext, target: torch.Tensor) -> ForecastTarget:
        """What a predicted scene (raw codes ``target``) is trained to give, given what its
        query block carries (``core.forecast_targets``): its codes with the query's wherever
        the scene under a cell did not change, and the cells where an agent moved; as it is
        (no movers known) when the query carries no scene or either has no labels."""
        made = query_source(self.scene_queries, context)
        mover = self.scene_mover
        if made is None or mover is None:
            return ForecastTarget(target, None)
        source, step = made
        if step is None:  # an unmoved query: nothing of the ego's move to separate
            return ForecastTarget(target, None)
        raw = self.raw_codes(source)
        query_labels, target_labels = mover.labels(raw, step), mover.labels(target, None)
        if query_labels is None or target_labels is None:
            return ForecastTarget(target, None)
        hw = self.vocab.scene_hw
        query = mover.codes(raw, step)
        codes = canonical_codes(query, target, query_labels, target_labels, self.vocab.num_codebooks, hw)
        return ForecastTarget(codes.to(target.device), mover_cells(query_labels, target_labels, hw))

    def tracked_scene(self, ids: torch.Tensor, payload: dict[str, torch.Tensor]) -> torch.Tensor:
        """What ``core.ego_steps.SceneTrack`` keeps of a scene laid out or generated as these
        tokens (and their payload), for the query blocks after it: its code ids."""
        return ids

    def scene_writer(self, recent: torch.Tensor, waypoint: torch.Tensor | None = None) -> SceneWriter:
        """What writes the next generated scene; ``recent`` are the last ids before it,
        ``waypoint`` the last one laid out or generated, its plan prior added back
        (``SceneTrack.waypoint``), which bins that wrote an offset cannot say."""
        raise ValueError(f"the {type(self).__name__} world model generates no scenes")

    def query_scene_writer(
        self, recent: torch.Tensor, queries: dict[str, torch.Tensor] | None, waypoint: torch.Tensor | None = None
    ) -> SceneWriter:
        """What writes the next generated scene from a query block that carried ``queries``
        (``scene_query_payload``'s): by default the scene writer, which reads only outputs."""
        return self.scene_writer(recent, waypoint)

    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Input embeddings: the LLM's own table (a family embeds its own tokens)."""
        return self.llm.get_input_embeddings()(input_ids)

    def pool_images(self, tokens: torch.Tensor, grid: tuple[int, int], views: int) -> torch.Tensor:
        """A camera encoder's patch tokens (B, views * h * w, D) -> the image tokens this
        model reads (a model that reads cameras says how it pools them)."""
        raise ValueError(f"the {type(self).__name__} world model reads no camera images")

    def scene_token_rows(self) -> torch.Tensor | None:
        """The scene tokens' input embeddings to write into an exported LLM's table (so plain
        transformers reads them too), or None when they come from a payload."""
        return None

    # -- running the LLM
    def _mask(self, allowed: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """Bool[B, 1, Lq, Lk] -> what the attention implementation takes: torch SDPA takes
        the boolean mask for any compute dtype (bf16 autocast included); eager adds a float one."""
        impl = getattr(self.llm.config, "_attn_implementation", "sdpa")
        return allowed if impl == "sdpa" else additive(allowed[:, 0], dtype)

    def _run(
        self,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        position_ids: torch.Tensor,
        past_key_values: Cache | None = None,
        use_cache: bool = False,
        hidden: bool = False,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> CausalLMOutputWithPast:
        emb = self.embed(input_ids, payload)
        return self.llm(
            inputs_embeds=emb,
            attention_mask=self._mask(attention_mask, emb.dtype),
            position_ids=position_ids,
            cache=past_key_values,  # transformers 5.24 renamed past_key_values (removed in 5.40)
            use_cache=use_cache,
            output_hidden_states=hidden,
        )

    def step(
        self,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        position_ids: torch.Tensor,
        past_key_values: Cache | None = None,
        use_cache: bool = False,
        payload: dict[str, torch.Tensor] | None = None,
    ) -> Step:
        """The LLM's output for ``input_ids`` (and their payload) under a boolean 4D mask."""
        # Only a model with a payload emits scenes from hidden states: the others skip keeping every layer's.
        hidden = bool(self.payload_spec)
        out = self._run(
            input_ids, attention_mask, position_ids, past_key_values, use_cache, hidden=hidden, payload=payload
        )
        return Step(out.logits, out.cache, out.hidden_states[-1] if hidden else None)

    def forward(self, batch: dict[str, torch.Tensor], output_hidden_states: bool = False) -> WorldModelOutput:
        """Cross-entropy over all targets (one uniform loss); the text (text + action +
        marker) and scene parts are reported apart."""
        out = self._run(
            batch["input_ids"],
            batch["attention_mask"],
            batch["position_ids"],
            hidden=output_hidden_states,
            payload=batch_payload(batch),
        )
        logits, labels = out.logits, batch["labels"]
        ce = token_ce(logits, labels)
        valid = labels != IGNORE
        scene = batch["scene_target_mask"] & valid
        text = valid & ~scene

        def mean(sel: torch.Tensor) -> torch.Tensor:
            return (ce * sel).sum() / sel.sum().clamp(min=1)

        hidden = out.hidden_states[-1] if output_hidden_states else None
        return WorldModelOutput(
            mean(valid), mean(text), mean(scene), logits, hidden, sample_means(ce * valid, valid, batch)
        )

    @staticmethod
    def token_accuracy(logits: torch.Tensor, labels: torch.Tensor, select: torch.Tensor | None = None) -> torch.Tensor:
        """Fraction of targets (``labels`` != -100, and ``select``) whose argmax is right."""
        valid = labels != IGNORE
        if select is not None:
            valid = valid & select
        hits = (logits.argmax(-1) == labels) & valid
        return hits.sum().float() / valid.sum().clamp(min=1)

    # -- generation
    def check_prompt(self, prefix: torch.Tensor | TokenSequence) -> torch.Tensor | TokenSequence:
        """A prompt this model can decode (a family refuses bare ids its tokens need the payload of)."""
        return prefix

    def decoder(self, prefix: torch.Tensor | TokenSequence, use_cache: bool = True) -> Decoder:
        """A greedy decoder after ``prefix``: ids, or a laid-out sequence with its payload."""
        return Decoder(self, self.check_prompt(prefix), use_cache)

    @torch.no_grad()
    def generate(self, prefix: torch.Tensor | TokenSequence, answers: list[Answer]) -> list:
        """Greedy answers after one prompt, in order."""
        return decode(self, self.check_prompt(prefix), answers)

    @torch.no_grad()
    def generate_batch(
        self, prefixes: Sequence[torch.Tensor | TokenSequence], answers: list[list[Answer]]
    ) -> list[list]:
        """Greedy answers for a batch of prompts at once."""
        return decode_batch(self, [self.check_prompt(p) for p in prefixes], answers)

    @torch.no_grad()
    def generate_text(
        self, prefix: torch.Tensor | TokenSequence, max_new_tokens: int = 64, stop_at_eos: bool = True
    ) -> str:
        """Greedy text after ``prefix``, up to end-of-text."""
        return self.vocab.decode_text(self.generate(prefix, [TextAnswer(max_new_tokens, stop_at_eos)])[0])

    @torch.no_grad()
    def generate_actions(self, prefix: torch.Tensor | TokenSequence, steps: int = 6) -> torch.Tensor:
        """Greedy ``<act>`` block after ``prefix``: Float[steps, 2] waypoints (metres)."""
        return self.generate(prefix, [ActionAnswer(steps)])[0]

    @torch.no_grad()
    def generate_scene(self, prefix: torch.Tensor | TokenSequence) -> torch.Tensor:
        """One greedy scene after ``prefix``: its codes, flat."""
        return self.generate(prefix, [SceneAnswer()])[0]

    def unused_parameters(self, tasks: BaseTaskConfig) -> list[nn.Parameter]:
        """Parameters no loss reaches under these task settings: a stage freezes them, so that
        DDP waits for no gradient that never comes. None here; a family whose branch a task
        weight turns off names that branch's."""
        return []

    # -- export
    def base_llm(self) -> nn.Module:
        """The LLM without a peft wrapper."""
        return without_peft(self.llm)

    def export_config(self) -> dict:
        """JSON-able settings from which ``from_export`` rebuilds the model around its LLM."""
        return {
            "attn_implementation": getattr(self.base_llm().config, "_attn_implementation", "sdpa"),
            "scene_prediction": self.scene_prediction,
        }

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: Any = None) -> dict[str, Any]:
        """The joint vocabulary's scene layout for this model over ``inputs``: the keyword
        arguments of ``JointVocab`` besides the text tokenizer and the LLM settings."""
        raise NotImplementedError

    @classmethod
    def create(
        cls, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs, scene_prediction: str, world_cfg: Any = None
    ) -> LMWorldModel:
        """A fresh model around ``llm`` over the frozen inputs (pretraining's start)."""
        raise NotImplementedError

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs) -> LMWorldModel:
        """The exported architecture around ``llm`` (loaded from the export's Hugging Face
        directory); the export's own weights are loaded next."""
        raise NotImplementedError

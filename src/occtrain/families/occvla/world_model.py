"""OccVLA's vision-language-action model (Sec. 3.2): image tokens spliced into a causal
LM's input, and occupancy queries that share every weight of the LM.

Sequence layout::

    bos  <image> x N  [<scene_q_0> ... <scene_q_{Q-1}>]  prompt text  eos  answer  eos

An ``<image>`` token's input embedding is the image projector (LayerNorm + two-layer GELU
MLP, LLaVA-style) of its image feature, carried beside the ids as payload: the frozen
camera encoder's tokens, average-pooled per camera. The Q occupancy queries are learnable
embeddings (``occ_queries``) run through the same layers; they form a query block of the
spatial-temporal mask (``models.attention``): bidirectional among themselves, seeing
``bos`` and the images, seen by nothing else. They take the positions of the tokens that
follow them, so the text's positions, and so its every output, are the same with or
without them (Setting 2 of App. B): inference may skip them.

Occupancy (Sec. 3.2, 3.4): the queries' last hidden states -> a linear projector -> a
continuous OccWorld latent (code_dim x h x w, a query per p x p patch) -> the OccWorld
VQ-VAE decoder of a tokenizer stage's export -> (18, 200, 200, 16) logits -> voxel
cross-entropy. The decoder stays frozen: its weights never change, yet the gradient flows
through it to the projector (autograd passes gradients through a module whose parameters
do not require them, which is what the paper's learning rate 0 achieves). The loss is
L_text + lambda_occ * L_occ, lambda_occ riding with each sequence (``voxel_weight``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from occtrain.core.builder import SequenceBuilder, batch_payload
from occtrain.core.decoding import Answer, Feed, Flush, QueryBlock, decode
from occtrain.core.lm_world_model import LMWorldModel, WorldInputs, WorldModelOutput, token_ce
from occtrain.core.protocols import PromptInputs
from occtrain.core.sequence import IGNORE, PayloadSpec, TokenSequence, empty_payload, head, tail
from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig
from occtrain.core.vocab import JointVocab
from occtrain.data.clips import Part
from occtrain.families.occvla.config import OccVLAWorldConfig, TaskConfig
from occtrain.families.occvla.parts import Images, Occupancy
from occtrain.models.camera_encoder import pool_views
from occtrain.models.patches import unpatchify
from occtrain.models.tokenizers.base import SceneTokenizer

if TYPE_CHECKING:
    from transformers import PreTrainedModel


class VLASequenceBuilder(SequenceBuilder):
    """Adds image tokens and the occupancy query block to the shared layout."""

    def __init__(self, world: OccVLAWorldModel):
        super().__init__(world.vocab, "next_scene", world.payload_spec)
        self._has_queries = False

    def lay(self, part: Part, inputs: PromptInputs, scenes: dict[int, torch.Tensor]) -> SequenceBuilder:
        if isinstance(part, Images):
            return self.images(inputs.read("image_tokens", part.token))
        if isinstance(part, Occupancy):
            return self.occupancy(inputs.read("voxels", part.token), part.weight)
        return super().lay(part, inputs, scenes)

    def images(self, features: torch.Tensor) -> VLASequenceBuilder:
        """Image tokens for ``features`` Float[N, D] (one per token)."""
        n = features.shape[0]
        payload = empty_payload(self.payload_spec, n)
        payload["image"] = features.detach().float().cpu()
        self.add(torch.full((n,), self.vocab.image_id), False, payload=payload)
        return self

    def occupancy(self, voxels: torch.Tensor, weight: float) -> VLASequenceBuilder:
        """The occupancy query block, trained with weight ``weight`` on ``voxels`` uint8 (X, Y, Z)."""
        if self._has_queries:
            raise ValueError("a sequence holds one occupancy query block")
        self._has_queries = True
        self.add(self.vocab.query_ids(), False, seg=-self.next_block())
        self.targets["voxels"] = torch.as_tensor(voxels)
        self.targets["voxel_weight"] = torch.tensor(float(weight))
        return self


class OccVLAWorldModel(LMWorldModel):
    """The LLM, the image projector, the occupancy queries and their latent projector; the
    OccWorld decoder is the engine's frozen scene encoder, held here by reference."""

    frame_separation = False
    #: Its prompts hold camera views, not scenes.
    reads_scenes = False
    #: Its occupancy queries' voxel targets are per sequence, read by row.
    packs_sequences = False
    #: The frozen OccWorld VQ-VAE whose decoder turns the queries' latent into voxels.
    decoder_model: SceneTokenizer

    def __init__(
        self,
        llm: PreTrainedModel,
        vocab: JointVocab,
        scene_tokenizer: SceneTokenizer,
        vision_dim: int,
        cfg: OccVLAWorldConfig,
    ):
        super().__init__(llm, vocab, "next_scene")
        if not vocab.image or vocab.patch != cfg.query_patch:
            raise ValueError("OccVLA's vocabulary needs the <image> token and the query patch layout")
        self.cfg = cfg
        self.vision_dim = int(vision_dim)
        hidden = llm.get_input_embeddings().embedding_dim
        self.image_proj = nn.Sequential(
            nn.LayerNorm(vision_dim),
            nn.Linear(vision_dim, cfg.projector_hidden),
            nn.GELU(),
            nn.Linear(cfg.projector_hidden, hidden),
        )
        self.occ_queries = nn.Parameter(torch.randn(vocab.scene_len, hidden) * 0.02)
        self.code_dim = int(scene_tokenizer.codebook.shape[1])
        h, w = scene_tokenizer.latent_hw
        self.latent_hw = (h, w)
        p = cfg.query_patch
        self.occ_proj = nn.Linear(hidden, self.code_dim * p * p)
        # A plain attribute, not a submodule: the engine owns (and checkpoints skip) the tokenizer.
        self.__dict__["decoder_model"] = scene_tokenizer
        self.payload_spec: PayloadSpec = {"image": ((self.vision_dim,), torch.float32, 0.0)}

    def builder(self) -> VLASequenceBuilder:
        return VLASequenceBuilder(self)

    def occupancy_parameters(self) -> list[nn.Parameter]:
        """What only the occupancy branch uses."""
        return [self.occ_queries, *self.occ_proj.parameters()]

    def unused_parameters(self, tasks: BaseTaskConfig) -> list[nn.Parameter]:
        """The occupancy branch, where the tasks give it no weight (``occupancy_weight: 0``)."""
        return self.occupancy_parameters() if isinstance(tasks, TaskConfig) and tasks.occupancy_weight == 0 else []

    # -- the model
    def embed(self, input_ids: torch.Tensor, payload: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """Text rows of the LLM's table; image tokens through the projector; queries their own."""
        emb = self.llm.get_input_embeddings()(input_ids)
        images = self.vocab.is_image(input_ids)
        if bool(images.any()) and not payload:
            raise ValueError("image tokens need their features: pass the laid-out sequence, not bare ids")
        if payload:
            emb = emb.masked_scatter(
                images[..., None], self.image_proj(payload["image"][images].to(emb.dtype)).to(emb.dtype)
            )
        queries = self.vocab.is_query(input_ids)
        lo = self.vocab.query_range[0]
        rows = F.embedding((input_ids - lo).clamp(0, self.vocab.scene_len - 1), self.occ_queries)
        return torch.where(queries[..., None], rows.to(emb.dtype), emb)

    def occupancy_logits(self, query_hidden: torch.Tensor) -> torch.Tensor:
        """Query hidden states (B, Q, H) -> voxel logits (B, 18, X, Y, Z) through the decoder."""
        b = query_hidden.shape[0]
        p = self.cfg.query_patch
        latent = unpatchify(self.occ_proj(query_hidden.float()), p, self.latent_hw)  # (B, code_dim, h, w)
        return self.decoder_model.decode_logits(latent.reshape(b, self.code_dim, *self.latent_hw))

    def forward(self, batch: dict[str, torch.Tensor], output_hidden_states: bool = False) -> WorldModelOutput:
        """L_text (mean over the answer tokens) + lambda_occ * L_occ (per sequence, mean voxel CE)."""
        with_occ = "voxels" in batch
        ids = batch["input_ids"]
        out = self._run(
            ids,
            batch["attention_mask"],
            batch["position_ids"],
            hidden=with_occ or output_hidden_states,
            payload=batch_payload(batch),
        )
        logits, labels = out.logits, batch["labels"]
        ce = token_ce(logits, labels)
        valid = labels != IGNORE
        text_sum, n_text = (ce * valid).sum(1), valid.sum(1)
        text_loss = text_sum.sum() / n_text.sum().clamp(min=1)
        per_sample = text_sum / n_text.clamp(min=1)
        occ_loss = logits.new_zeros((), dtype=torch.float32)
        loss = text_loss
        if with_occ:
            weight = batch["voxel_weight"].to(logits.device).float()
            rows = weight > 0
            queries = self.vocab.is_query(ids) & batch["pad_mask"] & rows[:, None]
            hidden = out.hidden_states[-1][queries].view(int(rows.sum()), self.vocab.scene_len, -1)
            voxel_logits = self.occupancy_logits(hidden)
            per_voxel = F.cross_entropy(voxel_logits.float(), batch["voxels"][rows].long(), reduction="none")
            occ_ce = per_voxel.flatten(1).mean(1)  # (rows,)
            occ_loss = occ_ce.mean() if occ_ce.numel() else occ_loss
            loss = text_loss + (weight[rows] * occ_ce).sum() / rows.sum().clamp(min=1)
            per_sample = per_sample + torch.zeros_like(per_sample).masked_scatter(rows, weight[rows] * occ_ce)
        hidden = out.hidden_states[-1] if output_hidden_states else None
        return WorldModelOutput(loss, text_loss, occ_loss, logits, hidden, per_sample)

    # -- inference
    def _split(self, prefix: TokenSequence) -> int:
        """Where a prompt's image tokens end (the query block goes there)."""
        images = self.vocab.is_image(prefix.input_ids).nonzero()
        if not len(images):
            raise ValueError("an OccVLA prompt starts with its image tokens")
        return int(images.max()) + 1

    def pool_images(self, tokens: torch.Tensor, grid: tuple[int, int], views: int) -> torch.Tensor:
        """Each camera's patch grid average-pooled to ``image_tokens`` (rows, cols)."""
        rows, cols = self.cfg.image_tokens  # validated: [rows, cols]
        return pool_views(tokens, grid, views, (rows, cols))

    @torch.no_grad()
    def generate_with_occupancy(
        self, prefix: TokenSequence, answers: list[Answer], occupancy: bool = False
    ) -> tuple[list, torch.Tensor | None]:
        """Greedy answers after a prompt (images then text, no query block), and with
        ``occupancy`` the voxel logits (1, 18, X, Y, Z) of the query block run after the
        images. The images are fed first either way, so the text sees the same cache."""
        n = self._split(prefix)
        first = QueryBlock(self.vocab.query_ids()) if occupancy else Flush()
        out = decode(self, head(prefix, n), [first, Feed(tail(prefix, n)), *answers])
        voxels = self.occupancy_logits(out[0].hidden[None]) if occupancy else None
        return out[2:], voxels

    @torch.no_grad()
    def predict_occupancy(self, prefix: TokenSequence) -> torch.Tensor:
        """Voxel logits (1, 18, X, Y, Z) of the query block after a prompt's images: one
        forward of bos, the images and the queries."""
        n = self._split(prefix)
        voxels = self.generate_with_occupancy(head(prefix, n), [], occupancy=True)[1]
        assert voxels is not None  # asked for with occupancy=True
        return voxels

    # -- export
    def export_config(self) -> dict:
        return {
            **super().export_config(),
            "vision_dim": self.vision_dim,
            "occvla": {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__},
        }

    @staticmethod
    def vocab_layout(inputs: WorldInputs, world_cfg: OccVLAWorldConfig | None = None) -> dict:
        """A query per p x p patch of the OccWorld latent, and the ``<image>`` token."""
        cfg = world_cfg or OccVLAWorldConfig()
        scene = inputs.scene
        return {
            "codebook_sizes": scene.codebook_sizes,
            "scene_hw": scene.latent_hw,
            "patch": cfg.query_patch,
            "image": True,
        }

    @classmethod
    def create(
        cls,
        llm: nn.Module,
        vocab: JointVocab,
        inputs: WorldInputs,
        scene_prediction: str,
        world_cfg: OccVLAWorldConfig | None = None,
    ) -> OccVLAWorldModel:
        if inputs.vision is None:
            raise ValueError("OccVLA needs a camera encoder")
        return cls(llm, vocab, inputs.scene.tokenizer, inputs.vision.hidden_size, world_cfg or OccVLAWorldConfig())

    @classmethod
    def from_export(cls, data: dict, llm: nn.Module, vocab: JointVocab, inputs: WorldInputs) -> OccVLAWorldModel:
        return cls(llm, vocab, inputs.scene.tokenizer, data["vision_dim"], OccVLAWorldConfig(**data["occvla"]))

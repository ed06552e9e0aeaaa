"""OccLLaMA's configs: its scene tokenizer (Sec. III-A) and its world model's stages (Sec. III-B/C)."""

from __future__ import annotations

from dataclasses import dataclass, field

from occtrain.config.llm import MAX_NEW_TEXT_TOKENS, LLMConfig, LoRAConfig
from occtrain.config.tokenizer import QuantizerFields, latent_hw
from occtrain.errors import ConfigError
from occtrain.models.adapters import AdapterConfig
from occtrain.families.occllama.tasks import TaskConfig


@dataclass
class OccLLaMATokenizerConfig(QuantizerFields):
    """OccLLaMA's tokenizer: sparse pillar encoder + swin block, VQ, decoupled status/semantics decoder.

    Defaults follow the paper's ``50 x 256 x 2048`` (latent side, feature dimension, codebook
    size) and its loss weights lambda1 = lambda2 = 2, lambda3 = 0.5 (Eq. 9-10).
    """

    num_codes: int = 2048
    code_dim: int = 256
    #: Dimension of the per-point (height, label) embedding inside a pillar.
    class_embed_dim: int = 64
    base_channels: int = 64
    channel_mult: list[int] = field(default_factory=lambda: [1, 2, 4])
    strides: list[int] = field(default_factory=lambda: [2, 2])
    #: ResNet blocks per level of the decoder (it follows OccWorld's decoder).
    num_res_blocks: int = 2
    #: Swin blocks at the latent; they alternate regular and shifted windows.
    swin_depth: int = 2
    swin_heads: int = 8
    #: Side of a square attention window; clipped to the latent side.
    window_size: int = 5
    mlp_ratio: float = 4.0
    #: Per-voxel feature dimension C of the decoded volume, input of the heads h_a and h_n.
    voxel_feature_dim: int = 16
    #: Eq. 9: weight of the semantics reconstruction loss.
    lambda1: float = 2.0
    #: Eq. 9: weight of the occupancy-status reconstruction loss.
    lambda2: float = 2.0
    #: Eq. 10: weight of Lovasz-softmax inside each reconstruction loss.
    lambda3: float = 0.5
    vq_weight: float = 1.0

    def validate(self, where: str) -> None:
        super().validate(where)
        dim = self.base_channels * self.channel_mult[-1]
        if dim % self.swin_heads:
            raise ConfigError(f"{where}.swin_heads: {self.swin_heads} must divide the latent channels {dim}")
        window = min(self.window_size, *latent_hw(self))
        if any(side % window for side in latent_hw(self)):
            raise ConfigError(f"{where}.window_size: {self.window_size} must divide the latent side {latent_hw(self)[0]}")


@dataclass
class PretrainModelConfig:
    """``model:`` of a pretrain stage (Sec. III-C, multi-task pretraining of the world model)."""

    llm: LLMConfig = field(default_factory=LLMConfig)
    tasks: TaskConfig = field(default_factory=TaskConfig)
    lora: LoRAConfig = field(default_factory=LoRAConfig)
    #: Train through a LoRA adapter, the base frozen (instruct's default).
    use_lora: bool = False
    #: Fold the adapter into the exported weights instead of exporting it as a peft dir.
    merge_export: bool = False
    #: Train through bottleneck adapters at the residual connections instead, the base
    #: frozen (OccVLA's stage 2 and VQA branch); an export that has them trains them on.
    use_adapters: bool = False
    adapter: AdapterConfig = field(default_factory=AdapterConfig)
    #: Validation generates answers for this many items per task (a fixed seeded subset
    #: of the val split, the same at every validation; -1: all of them) and scores them.
    val_samples: int = 64
    #: Prompts generated together in validation.
    val_batch_size: int = 16
    #: Encode the whole dataset with the frozen tokenizer once, before training, instead of
    #: every clip at every step (measured in tools/bench/world_model.py).
    cache_codes: bool = True
    max_new_text_tokens: int = MAX_NEW_TEXT_TOKENS


@dataclass
class InstructModelConfig(PretrainModelConfig):
    """``model:`` of an instruct stage: QA and chain-of-thought planning through LoRA."""

    use_lora: bool = True

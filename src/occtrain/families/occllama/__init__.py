"""OccLLaMA (seeds/000): scene tokenizer, joint-vocabulary world model with spatial-temporal
attention and next-scene prediction, and its pretraining and instruction tasks."""

from __future__ import annotations

from occtrain.families.occllama.config import InstructModelConfig, OccLLaMATokenizerConfig, PretrainModelConfig
from occtrain.families.occllama.tasks import EVERY_ITEM, INSTRUCT_TASKS, PRETRAIN_TASKS, TASKS, TaskConfig
from occtrain.families.occllama.tokenizer import OccLLaMATokenizer
from occtrain.families.occllama.world_model import OccWorldModel
from occtrain.families.registry import FamilySpec, TokenizerArch, register_family

OCCLLAMA = register_family(
    FamilySpec(
        name="occllama",
        paper="OccLLaMA",
        tokenizers=(TokenizerArch("occllama_tokenizer", OccLLaMATokenizerConfig, OccLLaMATokenizer),),
        world_model=OccWorldModel,
        tasks=TASKS,
        every_item=EVERY_ITEM,
        default_tasks={"pretrain": {t: 1.0 for t in PRETRAIN_TASKS}, "instruct": {t: 1.0 for t in INSTRUCT_TASKS}},
        task_config=TaskConfig,
    )
)

__all__ = [
    "OCCLLAMA", "InstructModelConfig", "OccLLaMATokenizer", "OccLLaMATokenizerConfig", "OccWorldModel",
    "PretrainModelConfig", "TaskConfig",
]

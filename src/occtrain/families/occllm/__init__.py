"""Occ-LLM (seeds/003): the Motion-Separation VAE scene tokenizer, a world model over patch
tokens of its latents with frame separation and pre-fusion of the ego action, and its
tasks (4-D occupancy forecasting with self-ego planning, question answering).

The tokenizer trains through the shared ``tokenizer`` stage kind (``model.arch:
occllm_msvae``), the world model through ``pretrain`` and ``instruct`` (``model.family:
occllm``, settings under ``model.occllm``), on any Occ3D-layout data.
"""

from __future__ import annotations

from occtrain.families.occllama.tasks import TaskConfig
from occtrain.families.occllm.config import MOVABLE_CLASSES, MSVAEConfig, OccLLMWorldConfig
from occtrain.families.occllm.msvae import MSVAE, merge, separate
from occtrain.families.occllm.tasks import EVERY_ITEM, PROMPT_WORDS, TASKS
from occtrain.families.occllm.world_model import OccLLMWorldModel
from occtrain.families.registry import FamilySpec, TokenizerArch, register_family

OCCLLM = register_family(
    FamilySpec(
        name="occllm",
        paper="Occ-LLM",
        tokenizers=(TokenizerArch("occllm_msvae", MSVAEConfig, MSVAE),),
        world_model=OccLLMWorldModel,
        tasks=TASKS,
        every_item=EVERY_ITEM,
        # Pretraining: forecasting with planning; instruction tuning adds QA and keeps forecasting.
        default_tasks={"pretrain": {"forecasting": 1.0}, "instruct": {"qa": 2.0, "forecasting": 1.0}},
        # OccLLaMA's task settings (history frames, forecast length, questions per sequence) fit its prompts as they are.
        task_config=TaskConfig,
        world_config=OccLLMWorldConfig,
        prompt_words=PROMPT_WORDS,
    )
)

__all__ = ["MOVABLE_CLASSES", "MSVAE", "MSVAEConfig", "OCCLLM", "OccLLMWorldConfig", "OccLLMWorldModel", "merge", "separate"]

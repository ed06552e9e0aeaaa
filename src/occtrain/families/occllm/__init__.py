"""Occ-LLM (arXiv:2502.06419): the Motion-Separation VAE scene tokenizer, a world model over patch
tokens of its latents with frame separation and pre-fusion of the ego action, and its
tasks (4-D occupancy forecasting with self-ego planning, question answering).

The tokenizer trains through the shared ``tokenizer`` stage kind (``model.arch:
occllm_msvae``), the world model through ``pretrain`` and ``instruct`` (``model.family:
occllm``, settings under ``model.occllm``), on any Occ3D-layout data.
"""

from __future__ import annotations

from occtrain.core import shared_operations
from occtrain.core.registry import FamilySpec, Showcase, TokenizerArch, WorldSpec, register_family
from occtrain.core.scene_encoders import load_vq_scene_encoder, vq_scene_encoder
from occtrain.families.occllm.config import MOVABLE_CLASSES, MSVAEConfig, OccLLMWorldConfig
from occtrain.families.occllm.msvae import MSVAE, merge, separate
from occtrain.families.occllm.paper import PAPER_FIGURES
from occtrain.families.occllm.tasks import PROMPT_WORDS, TASKS, TaskConfig
from occtrain.families.occllm.world_model import OccLLMWorldModel

OCCLLM = register_family(
    FamilySpec(
        name="occllm",
        paper="Occ-LLM",
        tokenizers=(TokenizerArch("occllm_msvae", MSVAEConfig, MSVAE),),
        world=WorldSpec(
            model=OccLLMWorldModel,
            task_config=TaskConfig,
            tasks=TASKS,
            # Pretraining: forecasting with planning; instruction tuning adds QA and keeps forecasting.
            default_tasks={"pretrain": {"forecasting": 1.0}, "instruct": {"qa": 2.0, "forecasting": 1.0}},
            world_config=OccLLMWorldConfig,
            prompt_words=PROMPT_WORDS,
            inputs=("tokenizer",),
            scene_encoder=vq_scene_encoder,
            load_scene_encoder=load_vq_scene_encoder,
            operations={
                "answer": shared_operations.answer,
                "forecast": shared_operations.forecast,
                "plan": shared_operations.plan,
                "scene_summary": shared_operations.scene_summary,
            },
        ),
        paper_figures=PAPER_FIGURES,
        # Waypoints generated between the forecast frames, as the paper plans.
        showcase=Showcase(
            recipe="occllm",
            world="pretrain",
            forecast="pretrain",
            plan="pretrain",
            plan_metric="plan_alternate",
            qa="instruct",
            note="MS-VAE codes, patchified",
        ),
    )
)

__all__ = [
    "MOVABLE_CLASSES",
    "MSVAE",
    "MSVAEConfig",
    "OCCLLM",
    "OccLLMWorldConfig",
    "OccLLMWorldModel",
    "TaskConfig",
    "merge",
    "separate",
]

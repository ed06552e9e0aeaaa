"""OccLLaMA (arXiv:2409.03272): scene tokenizer, joint-vocabulary world model with spatial-temporal
attention and next-scene prediction, and its pretraining and instruction tasks."""

from __future__ import annotations

from functools import partial

from occtrain.core.meta_action_planner import MetaActionPlannerConfig, load_meta_action_planner, meta_action_planner
from occtrain.core.registry import FamilySpec, Showcase, TokenizerArch, WorldSpec, register_family
from occtrain.core.scene_encoders import load_vq_scene_encoder, vq_scene_encoder
from occtrain.families.occllama.config import OccLLaMATokenizerConfig, OccLLaMAWorldConfig
from occtrain.families.occllama.operations import OPERATIONS
from occtrain.families.occllama.paper import PAPER_FIGURES
from occtrain.families.occllama.scene_tokenizer import OccLLaMATokenizer
from occtrain.families.occllama.tasks import INSTRUCT_TASKS, PRETRAIN_TASKS, TASKS, TaskConfig
from occtrain.families.occllama.world_model import OccLLaMAWorldModel

OCCLLAMA = register_family(
    FamilySpec(
        name="occllama",
        paper="OccLLaMA",
        tokenizers=(TokenizerArch("occllama_tokenizer", OccLLaMATokenizerConfig, OccLLaMATokenizer),),
        world=WorldSpec(
            model=OccLLaMAWorldModel,
            task_config=TaskConfig,
            world_config=OccLLaMAWorldConfig,
            tasks=TASKS,
            default_tasks={"pretrain": {t: 1.0 for t in PRETRAIN_TASKS}, "instruct": {t: 1.0 for t in INSTRUCT_TASKS}},
            inputs=("tokenizer",),
            scene_encoder=vq_scene_encoder,
            load_scene_encoder=load_vq_scene_encoder,
            # OccVLA's MLP head on the meta action its chain of thought ends with (the sidecar's in training).
            planner=partial(meta_action_planner, sidecar_reference=True),
            planner_config=MetaActionPlannerConfig,
            load_planner=partial(load_meta_action_planner, sidecar_reference=True),
            operations=OPERATIONS,
        ),
        paper_figures=PAPER_FIGURES,
        # The planning head on the meta action the instruct model generates (not the reference one).
        showcase=Showcase(
            recipe="quickstart",
            world="pretrain",
            forecast="pretrain",
            plan="planner",
            plan_metric="head_generated_meta",
            qa="instruct",
            note="VQ codes of a 2D VAE",
        ),
    )
)

__all__ = [
    "OCCLLAMA",
    "OccLLaMATokenizer",
    "OccLLaMATokenizerConfig",
    "OccLLaMAWorldConfig",
    "OccLLaMAWorldModel",
    "TaskConfig",
]

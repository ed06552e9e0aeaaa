"""OccVLA (arXiv:2509.05578): a vision-language-action model whose occupancy queries share the
LLM's weights, read the camera tokens and are supervised through a frozen OccWorld VQ-VAE
decoder; meta actions with a chain of thought; a planning head on the predicted meta action.

Its stages are the shared kinds: ``vision`` (the camera encoder), ``tokenizer``
(``model.arch: occworld_vqvae``, whose decoder the queries train through), ``pretrain``
with ``model.family: occvla`` consuming both (stage 1, full fine-tuning), ``instruct``
with bottleneck adapters (stage 2, and the VQA branch), ``planner`` (stage 3).
"""

from __future__ import annotations

from functools import partial

from occtrain.core.meta_action_planner import MetaActionPlannerConfig, load_meta_action_planner, meta_action_planner
from occtrain.core.registry import FamilySpec, Showcase, WorldSpec, register_family
from occtrain.core.sample_inputs import IMAGE_TOKENS, VOXELS
from occtrain.core.scene_encoders import load_vq_scene_encoder, vq_scene_encoder
from occtrain.families.occvla.config import OccVLAWorldConfig, TaskConfig
from occtrain.families.occvla.operations import OPERATIONS
from occtrain.families.occvla.paper import PAPER_FIGURES
from occtrain.families.occvla.scoring import OccupancyQueries
from occtrain.families.occvla.tasks import PROMPT_WORDS, TASKS
from occtrain.families.occvla.world_model import OccVLAWorldModel

OCCVLA = register_family(
    FamilySpec(
        name="occvla",
        paper="OccVLA",
        world=WorldSpec(
            model=OccVLAWorldModel,
            task_config=TaskConfig,
            tasks=TASKS,
            # Stage 1 learns driving scenes in text; stage 2 the meta action with its reasoning.
            default_tasks={
                "pretrain": {"caption": 1.0, "qa": 1.0, "meta_action": 1.0},
                "instruct": {"meta_action": 1.0},
            },
            world_config=OccVLAWorldConfig,
            prompt_words=PROMPT_WORDS,
            # The OccWorld VQ-VAE whose decoder its queries train through, and the camera encoder.
            inputs=("vision", "tokenizer"),
            scene_encoder=vq_scene_encoder,
            load_scene_encoder=load_vq_scene_encoder,
            reads_cameras=True,
            # What its parts read (parts.Images, parts.Occupancy).
            sample_inputs=(IMAGE_TOKENS, VOXELS),
            eval_hooks=(OccupancyQueries,),
            # Stage 3: the MLP head on the meta action it labels from the poses.
            planner=partial(meta_action_planner, sidecar_reference=False),
            planner_config=MetaActionPlannerConfig,
            load_planner=partial(load_meta_action_planner, sidecar_reference=False),
            operations=OPERATIONS,
        ),
        paper_figures=PAPER_FIGURES,
        # Stage 1 trains on captions, but the paper's evaluation scores meta actions and QA only.
        showcase=Showcase(
            recipe="occvla",
            world="stage1",
            plan="stage3",
            plan_metric="head_generated_meta",
            qa="vqa",
            note="camera patches (occupancy is an output)",
        ),
    )
)

__all__ = ["OCCVLA", "OccVLAWorldConfig", "OccVLAWorldModel", "TaskConfig"]

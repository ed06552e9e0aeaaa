"""OccVLA (seeds/002): a vision-language-action model whose occupancy queries share the
LLM's weights, read the camera tokens and are supervised through a frozen OccWorld VQ-VAE
decoder; meta actions with a chain of thought; a planning head on the predicted meta action.

Its stages are the shared kinds: ``vision`` (the camera encoder), ``tokenizer``
(``model.arch: occworld_vqvae``, whose decoder the queries train through), ``pretrain``
with ``model.family: occvla`` consuming both (stage 1, full fine-tuning), ``instruct``
with bottleneck adapters (stage 2, and the VQA branch), ``planner`` (stage 3).
"""

from __future__ import annotations

from occtrain.families.occllama.tasks import TaskConfig
from occtrain.families.occvla.config import OccVLAWorldConfig
from occtrain.families.occvla.tasks import EVERY_ITEM, PROMPT_WORDS, TASKS
from occtrain.families.occvla.world_model import OccVLAWorldModel
from occtrain.families.registry import FamilySpec, register_family

OCCVLA = register_family(
    FamilySpec(
        name="occvla",
        paper="OccVLA",
        world_model=OccVLAWorldModel,
        tasks=TASKS,
        every_item=EVERY_ITEM,
        # Stage 1 learns driving scenes in text; stage 2 the meta action with its reasoning.
        default_tasks={"pretrain": {"caption": 1.0, "qa": 1.0, "meta_action": 1.0}, "instruct": {"meta_action": 1.0}},
        task_config=TaskConfig,
        world_config=OccVLAWorldConfig,
        prompt_words=PROMPT_WORDS,
        reads_cameras=True,
    )
)

__all__ = ["OCCVLA", "OccVLAWorldConfig", "OccVLAWorldModel"]

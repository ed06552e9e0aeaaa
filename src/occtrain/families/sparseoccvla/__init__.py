"""SparseOccVLA (arXiv:2601.06474): sparse occupancy queries bridging occupancy and a VLM.

Its stages are the shared kinds: ``vision`` (the frozen teacher its encoder distils from),
``tokenizer`` with ``model.arch: sparseocc`` (stage 1: the sparse occupancy encoder and
connector, from the cameras, with the occupancy and distillation losses), ``pretrain`` with
``model.family: sparseoccvla`` consuming it (stage 2: connector, global queries,
forecaster and the LLM), ``instruct`` through LoRA (stage 3: everything, the LLM through
LoRA) and ``planner`` (the LLM-guided anchor-diffusion planner).
"""

from __future__ import annotations

from occtrain.core.registry import FamilySpec, Showcase, TokenizerArch, WorldSpec, register_family
from occtrain.core.sample_inputs import VOXELS
from occtrain.families.sparseoccvla.anchor_diffusion import AnchorDiffusionConfig, AnchorDiffusionPlanner
from occtrain.families.sparseoccvla.config import SparseOccConfig, SparseOccVLAWorldConfig
from occtrain.families.sparseoccvla.encoder import SparseOccEncoder
from occtrain.families.sparseoccvla.forecasting import ForecastHead
from occtrain.families.sparseoccvla.operations import OPERATIONS
from occtrain.families.sparseoccvla.paper import PAPER_FIGURES
from occtrain.families.sparseoccvla.scene_encoder import ARCH, load_sparse_scene_encoder, sparse_scene_encoder
from occtrain.families.sparseoccvla.tasks import PROMPT_WORDS, TASKS, TaskConfig
from occtrain.families.sparseoccvla.world_model import SparseOccVLAWorldModel

SPARSEOCCVLA = register_family(
    FamilySpec(
        name="sparseoccvla",
        paper="SparseOccVLA",
        tokenizers=(TokenizerArch(ARCH, SparseOccConfig, SparseOccEncoder, reads_cameras=True, teachers=("vision",)),),
        world=WorldSpec(
            model=SparseOccVLAWorldModel,
            task_config=TaskConfig,
            tasks=TASKS,
            # Stage 2 and stage 3 train understanding, forecasting and the decision together (Eq. 12).
            default_tasks={
                "pretrain": {"caption": 1.0, "qa": 1.0, "planning": 1.0, "forecast": 1.0},
                "instruct": {"caption": 1.0, "qa": 1.0, "planning": 1.0, "forecast": 1.0},
            },
            world_config=SparseOccVLAWorldConfig,
            prompt_words=PROMPT_WORDS,
            inputs=("tokenizer",),
            # A forecast's targets: the future frame's points, drawn from its voxels.
            sample_inputs=(VOXELS,),
            scene_encoder=sparse_scene_encoder,
            load_scene_encoder=load_sparse_scene_encoder,
            eval_hooks=(ForecastHead,),
            planner=AnchorDiffusionPlanner.from_stage,
            planner_config=AnchorDiffusionConfig,
            load_planner=AnchorDiffusionPlanner.from_export,
            operations=OPERATIONS,
        ),
        paper_figures=PAPER_FIGURES,
        showcase=Showcase(
            recipe="sparseoccvla",
            world="stage3",
            forecast="stage3",
            plan="planner",
            qa="stage3",
            caption="stage3",
            note="sparse queries + global queries",
        ),
    )
)

__all__ = [
    "SPARSEOCCVLA",
    "SparseOccConfig",
    "SparseOccEncoder",
    "SparseOccVLAWorldConfig",
    "SparseOccVLAWorldModel",
    "TaskConfig",
]

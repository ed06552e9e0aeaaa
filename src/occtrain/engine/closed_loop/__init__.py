"""Closed loop, Lightning-free: trained stages and baselines behind the wheel of the simulator.

- ``planners``: a trained stage as the loop's planner (``StageDriver``, ``StagePlanner``,
  ``OpenLoopPlanner``), who drove each frame (``PlanCounts``);
- ``baselines``: the expert and the kinematic rules, with the same start as a stage;
- ``episodes``: the one loop every driver runs (``drive_episode``) and its open-loop shadow;
- ``workers``: one pool of worker processes for episodes, drivers built from picklable specs;
- ``dagger``, ``rollouts``: closed-loop training's driving, aggregate and labels.

``occtrain drive`` and the dagger stage both drive through these; the simulator
(``data.closed_loop_recording``) only simulates.
"""

from occtrain.engine.closed_loop.planners import (
    NonFinitePlan,
    OpenLoopPlanner,
    PlanCounts,
    StageDriver,
    StagePlanner,
    model_planner,
    refuse_short_episodes,
    world_model_driver,
)

__all__ = [
    "NonFinitePlan",
    "OpenLoopPlanner",
    "PlanCounts",
    "StageDriver",
    "StagePlanner",
    "model_planner",
    "refuse_short_episodes",
    "world_model_driver",
]

"""OccVLA's settings: its world model's (``model.occvla`` of a pretrain stage) and its
tasks' (``model.tasks``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from occtrain.core.shared_tasks import TaskConfig as BaseTaskConfig
from occtrain.data.meta_actions import MetaActionConfig
from occtrain.errors import ConfigError

if TYPE_CHECKING:
    from occtrain.core.lm_world_model import WorldInputs


@dataclass
class OccVLAWorldConfig:
    """The image tokens, the occupancy queries and their projections (Sec. 3.2)."""

    #: One occupancy query per p x p patch of the OccWorld latent grid (p = 1: a query per
    #: latent cell; the paper does not give its count).
    query_patch: int = 1
    #: Image tokens per camera: the vision tower's patch grid average-pooled to (rows,
    #: cols). The paper feeds 256 per view (SigLIP at 224 px); six views of 3 x 4 keep the
    #: tiny LLM's sequences short on a CPU.
    image_tokens: list[int] = field(default_factory=lambda: [3, 4])
    #: Hidden width of the two-layer image projector (vision width -> LLM width).
    projector_hidden: int = 256

    def validate(self, where: str, inputs: WorldInputs) -> None:
        """One line naming the key when a setting cannot work over ``inputs`` (a ``WorldInputs``)."""
        latent = tuple(inputs.scene.latent_hw)
        p = self.query_patch
        if p < 1 or latent[0] % p or latent[1] % p:
            raise ConfigError(
                f"{where}.query_patch: {p} must divide the tokenizer's latent grid {latent[0]} x {latent[1]}"
            )
        if len(self.image_tokens) != 2 or min(self.image_tokens) < 1:
            raise ConfigError(f"{where}.image_tokens: {list(self.image_tokens)} must be [rows, cols], each >= 1")
        if self.projector_hidden < 1:
            raise ConfigError(f"{where}.projector_hidden: must be >= 1, got {self.projector_hidden}")


#: ``cot_scene`` values: the caption without its clause on the ego's motion, or all of it.
COT_SCENES = ("surroundings", "caption")
#: ``meta_action_prior`` values, the paper's first.
META_ACTION_PRIORS = ("none", "repeat_last")


@dataclass
class TaskConfig(BaseTaskConfig):
    """OccVLA's task settings: its prompts, the chain of thought and the occupancy loss."""

    #: History frames of a clip (the past meta actions t-5 .. t-1 read the poses back to t-6).
    context_frames: int = 6
    #: lambda_occ (Eq. 3): the weight of the occupancy-query loss beside the text loss in
    #: every sequence; 0 leaves the queries out.
    occupancy_weight: float = 1.0
    #: The answer reasons (scene, history) before the meta action (Table 7).
    chain_of_thought: bool = True
    #: The chain's scene step: "surroundings", the caption without its opening clause on the
    #: ego's own motion, or "caption", the whole caption. That clause states the frame's
    #: meta action, so under teacher forcing the model learns to copy it into the answer,
    #: and at inference it guesses the clause from the cameras and copies the guess over the
    #: prompt's history (docs/families/occllama.md, "Switches beyond the papers").
    cot_scene: str = "surroundings"
    #: How the answer writes its meta action. "none" (the paper): always as speed and
    #: direction. "repeat_last": "as before" when it equals the last past one, which the
    #: prompt lists, so keeping it is one phrase and the model learns when it changes
    #: (docs/families/occllama.md, "Switches beyond the papers").
    meta_action_prior: str = "none"
    #: Past meta actions in the prompt (t-5 .. t-1; fewer where the clip's history is shorter).
    past_meta_actions: int = 5
    #: How meta actions are labelled from the ego poses.
    meta_actions: MetaActionConfig = field(default_factory=MetaActionConfig)

    def __post_init__(self) -> None:
        if isinstance(self.meta_actions, dict):  # as an export's config.json holds it
            self.meta_actions = MetaActionConfig(**self.meta_actions)

    def validate(self, key: str) -> None:
        super().validate(key)
        if self.occupancy_weight < 0:
            raise ConfigError(
                f"{key}.occupancy_weight: {self.occupancy_weight} is negative (paper: 1; 0 turns the occupancy queries "
                "off)"
            )
        if self.past_meta_actions < 0:
            raise ConfigError(f"{key}.past_meta_actions: {self.past_meta_actions} is negative (paper: 5)")
        self.meta_actions.validate(f"{key}.meta_actions")
        if self.meta_action_prior not in META_ACTION_PRIORS:
            raise ConfigError(
                f"{key}.meta_action_prior: {self.meta_action_prior!r} is not one of {', '.join(META_ACTION_PRIORS)} "
                "(paper: none)"
            )
        if self.cot_scene not in COT_SCENES:
            raise ConfigError(f"{key}.cot_scene: {self.cot_scene!r} is not one of {', '.join(COT_SCENES)}")

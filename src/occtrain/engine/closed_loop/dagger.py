"""Closed-loop training of a planner (DAgger: Ross, Gordon and Bagnell, 2011): the planner
drives the reactive world on training routes, every planning frame it reaches is labelled
with what the world's expert would drive from there, and the labelled frames join its
training data.

A planner trained on the expert's frames alone never sees the states its own mistakes lead
to; the embedded world has what real logs lack, an expert that answers from any state
(``DrivingWorld.expert_from_here``). Round ``r`` drives ``routes_per_round`` routes whose
seeds are drawn from ``route_seed`` and the round (apart from the data's scene seeds and
from ``occtrain drive``'s evaluation routes), with the policy mixed with the expert: at each
planning frame the expert's plan is followed with probability ``beta_r = beta *
beta_decay ** r`` (a coin seeded by the round, the route and the frame), the policy's
otherwise; before the policy has the history its prompts read, the expert drives. Every
frame is recorded with its expert label (``RecordedDataset``: one train scene per route,
the label as the frame's ``ego_future`` and meta action), and a round's routes are written
one by one, each marked with the policy it was driven by, so a cut-off round resumes at its
first route not driven by the same weights. Lightning-free: ``stages/planner.py`` runs
the rounds between its training steps.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from occtrain.config.groups import check_seed
from occtrain.core.protocols import Planner
from occtrain.data.clips import Clip, frame_clips
from occtrain.data.closed_loop_recording import DrivingWorld, EpisodeRecorder, RecordedDataset
from occtrain.data.layout import DatasetIndex
from occtrain.data.schema import FrameAnnotation
from occtrain.engine.closed_loop.episodes import drive_episode
from occtrain.engine.closed_loop.planners import StageDriver, StagePlanner
from occtrain.engine.trained_planner import PlannerRequest, load_planner
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_write_json
from occtrain.metrics.closed_loop_scores import score_episode

#: Training routes are drawn as ``SeedSequence([route_seed, round, route])``, where the data's
#: scenes and ``occtrain drive``'s routes are ``SeedSequence([seed, scene])`` from seeds 0,
#: 1, ... and 1000: other draws, from another seed.
DEFAULT_ROUTE_SEED = 5000
#: What a round reports, per route and in the mean (``metrics.closed_loop_scores``).
ROUND_SCORES = ("driving_score", "route_completion", "collisions")


@dataclass
class DaggerSettings:
    """How a ``dagger`` stage drives and aggregates (flat in its ``model:``)."""

    #: Rounds of driving, then fine-tuning on everything aggregated so far.
    rounds: int = 3
    #: Optimizer steps after each round's driving (``trainer.max_steps`` = rounds x this).
    steps_per_round: int = 100
    #: Routes each round drives, and how long each episode lasts (s, at most 40).
    routes_per_round: int = 4
    seconds: float = 20.0
    #: The expert's share of control in round 0, and its decay per round (DAgger's beta_i =
    #: beta * decay^i; Ross et al. use beta_1 = 1 then 0, or a geometric decay).
    beta: float = 0.5
    beta_decay: float = 0.5
    #: Where the training routes' seeds are drawn from (not the data's, not drive's 1000).
    route_seed: int = DEFAULT_ROUTE_SEED
    #: Share of each training batch drawn from the aggregated frames (the rest: the dataset's).
    aggregate_share: float = 0.5
    #: How much likelier a critical aggregated frame is drawn than an ordinary one
    #: (``critical``: a turn, a stop line or a lead close ahead); 1: all alike.
    critical_weight: float = 3.0
    #: Processes a round's routes are driven in (1: in the training process, one after
    #: another; more: spawned workers of one thread each, as ``occtrain drive --workers``).
    workers: int = 1

    def validate(self, where: str) -> None:
        for key in ("rounds", "steps_per_round", "routes_per_round", "workers"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{where}.{key}: {getattr(self, key)} must be at least 1")
        cores = len(os.sched_getaffinity(0))
        if self.workers > cores:
            raise ConfigError(
                f"{where}.workers: {self.workers} is more than the {cores} cores this process may use (each worker "
                f"drives on its own); give 1 to {cores}"
            )
        check_seed(self.route_seed, f"{where}.route_seed")
        if not 0 < self.seconds <= 40:
            raise ConfigError(f"{where}.seconds: {self.seconds:g} must be in (0, 40]")
        for key in ("beta", "beta_decay", "aggregate_share"):
            if not 0 <= getattr(self, key) <= 1:
                raise ConfigError(f"{where}.{key}: {getattr(self, key):g} must be within [0, 1]")
        if not self.critical_weight >= 1:
            raise ConfigError(f"{where}.critical_weight: {self.critical_weight:g} must be at least 1")

    def beta_at(self, round_: int) -> float:
        return self.beta * self.beta_decay**round_


#: Within these (m) a stop line whose light is not green, or a lead vehicle, makes a frame
#: critical: where the expert brakes, and where a planner that cannot see it collides.
CRITICAL_STOP_M, CRITICAL_LEAD_M = 30.0, 20.0


def critical(anchor: dict) -> bool:
    """Whether an aggregated frame is one DAgger must not dilute: the route turns (its
    command), a stop line not green lies close ahead, or a lead vehicle does."""
    if anchor.get("command", "go straight") != "go straight":
        return True
    road = anchor.get("road")
    if road is None:
        return False
    stop, lead = road.get("stop_line"), road.get("lead")
    return bool(
        (stop is not None and stop["light"] != "green" and stop["distance"] < CRITICAL_STOP_M)
        or (lead is not None and lead["gap"] < CRITICAL_LEAD_M)
    )


def replay_weights(clips: list[Clip], critical_weight: float) -> np.ndarray:
    """How likely each aggregated clip is drawn (summing to 1): critical ones ``critical_weight``
    times an ordinary one, so the few frames where the expert does something are not lost
    among the many where it cruises."""
    w = np.array([critical_weight if critical(c.anchor) else 1.0 for c in clips], dtype=np.float64)
    return w / w.sum()


def route_seed(settings: DaggerSettings, round_: int, route: int) -> int:
    """Route ``route`` of round ``round_``: its own scene seed, as ``data synth`` draws them."""
    return int(np.random.SeedSequence([settings.route_seed, round_, route]).generate_state(1)[0])


def scene_name(round_: int, route: int) -> str:
    return f"round{round_:02d}-route{route:02d}"


def policy_key(policy: torch.nn.Module) -> str:
    """The policy's trained weights (those that require gradients: not its frozen world
    model), hashed: a route driven by other weights is driven again."""
    h = hashlib.sha256()
    for name, tensor in sorted(policy.named_parameters()):
        if tensor.requires_grad:
            h.update(name.encode())
            h.update(tensor.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def load_policy(request: PlannerRequest, where: str, max_new_text_tokens: int) -> tuple[Planner, WorldModelEngine]:
    """The planner a dagger stage drives and fine-tunes, over its frozen world model (eval
    mode, no gradients), as the stage and its rollout workers both load it: refused in one
    line (``where``: whose) when it cannot drive closed loop; the world model's generation
    capped at ``max_new_text_tokens`` (0: its export's)."""
    planner, teacher = load_planner(request, "a dagger stage")
    refusal = planner.closed_loop_refusal()
    if refusal is not None:
        raise ConfigError(f"{where}: {request.export}: {refusal}")
    if max_new_text_tokens > 0:
        teacher.with_settings(max_new_text_tokens=max_new_text_tokens)
    return planner, teacher.requires_grad_(False).eval()


class MixedPlanner:
    """The closed loop's planner for one route: records each planning frame with the expert's
    label from there, and follows the expert (with probability ``beta``, and through the
    policy's history) or the policy."""

    def __init__(self, stage: StagePlanner, beta: float, coin: np.random.Generator):
        self.stage, self.beta, self.coin = stage, beta, coin
        self.labelled: list[FrameAnnotation] = []
        self.expert = self.policy = 0

    def __call__(self, world: DrivingWorld) -> np.ndarray:
        label = world.expert_from_here()
        plan = self.stage(world)  # records the frame; None while the history fills
        recorder = self.stage.recorder
        self.labelled.append(world.frame_annotation(recorder.scene, recorder.episode, future=label))
        # The coin is tossed at every frame, so the draws do not depend on the history length.
        follow_expert = self.coin.random() < self.beta
        if plan is None or follow_expert:
            self.expert += 1
            return label
        self.policy += 1
        return plan


@dataclass
class RouteResult:
    """One driven route, as its file records it."""

    scene: str
    route_seed: int
    beta: float
    policy: str
    frames: int
    policy_frames: int
    expert_frames: int
    scores: dict[str, float]
    wall_s: float


def drive_route(
    driver: StageDriver,
    dataset: RecordedDataset,
    scene: str,
    seed: int,
    seconds: float,
    beta: float,
    camera: tuple[int, int] | None,
    policy: str,
) -> tuple[list[FrameAnnotation], RouteResult]:
    """Drive route ``seed`` mixed with its expert, recording every frame under ``dataset``
    as scene ``scene`` (labels and cameras; the frame sidecar is the caller's to write)."""
    start = time.perf_counter()
    world = DrivingWorld(seed, seconds)
    recorder = EpisodeRecorder(dataset.root, world, camera, episode=scene, scene=scene)
    mixed = MixedPlanner(StagePlanner(driver, recorder), beta, np.random.default_rng([seed, 7]))
    scores = score_episode(drive_episode(world, mixed)).as_dict()
    result = RouteResult(
        scene,
        seed,
        beta,
        policy,
        len(mixed.labelled),
        mixed.policy,
        mixed.expert,
        {k: float(scores[k]) for k in ROUND_SCORES},
        round(time.perf_counter() - start, 2),
    )
    return mixed.labelled, result


class Aggregate:
    """Every round's labelled frames under ``root`` (a ``RecordedDataset``) and each route's
    record (``routes/<scene>.json``, written once its frames are complete)."""

    def __init__(self, root: Path, settings: DaggerSettings, dataset: RecordedDataset):
        self.root, self.settings, self.dataset = root, settings, dataset

    def route_file(self, scene: str) -> Path:
        return self.root / "routes" / f"{scene}.json"

    def result(self, round_: int, route: int) -> RouteResult | None:
        file = self.route_file(scene_name(round_, route))
        return RouteResult(**json.loads(file.read_text())) if file.is_file() else None

    def driven(self, round_: int, route: int, policy: str) -> bool:
        """Whether the route was driven, to the end, by these weights."""
        result = self.result(round_, route)
        return result is not None and result.policy == policy

    def complete(self, round_: int) -> bool:
        return all(self.result(round_, k) is not None for k in range(self.settings.routes_per_round))

    def record(self, labelled: list[FrameAnnotation], result: RouteResult) -> None:
        """A driven route's frame sidecar, then its record (which marks it driven)."""
        self.dataset.files.write_frames(result.scene, labelled)
        atomic_write_json(self.route_file(result.scene), asdict(result))

    def scenes(self, rounds: int) -> list[str]:
        return [scene_name(r, k) for r in range(rounds) for k in range(self.settings.routes_per_round)]

    def index(self, rounds: int) -> DatasetIndex:
        """The dataset of the first ``rounds`` rounds (each complete)."""
        return self.dataset.write_index(self.scenes(rounds))

    def clips(self, index: DatasetIndex, history: int) -> list[Clip]:
        """Every aggregated frame with ``history`` driven frames before it, as a clip whose
        future is the expert's label."""
        return list(frame_clips(index, "train", history, 0, partial_history=False))

    def round_scores(self, round_: int) -> dict[str, float]:
        """The round's routes in the mean: the mixed driver's scores and the policy's share."""
        results = [r for k in range(self.settings.routes_per_round) if (r := self.result(round_, k)) is not None]
        out = {f"rollout_{k}": float(np.mean([r.scores[k] for r in results])) for k in ROUND_SCORES}
        frames = sum(r.frames for r in results)
        out["rollout_policy_share"] = 100.0 * sum(r.policy_frames for r in results) / max(frames, 1)
        out["rollout_frames"] = float(frames)
        out["rollout_beta"] = self.settings.beta_at(round_)
        return out


__all__ = [
    "Aggregate",
    "DaggerSettings",
    "critical",
    "replay_weights",
    "MixedPlanner",
    "RouteResult",
    "drive_route",
    "load_policy",
    "policy_key",
    "route_seed",
    "scene_name",
]

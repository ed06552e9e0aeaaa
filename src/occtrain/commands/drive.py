"""``occtrain drive RUN/STAGE``: a trained stage's planner behind the wheel of the synthetic world.

Each route is a scene of the synthetic world built from a route seed (drawn from ``--seed``
as ``occtrain data synth`` draws its scene seeds, so ``--seed`` other than the training
worlds' gives routes no training saw). On every route the stage drives (its kind's
``Stage.driver``: a world model's ``plan`` operation, a planner stage's head), and so do the
baselines: the simulator's own expert (the route follower that generated the data),
constant velocity, constant acceleration (from the ego's past: ``kinematics``) and
standing still. The ego replans every 0.5 s and follows each plan
through a kinematic bicycle in between; the traffic reacts to it.

Results go to ``<stage>/drive/seed<S>-<T>s/``: one JSON per episode, written as it ends (a
killed ``drive`` resumes at the first episode without one), then ``summary.json`` with the
mean scores of each driver (``metrics.closed_loop_scores``: CARLA's driving score, NAVSIM's PDM score
and their terms) and who drove its planning frames: the stage with a plan of its own, its
constant-velocity fallback, or the expert (the history its prompts read). An episode too
short for the stage to plan once is refused. ``--save-videos DIR`` also writes a bird's-eye
GIF of every episode (an episode driven earlier without one is driven again for it). A stop
signal ends the drive in one line, its temporary files removed; the episodes written stay.
"""

from __future__ import annotations

import functools
import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from occtrain.engine.closed_loop.baselines import BASELINES
from occtrain.engine.closed_loop.planners import refuse_short_episodes
from occtrain.engine.closed_loop.workers import driver_for, run_jobs
from occtrain.errors import ConfigError
from occtrain.formats.io import atomic_write_json, check_output
from occtrain.formats.metrics_file import Provenance
from occtrain.progress import console, print_wide, progress_bar
from occtrain.run.control import Interrupted, stop_on_signals
from occtrain.run.done_stage import DoneStage, done_stage

#: The job that scores the plans open loop on the same routes (the expert drives; see ``shadow_episode``).
OPEN_LOOP = "open-loop"
#: What the scores follow, written into every result.
CONVENTIONS = {
    "driving_score": "CARLA leaderboard 1.0 (route completion x infraction penalties)",
    "pdm_score": "NAVSIM v1 (NC x DAC x (5 TTC + 5 EP + 2 C) / 12), over the whole reactive episode",
    "comfort": "nuPlan ego_is_comfortable bounds on Savitzky-Golay-smoothed signals",
}


@dataclass(frozen=True)
class DriveJob:
    """One episode: who drives which route."""

    driver: str
    route: int
    route_seed: int
    seconds: float


def route_seeds(seed: int, routes: int) -> list[int]:
    """The scene seed of each route, drawn from ``seed`` as the synthesizer draws its scenes'."""
    return [int(np.random.SeedSequence([seed, i]).generate_state(1)[0]) for i in range(routes)]


def drive_dir(stage_dir: str | Path, seed: int, seconds: float) -> Path:
    return Path(stage_dir) / "drive" / f"seed{seed}-{seconds:g}s"


#: The most routes one drive takes (each is five episodes and a JSON file apiece): a bigger
#: study is several drives over other ``--seed`` values, each resumable on its own.
MAX_ROUTES = 10_000
#: Seeds numpy's generators accept.
MAX_SEED = 2**32 - 1


_WRITABLE = "drive writes its results into {stage_dir}; make it writable, or copy the run and drive the copy"


def drive(
    stage_dir: str | Path,
    routes: int = 8,
    seed: int = 1000,
    seconds: float = 20.0,
    workers: int = 1,
    save_videos: str | Path | None = None,
) -> dict[str, dict[str, float]]:
    """Drive the stage and the baselines on ``routes`` routes; each driver's mean scores. The
    stage is held (a shared lock: a ``--restart`` of it waits) while its results are written."""
    from occtrain.run.control import scoring_lock
    from occtrain.version import code_version

    start = time.perf_counter()
    stage_dir = Path(stage_dir)
    workers = _check_arguments(routes, seed, seconds, workers)
    done = done_stage(stage_dir, "occtrain drive", "drives", lambda module: module.drivable)
    history = planning_history(stage_dir, list(done.spec.consumes))
    refuse_short_episodes(seconds, history, "--seconds")
    out = drive_dir(stage_dir, seed, seconds)
    check_output(out / "summary.json", "the drive results", kind="file", fix=_WRITABLE.format(stage_dir=stage_dir))
    videos = None if save_videos is None else check_output(save_videos, "--save-videos", kind="dir")
    drivers = [done.spec.name, *BASELINES]
    jobs = [DriveJob(d, i, s, seconds) for i, s in enumerate(route_seeds(seed, routes)) for d in [*drivers, OPEN_LOOP]]
    # An episode driven earlier without its animation, or from another start, is driven again.
    todo = [j for j in jobs if not _episode_done(out, j, history) or (videos is not None and not _has_video(videos, j))]
    camera = (done.recipe.data.synth.camera_height, done.recipe.data.synth.camera_width)
    workers = min(workers, max(1, len(todo)))
    with (
        scoring_lock(stage_dir, "occtrain drive"),
        stop_on_signals(),
        tempfile.TemporaryDirectory(prefix="occtrain-drive-") as scratch,
    ):
        context = _EpisodeContext(
            str(stage_dir), camera, str(out), str(videos) if videos else None, scratch, code_version(), history
        )
        try:
            with progress_bar(len(jobs), f"driving {routes} routes of {seconds:g} s: {', '.join(drivers)}") as advance:
                advance(len(jobs) - len(todo))
                run_jobs(functools.partial(_run_episode, context), todo, workers, advance)
        except Interrupted as stop:
            left = sum(not _episode_file(out, j).is_file() for j in jobs)
            raise stop.with_message(
                f"occtrain drive of {stage_dir} {stop}; {len(jobs) - left} of {len(jobs)} episodes are written under "
                f"{out}, run the same command again to drive the rest"
            ) from None
        done.refuse_changed("occtrain drive")
        summary = summarize(out, jobs, drivers)
        gifs = {f"{j.driver}-{j.route:03d}": videos / f"{j.driver}-{j.route:03d}.gif" for j in jobs} if videos else {}
        atomic_write_json(
            out / "summary.json",
            {"stage": done.spec.name, "routes": routes, "seed": seed, "seconds": seconds, "conventions": CONVENTIONS}
            | {"drivers": summary, "videos": {k: str(p.resolve()) for k, p in gifs.items() if p.is_file()}}
            # How long this invocation took: the whole drive only when no episode was resumed.
            | {"wall_s": round(time.perf_counter() - start, 1), "workers": workers, "resumed": len(jobs) - len(todo)}
            | {"expert_start_frames": history}
            | {"provenance": _provenance(done, routes, seed, seconds, _codes(out, jobs)).to_json()},
        )
    _refresh_dashboard(stage_dir.parent)
    return summary


def _codes(out: Path, jobs: list[DriveJob]) -> str:
    """The code that drove the episodes, every version where a resumed drive's differ."""
    codes = {json.loads(_episode_file(out, job).read_text()).get("code_version", "not recorded") for job in jobs}
    return ", ".join(sorted(codes))


def _provenance(done: DoneStage, routes: int, seed: int, seconds: float, code: str) -> Provenance:
    """What a drive's numbers were measured on: the routes (the world is the route seeds'),
    the code that drove them, and the attempt of the stage that drove."""
    return Provenance(
        by="occtrain drive",
        split=f"routes of seed {seed}",
        coverage={"routes": [routes, routes]},
        world_name=f"{routes} routes of {seconds:g} s drawn from seed {seed}",
        code_version=code,
        stage=done.attempt,
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )


def _check_arguments(routes: int, seed: int, seconds: float, workers: int) -> int:
    """Refuse arguments no drive can take, in one line each; the workers this machine can run."""
    from occtrain.data.closed_loop_recording import MAX_SECONDS

    if not 1 <= routes <= MAX_ROUTES:
        raise ConfigError(
            f"--scenes {routes}: drive 1 to {MAX_ROUTES} routes at a time (drive more as several drives over other "
            "--seed values)"
        )
    if not 0 <= seed <= MAX_SEED:
        raise ConfigError(f"--seed {seed}: a route seed is a whole number from 0 to {MAX_SEED}")
    if not 0 < seconds <= MAX_SECONDS:
        raise ConfigError(f"--seconds {seconds:g}: an episode lasts more than 0 and at most {MAX_SECONDS:g} s")
    cores = len(os.sched_getaffinity(0))
    if not 1 <= workers <= cores:
        raise ConfigError(
            f"--workers {workers}: give 1 to {cores} (the cores this process may use; each worker drives on its own)"
        )
    return workers


def planning_history(stage_dir: Path, consumes: list[str]) -> int:
    """The frames before the current one the stage's prompts read, from its exports' configs
    (a world model's, or the world model a planner stage reads): the expert drives them."""
    from occtrain.formats.exports import read_config

    for export in [stage_dir / "export", *(stage_dir.parent / dep / "export" for dep in consumes)]:
        config = read_config(export)
        if config.get("stage_kind") == "world_model":
            tasks = config.get("tasks")
            return int(tasks.get("context_frames", 0)) if isinstance(tasks, dict) else 0
    return 0


def _has_video(videos: Path, job: DriveJob) -> bool:
    return job.driver == OPEN_LOOP or (videos / f"{job.driver}-{job.route:03d}.gif").is_file()


def _refresh_dashboard(run_dir: Path) -> None:
    """The run's dashboard drawn again, now with the drive beside the stage's open-loop numbers."""
    from occtrain.dashboard import write_dashboard
    from occtrain.errors import OcctrainError

    try:
        write_dashboard(run_dir)
    except OcctrainError as err:  # the results are written; a dashboard that cannot be is said, not fatal
        console.print(f"[yellow]dashboard not updated[/]: {err}")


def summarize(out: Path, jobs: list[DriveJob], drivers: list[str]) -> dict[str, dict[str, float]]:
    """Each driver's mean scores over its episodes' result files."""
    from occtrain.metrics.closed_loop_scores import DrivingScores, aggregate

    per: dict[str, list[DrivingScores]] = {d: [] for d in drivers}
    who: dict[str, dict[str, int] | None] = {d: dict.fromkeys(PLAN_COUNTS, 0) for d in drivers}
    open_loop: list[dict[str, Any]] = []
    for job in jobs:
        record = json.loads(_episode_file(out, job).read_text())
        if job.driver == OPEN_LOOP:
            open_loop.append(record)
            continue
        scores: dict[str, Any] = record["scores"]  # JSON has no infinity: a time to collision never met is null
        fields: dict[str, Any] = {
            k: float("inf") if scores[k] is None else scores[k] for k in DrivingScores.__dataclass_fields__
        }
        per[job.driver].append(DrivingScores(**fields))
        counts, total = record.get("planning_frames"), who[job.driver]
        if counts is None or total is None:  # an episode driven before drives counted its frames
            who[job.driver] = None
        else:
            who[job.driver] = {k: total[k] + int(counts[k]) for k in PLAN_COUNTS}
    summary = {d: aggregate(scores) | _plan_shares(who[d]) for d, scores in per.items()}
    for driver, scores in open_loop_means(open_loop).items():
        summary.setdefault(driver, {}).update(scores)
    return summary


#: Who drove a driver's planning frames, counted per episode (``engine.closed_loop.PlanCounts``).
PLAN_COUNTS = ("frames", "planned", "fell_back", "expert")


def _plan_shares(counts: dict[str, int] | None) -> dict[str, float]:
    """The planning frames of a driver's episodes and the share it planned itself, fell back
    on constant velocity for, and left to the expert (percent); none when not counted."""
    if counts is None or not counts["frames"]:
        return {}
    shares = {f"{k}_share": 100.0 * counts[k] / counts["frames"] for k in PLAN_COUNTS[1:]}
    return {"planning_frames": float(counts["frames"]), **shares}


def open_loop_means(records: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Each planner's open-loop L2 and collision rate (``stp3``) over the routes' frames
    (weighted by frames); the expert's are 0: its plan is the log."""
    frames = sum(r["frames"] for r in records)
    out: dict[str, dict[str, float]] = {"expert": {"open_loop_L2_stp3_avg": 0.0, "open_loop_collision_stp3_avg": 0.0}}
    if not frames:
        return out
    for name in records[0]["planners"]:
        out[name] = {
            f"open_loop_{metric}_stp3_avg": sum(r["frames"] * r["planners"][name][metric] for r in records) / frames
            for metric in ("L2", "collision")
        }
    return out


@dataclass(frozen=True)
class _EpisodeContext:
    stage_dir: str
    camera: tuple[int, int]
    out: str
    videos: str | None
    #: Where episodes keep their frames and the stage its caches: removed by the drive as it ends.
    scratch: str
    #: The code driving, recorded with each episode (a drive resumed by other code names both).
    code: str
    #: Planning frames the expert drives first, for every driver: what the stage's prompts read.
    history: int


@dataclass(frozen=True)
class _StageSpec:
    """The stage's driver as a worker builds it (``workers.DriverSpec``): its caches in the
    drive's scratch, fresh (a planner's caches are keyed by sample token, and the stage's own
    hold its dataset's frames, not these)."""

    stage_dir: str
    scratch: str

    @property
    def key(self) -> str:
        return f"{self.stage_dir}\0{self.scratch}"

    def build(self) -> Any:
        from occtrain.stages.stage import EvalRequest

        stage_dir = Path(self.stage_dir)
        done = done_stage(stage_dir, "occtrain drive", "drives", lambda module: module.drivable)
        request = EvalRequest(
            stage_dir / "export",
            [stage_dir.parent / dep / "export" for dep in done.spec.consumes],
            done.recipe.data.root,
            cache_dir=Path(tempfile.mkdtemp(prefix="cache-", dir=self.scratch)),
        )
        return done.kind.module.driver(request)


def _episode_file(out: Path, job: DriveJob) -> Path:
    return out / "episodes" / f"{job.driver}-{job.route:03d}.json"


def _episode_done(out: Path, job: DriveJob, history: int) -> bool:
    """Whether the episode was driven already, from the same start (an earlier drive's
    baselines planned from frame 0: theirs is another episode)."""
    file = _episode_file(out, job)
    try:
        return file.is_file() and json.loads(file.read_text()).get("expert_start_frames") == history
    except ValueError:
        return False


def _stage_reader(context: _EpisodeContext, world: Any, frames: str, episode: str) -> tuple[Any, Any]:
    """The stage's driver and a recorder of ``world``'s planning frames under ``frames``
    (with the cameras when its encoders read them), tokened apart as ``episode``'s."""
    from occtrain.data.closed_loop_recording import EpisodeRecorder

    driver = driver_for(_StageSpec(context.stage_dir, context.scratch))
    reads_cameras = driver.engine.vision is not None or driver.engine.scenes_from_cameras()
    return driver, EpisodeRecorder(frames, world, context.camera if reads_cameras else None, episode)


def _run_episode(context: _EpisodeContext, job: DriveJob) -> None:
    """Drive one episode and write its result (and its animation)."""
    from occtrain.engine.closed_loop import NonFinitePlan

    try:
        _drive_episode(context, job)
    except NonFinitePlan as err:  # the stage's own fault, said with where it happened
        raise NonFinitePlan(f"{context.stage_dir}, route {job.route} ({job.driver} episode): {err}") from None


def _drive_episode(context: _EpisodeContext, job: DriveJob) -> None:
    from occtrain.data.closed_loop_recording import STRIDE, save_gif
    from occtrain.engine.closed_loop.baselines import baseline_planner
    from occtrain.engine.closed_loop.episodes import drive_episode
    from occtrain.engine.closed_loop.planners import PlanCounts, model_planner
    from occtrain.engine.closed_loop.workers import fresh_world
    from occtrain.metrics.closed_loop_scores import score_episode

    start = time.perf_counter()
    world = fresh_world(job.route_seed, job.seconds)
    views: list | None = [] if context.videos else None
    if job.driver == OPEN_LOOP:
        _write_open_loop(context, job, world, start)
        return
    with tempfile.TemporaryDirectory(prefix="frames-", dir=context.scratch) as frames:
        if job.driver in BASELINES:
            planner = baseline_planner(job.driver, context.history)
            trace = drive_episode(world, planner, views)
            # The expert drove every planning frame reached (the loop plans at each until the episode ends).
            counts = PlanCounts(expert=-(-world.step // STRIDE)) if planner is None else planner.counts
        else:
            stage = model_planner(*_stage_reader(context, world, frames, job.driver))
            trace = drive_episode(world, stage, views)
            counts = stage.counts
    scores = score_episode(trace)
    record = {
        "driver": job.driver,
        "route": job.route,
        "route_seed": job.route_seed,
        "seconds": job.seconds,
        "scores": scores.as_dict(),
        "planning_frames": asdict(counts) | {"frames": counts.frames},
        "infractions": [asdict(i) for i in trace.infractions],
        "wall_s": round(time.perf_counter() - start, 2),
        "conventions": CONVENTIONS,
        "code_version": context.code,
        "expert_start_frames": context.history,
    }
    out = Path(context.out)
    if context.videos and views:
        save_gif(world.static, views, Path(context.videos) / f"{job.driver}-{job.route:03d}.gif", 0.5)
    atomic_write_json(_episode_file(out, job), record)


def _write_open_loop(context: _EpisodeContext, job: DriveJob, world: Any, start: float) -> None:
    """The stage's plans and the baselines' scored open loop on the route (the expert drives;
    ST-P3's convention, collisions against the agents where they then were)."""
    import torch

    from occtrain.engine.closed_loop.baselines import RULES
    from occtrain.engine.closed_loop.episodes import shadow_episode
    from occtrain.engine.closed_loop.planners import OpenLoopPlanner
    from occtrain.metrics.planning import PlanningMetric

    stage = Path(context.stage_dir).name
    with tempfile.TemporaryDirectory(prefix="frames-", dir=context.scratch) as frames:
        model = OpenLoopPlanner(*_stage_reader(context, world, frames, OPEN_LOOP))
        baselines = dict(RULES)
        shadow = shadow_episode(world, {stage: model, **baselines})
        for frame, plan in zip(shadow, model.plans(len(shadow))):  # the first planning frames, in order
            frame.plans[stage] = plan
    # Scored where the stage planned: every planner on the same frames.
    shadow = [f for f in shadow if f.plans[stage] is not None]
    scores: dict[str, dict[str, float]] = {}
    for name in [stage, *baselines]:
        metric = PlanningMetric()
        if shadow:
            metric.update(
                torch.from_numpy(np.stack([np.asarray(f.plans[name]) for f in shadow])),
                torch.from_numpy(np.stack([f.logged for f in shadow])),
                torch.ones(len(shadow), 6),
                [f.agents for f in shadow],
            )
            result = metric.compute()
            scores[name] = {"L2": float(result["L2_stp3"]["avg"]), "collision": float(result["collision_stp3"]["avg"])}
        else:
            scores[name] = {"L2": float("nan"), "collision": float("nan")}
    record = {
        "driver": OPEN_LOOP,
        "route": job.route,
        "route_seed": job.route_seed,
        "seconds": job.seconds,
        "frames": len(shadow),
        "planners": scores,
        "wall_s": round(time.perf_counter() - start, 2),
        "conventions": {"L2": "stp3 (ST-P3 / VAD)", "collision": "stp3, agents from the simulator"},
        "code_version": context.code,
        "expert_start_frames": context.history,
    }
    atomic_write_json(_episode_file(Path(context.out), job), record)


def print_summary(summary: dict[str, dict[str, float]], title: str) -> None:
    """The drivers' mean scores as a table."""
    from rich.table import Table

    from occtrain.metrics.closed_loop_scores import TABLE_COLUMNS as columns

    table = Table(title=title)
    table.add_column("driver")
    for name, _, _ in columns:
        table.add_column(name, justify="right")
    for driver, scores in summary.items():
        table.add_row(driver, *(fmt.format(scores.get(key, float("nan"))) for _, key, fmt in columns))
    print_wide(table)

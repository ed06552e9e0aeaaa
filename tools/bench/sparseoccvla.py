"""SparseOccVLA's costs, each measured side by side in one run.

    python tools/bench/sparseoccvla.py planner [--stage runs/sparseoccvla/planner] [--steps 1,2,3]
    python tools/bench/sparseoccvla.py tokens  [--sparse runs/sparseoccvla/stage2] [--dense runs/occvla/stage1]
    python tools/bench/sparseoccvla.py chamfer [--points 4096] [--gt 2048] [--batch 4]

``planner``: the trained anchor-diffusion planner on every val clip with a whole 3 s
future, denoising its anchors in 1, 2 (the paper's) and 3 DDIM steps. The steps are
interleaved per batch, in a rotating order, so machine noise falls on each alike; the
world model's decisions are computed once beforehand (they are the same for every step
count and are cached by training anyway). It prints seconds per batch and L2 (ST-P3) per
step count: the paper's Table 11 finds 2 steps as good as 3.

``tokens``: what each family's LLM reads per frame and what one training step costs, on
two finished world-model stages (SparseOccVLA's stage 2, OccVLA's stage 1 by default):
scene tokens per frame (the vocabulary's scene length) and image tokens in a laid-out
training sequence, the batch's mean sequence length, and
the forward + backward time of one batch and the peak resident memory of a process that
runs only that (each family in its own child process, alternating, ``--repeats`` times).
The paper's Tables 12-13: 612 tokens against HERMES' 2,500, about half the memory.

``chamfer``: the nearest-point search inside every Chamfer loss (Eq. 1, 11), both
directions, on a forecaster frame's sizes (64 queries x 64 points against 2,048 ground-truth
voxel centres): dense distances (argmin of ``torch.cdist``) against the k-d tree the CPU
path uses, interleaved on the same inputs; the two must match the same pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import torch  # noqa: E402
from records import Row, record  # noqa: E402

from occtrain.config import load_config  # noqa: E402
from occtrain.config.recipe import RecipeConfig  # noqa: E402
from occtrain.data.clips import frame_clips, plan_target  # noqa: E402
from occtrain.data.layout import DatasetIndex  # noqa: E402
from occtrain.engine import load_world_model  # noqa: E402
from occtrain.formats.occ3d import FUTURE_STEPS  # noqa: E402
from occtrain.metrics import PlanningMetric  # noqa: E402
from occtrain.stages.stage import shared_cache_dir  # noqa: E402


def _recipe(stage: Path) -> RecipeConfig:
    return load_config(RecipeConfig, stage.parent / "pipeline.yaml")


def bench_planner(stage: Path, steps: list[int], batch: int) -> None:
    from occtrain.stages.planner import PlannerStage
    from occtrain.stages.stage import EvalRequest

    recipe = _recipe(stage)
    spec = next(s for s in recipe.stages if s.name == stage.name)
    request = EvalRequest(
        stage / "export",
        [stage.parent / d / "export" for d in spec.consumes],
        recipe.data.root,
        cache_dir=stage / "cache",
        shared_cache_dir=shared_cache_dir(stage),
    )
    planner, clips = PlannerStage.rebuild(request)
    batches = [clips[i : i + batch] for i in range(0, len(clips), batch)]
    for b in batches:  # the decisions, once: the same for every step count
        planner.decisions(b)
    times = {s: 0.0 for s in steps}
    metrics = {s: PlanningMetric() for s in steps}
    planner.plan(batches[0], steps=steps[0])  # warm-up
    for i, b in enumerate(batches):
        gt = plan_target([c.anchor for c in b], planner.device)
        for s in steps[i % len(steps) :] + steps[: i % len(steps)]:
            start = time.perf_counter()
            plan, _, _ = planner.plan(b, steps=s)
            times[s] += time.perf_counter() - start
            metrics[s].update(plan, gt.traj, gt.mask, gt.agents)
    print(f"{stage}: {len(clips)} val clips in {len(batches)} batches of {batch}, {planner.cfg.anchors} anchors")
    base = times[steps[0]]
    shown = []
    for s in steps:
        l2 = metrics[s].compute()["L2_stp3"]
        print(
            f"  {s} DDIM step(s): {1e3 * times[s] / len(batches):7.2f} ms/batch ({times[s] / base:.2f}x {steps[0]} "
            "step), "
            f"L2 stp3 1s/2s/3s/avg {l2['1s']:.3f} / {l2['2s']:.3f} / {l2['3s']:.3f} / {l2['avg']:.3f} m"
        )
        shown.append(f"{s} step(s) {1e3 * times[s] / len(batches):.1f} ms, L2 {l2['avg']:.3f} m")
    record(
        [
            Row(
                f"SparseOccVLA's anchor-diffusion planner on {len(clips)} val clips in batches of {batch}, its "
                "anchors denoised in " + " / ".join(map(str, steps)) + " DDIM steps, interleaved per batch",
                "; ".join(shown) + " (a batch; L2 `stp3` average)",
            )
        ]
    )


def measure_step(stage: Path, batch: int, steps: int) -> dict:
    """In this process (a child): one family's world model, one training batch laid out,
    forward + backward ``steps`` times; tokens per frame, the sequence length, seconds per
    step and the process's peak resident memory (MB)."""
    import resource

    recipe = _recipe(stage)
    engine = load_world_model(stage / "export")
    engine.prepare_inputs(recipe.data.root, stage / "cache", shared_cache_dir(stage))
    engine.train()
    clips = list(
        frame_clips(
            DatasetIndex.open(recipe.data.root),
            "train",
            engine.tasks.context_frames,
            FUTURE_STEPS,
            partial_history=False,
        )
    )[:batch]
    laid, _ = engine.task_batch(clips, {"ann": [c.ann for c in clips]}, seed=0)
    params = [p for p in engine.world.parameters() if p.requires_grad]
    engine.world(laid).loss.backward()  # warm-up
    start = time.perf_counter()
    for _ in range(steps):
        for p in params:
            p.grad = None
        engine.world(laid).loss.backward()
    step_s = (time.perf_counter() - start) / steps
    ids = laid["input_ids"]
    images = int(engine.vocab.is_image(ids[0]).sum()) if engine.vocab.image else 0
    return {
        "family": engine.family,
        "scene_tokens": int(engine.vocab.scene_len),
        "image_tokens": images,
        "sequence_length": float((ids != engine.vocab.pad_id).sum(1).float().mean()),
        "batch": len(clips),
        "step_s": step_s,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def bench_tokens(sparse: Path, dense: Path, batch: int, steps: int, repeats: int) -> None:
    results: dict[str, list[dict]] = {"sparse": [], "dense": []}
    for rep in range(repeats):
        for name in ("sparse", "dense") if rep % 2 == 0 else ("dense", "sparse"):
            stage = sparse if name == "sparse" else dense
            out = subprocess.run(
                [sys.executable, __file__, "_step", str(stage), "--batch", str(batch), "--steps", str(steps)],
                capture_output=True,
                text=True,
                check=True,
            )
            results[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(
        f"one training step (forward + backward), batch {batch}, {steps} steps x {repeats} alternating processes each"
    )
    row = {}
    for name, runs in results.items():
        r = runs[0]
        step = sorted(x["step_s"] for x in runs)[len(runs) // 2]
        rss = max(x["peak_rss_mb"] for x in runs)
        row[name] = (step, rss)
        print(
            f"  {r['family']:>12}: {r['scene_tokens']:4d} scene + {r['image_tokens']:3d} image tokens per frame, "
            f"mean sequence {r['sequence_length']:6.1f}, "
            f"{1e3 * step:7.1f} ms/step (median), peak RSS {rss:7.0f} MB"
        )
    (s_step, s_rss), (d_step, d_rss) = row["sparse"], row["dense"]
    print(f"  -> sparse / dense: step time {s_step / d_step:.2f}x, peak RSS {s_rss / d_rss:.2f}x")
    s_run, d_run = results["sparse"][0], results["dense"][0]
    record(
        [
            Row(
                f"one training step (forward and backward, batch {batch}) of SparseOccVLA's stage 2 vs OccVLA's "
                f"stage 1, {repeats} alternating processes each",
                f"mean sequence {s_run['sequence_length']:.0f} vs {d_run['sequence_length']:.0f} tokens; "
                f"{1e3 * s_step:.0f} vs {1e3 * d_step:.0f} ms a step ({s_step / d_step:.2f}x); peak RSS "
                f"{s_rss:.0f} vs {d_rss:.0f} MB ({s_rss / d_rss:.2f}x)",
            )
        ]
    )


def bench_chamfer(points: int, gt_points: int, batch: int, repeats: int) -> None:
    from occtrain.models import point_sets

    gen = torch.Generator().manual_seed(0)
    pred = torch.randn(batch, points, 3, generator=gen) * 15
    # Distinct voxel centres, as occupied_points draws them; a tenth of them padding.
    cells = torch.stack([torch.randperm(200 * 200 * 16, generator=gen)[:gt_points] for _ in range(batch)])
    gt = point_sets.voxel_centres(torch.stack([cells // (200 * 16), cells // 16 % 200, cells % 16], -1))
    valid = torch.rand(batch, gt_points, generator=gen) > 0.1

    searches = {"dense cdist": point_sets._nearest_dense, "k-d tree": point_sets._nearest_by_tree}
    times: dict[str, list[float]] = {name: [] for name in searches}
    matches = {}
    for rep in range(repeats):
        for name in list(searches) if rep % 2 == 0 else list(searches)[::-1]:
            t = time.perf_counter()
            # Both directions of Eq. 1: each point to its nearest real truth, each truth to its nearest point.
            matches[name] = (searches[name](pred, gt, valid), searches[name](gt, pred))
            times[name].append(time.perf_counter() - t)
    same = all(torch.equal(a, b) for a, b in zip(*matches.values()))
    print(
        f"Chamfer's nearest-point search, both directions, {batch} x {points} points against {gt_points}, {repeats} "
        "alternating runs each"
    )
    med = {name: sorted(ts)[len(ts) // 2] for name, ts in times.items()}
    for name, t in med.items():
        print(f"  {name:>11}: {1e3 * t:8.1f} ms (median)")
    print(f"  -> dense / tree: {med['dense cdist'] / med['k-d tree']:.1f}x; the same nearest pairs: {same}")
    record(
        [
            Row(
                f"the nearest-point search of every Chamfer loss, both directions, {batch} x {points} points "
                f"against {gt_points} voxel centres, {repeats} alternating runs: dense `torch.cdist` vs a k-d tree",
                f"{1e3 * med['dense cdist']:.0f} vs {1e3 * med['k-d tree']:.0f} ms (median; "
                f"{med['dense cdist'] / med['k-d tree']:.1f}x); the same nearest pairs: {same}",
            )
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("planner", help="1 / 2 / 3 DDIM steps of the anchor-diffusion planner")
    p.add_argument("--stage", default="runs/sparseoccvla/planner")
    p.add_argument("--steps", default="1,2,3", help="step counts, comma-separated")
    p.add_argument("--batch", type=int, default=8)
    t = sub.add_parser("tokens", help="scene tokens, step time and peak RSS: SparseOccVLA vs OccVLA")
    t.add_argument("--sparse", default="runs/sparseoccvla/stage2")
    t.add_argument("--dense", default="runs/occvla/stage1")
    t.add_argument("--batch", type=int, default=4)
    t.add_argument("--steps", type=int, default=5)
    t.add_argument("--repeats", type=int, default=2)
    ch = sub.add_parser("chamfer", help="the Chamfer loss's nearest-point search: dense distances vs a k-d tree")
    ch.add_argument("--points", type=int, default=4096)
    ch.add_argument("--gt", type=int, default=2048)
    ch.add_argument("--batch", type=int, default=4)
    ch.add_argument("--repeats", type=int, default=6)
    c = sub.add_parser("_step")  # the child process of `tokens`
    c.add_argument("stage")
    c.add_argument("--batch", type=int)
    c.add_argument("--steps", type=int)
    args = parser.parse_args()
    if args.what == "planner":
        bench_planner(Path(args.stage), [int(s) for s in args.steps.split(",")], args.batch)
    elif args.what == "tokens":
        bench_tokens(Path(args.sparse), Path(args.dense), args.batch, args.steps, args.repeats)
    elif args.what == "chamfer":
        bench_chamfer(args.points, args.gt, args.batch, args.repeats)
    else:
        print(json.dumps(measure_step(Path(args.stage), args.batch, args.steps)))


if __name__ == "__main__":
    main()

"""Does a change keep what the shipped recipes compute? Run them shrunk, then compare.

    python tools/compare_recipes.py run before/            # every shipped recipe, shrunk, one thread
    ... change the code ...
    python tools/compare_recipes.py run after/
    python tools/compare_recipes.py compare before/ after/

    python tools/compare_recipes.py run before/ --repo ../old-worktree   # an older tree's code and recipes

``run`` trains each recipe with the same overrides (a 3-scene world, ``--steps`` optimizer
steps per stage, a small validation) through the real CLI at one thread, so two runs of
the same code agree bit for bit. ``compare`` lists, stage by stage, every final metric
that differs (wall-clock timings left out) and every exported tensor that differs or
exists on one side only (every ``*.safetensors`` under ``export/``, the Hugging Face LLM
directory included), and exits 1 when anything does, or when a stage left no metrics and
no export on a side (MISSING: it did not run to the end there).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import yaml

from occtrain.stages.callbacks import MEASURED

REPO = Path(__file__).resolve().parents[1]
#: Where the recipes live, newest layout first (they were in stages/ before recipes/).
RECIPE_DIRS = ("recipes", "stages")
#: Recipes that only size a stage for ``occtrain plan-memory`` (a 7B LLM): never trained here.
PLAN_ONLY = "scale/"


def shipped_recipes(repo: Path) -> list[str]:
    """Every recipe a refactoring must leave unchanged: the shipped ones but the plan-only sizes,
    by name relative to the recipes folder (``quickstart``, ``ablations/occllm_msvae``)."""
    folder = recipes_dir(repo)
    names = (str(p.relative_to(folder).with_suffix("")) for p in folder.rglob("*.yaml"))
    return sorted(n for n in names if not n.startswith(PLAN_ONLY))


def recipes_dir(repo: Path) -> Path:
    return next((repo / d for d in RECIPE_DIRS if (repo / d / "quickstart.yaml").is_file()), repo / RECIPE_DIRS[0])


#: Stage kinds that generate answers in validation (they take ``model.val_samples``).
GENERATING = ("pretrain", "instruct", "distill")
#: Metrics that measure the machine, not the model (the stages' step meter's, and
#: distillation's generation speedup).
TIMINGS = ("speedup", *MEASURED)


def shrink(recipe: Path, data: Path, steps: int, frames: int = 16) -> list[str]:
    """Overrides that make ``recipe`` a few-minute run on a 3-scene world."""
    stages = yaml.safe_load(recipe.read_text())["stages"]
    out = [
        f"data.root={data}",
        f"data.shards={data / ('shards_' + recipe.stem)}",
        "data.synth.train_scenes=2",
        "data.synth.val_scenes=1",
        f"data.synth.frames_per_scene={frames}",
        "data.samples_per_shard=8",
        "data.shuffle_buffer=4",
        "trainer.ckpt_every_n_steps=1000",
    ]
    for i, stage in enumerate(stages):
        out += [
            f"stages[{i}].trainer.max_steps={steps}",
            f"stages[{i}].trainer.val_check_interval={steps}",
            f"stages[{i}].trainer.limit_val_batches=2",
        ]
        if stage["kind"] in GENERATING:
            out.append(f"stages[{i}].model.val_samples=6")
        if stage["kind"] == "vision":
            out.append(f"stages[{i}].model.prior_batches=2")
        if stage["kind"] == "planner":
            out.append(f"stages[{i}].model.generate_batches=1")
    return out


def run(out: Path, recipes: list[str], steps: int, repo: Path = REPO, frames: int = 16) -> int:
    """Train ``recipes`` of ``repo``, shrunk, with ``repo``'s own code (its ``src`` first on the path)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONWARNINGS="ignore", PYTHONHASHSEED="0")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo / "src"), os.environ.get("PYTHONPATH", "")]))
    failed = []
    for name in recipes:
        recipe = recipes_dir(repo) / f"{name}.yaml"
        # One world per data config (the OccVLA recipe reads 6 history frames from its own shards).
        data = out / "data"
        cmd = [
            sys.executable,
            "-m",
            "occtrain",
            "run",
            str(recipe),
            *shrink(recipe, data, steps, frames),
            "--run-dir",
            str(out / name.replace("/", "__")),
        ]
        print(f"== {name}", file=sys.stderr, flush=True)
        if subprocess.run(cmd, cwd=repo, env=env).returncode != 0:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def _metrics(stage_dir: Path) -> dict[str, float]:
    path = stage_dir / "metrics.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    return {k: v for k, v in data.items() if not k.endswith(TIMINGS)}


def _tensors(stage_dir: Path) -> dict[str, object]:
    from safetensors.torch import load_file

    out: dict[str, object] = {}
    for f in sorted((stage_dir / "export").rglob("*.safetensors")):
        rel = f.relative_to(stage_dir / "export")
        out.update({f"{rel}:{k}": v for k, v in load_file(str(f)).items()})
    return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def compare(before: Path, after: Path) -> int:
    import torch

    problems = 0
    for run_dir in sorted(p for p in before.iterdir() if (p / "manifest.json").is_file()):
        other = after / run_dir.name
        stages = json.loads((run_dir / "manifest.json").read_text())["stages"]
        for stage in stages:
            a_dir, b_dir = run_dir / stage, other / stage
            a_m, b_m = _metrics(a_dir), _metrics(b_dir)
            diff = sorted(k for k in set(a_m) | set(b_m) if not _same(a_m.get(k), b_m.get(k)))
            a_t, b_t = _tensors(a_dir), _tensors(b_dir)
            only = sorted(set(a_t) ^ set(b_t))
            changed = sorted(
                k for k in set(a_t) & set(b_t) if a_t[k].shape != b_t[k].shape or not torch.equal(a_t[k], b_t[k])
            )
            # A stage that did not finish on a side has nothing to differ in: that is no "same".
            missing = not (a_m or a_t) or not (b_m or b_t)
            status = "MISSING" if missing else "same" if not (diff or only or changed) else "DIFFERS"
            print(f"{run_dir.name:36s} {stage:10s} {status:8s} {len(a_m)} metrics, {len(a_t)} tensors")
            for k in diff[:10]:
                print(f"    metric {k}: {a_m.get(k)} -> {b_m.get(k)}")
            for k in only[:10]:
                print(f"    tensor {k} only {'before' if k in a_t else 'after'}")
            for k in changed[:10]:
                same_shape = a_t[k].shape == b_t[k].shape
                diff = float((a_t[k].float() - b_t[k].float()).abs().max()) if same_shape else "shape"
                print(f"    tensor {k} changed (max |diff| {diff})")
            problems += status != "same"
    return 1 if problems else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train the shipped recipes, shrunk, into OUT/<recipe>")
    r.add_argument("out", type=Path)
    r.add_argument("--recipes", help="comma-separated names (default: every shipped recipe but scale/)")
    r.add_argument("--steps", type=int, default=24)
    r.add_argument("--repo", type=Path, default=REPO, help="the tree whose code and recipes run (default: this one)")
    # SparseOccVLA's 21-anchor variant needs 21 whole 3 s futures: 18 frames a scene give them.
    r.add_argument("--frames", type=int, default=16, help="frames per scene of the shrunk world (default 16)")
    c = sub.add_parser("compare", help="compare two OUT directories")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    if args.cmd == "run":
        repo = args.repo.resolve()
        recipes = args.recipes.split(",") if args.recipes else shipped_recipes(REPO)
        return run(args.out.resolve(), recipes, args.steps, repo, args.frames)
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())

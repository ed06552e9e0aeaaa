"""The contract every family with a world model keeps, checked the same way on each
family's tiny end-to-end run (as transformers' ModelTesterMixin checks every model):

- every task it registers builds its parts on the run's world, unless the world lacks
  what the task reads (``DatasetIndex.available_tasks`` says why);
- every scorer of the tasks its stage trained scores a small batch: metrics it names come
  out of the evaluator, none infinite;
- its export, loaded, exported again and loaded back, gives the same outputs;
- every per-sample input it declares is served for a sample;
- a few optimizer steps on one batch lower the loss.

Each family's end-to-end test file calls :func:`check_contract` on its own run (the runs
cost minutes, so each is built once, where its other tests read it), and
``tests/repo/test_family_contract.py`` fails on a registered family that no test
holds to it.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from omegaconf import OmegaConf

from occtrain.core.registry import get_world, scorer_factories
from occtrain.core.scorers import Priors
from occtrain.data.clips import frame_clips
from occtrain.data.layout import DatasetIndex
from occtrain.engine.evaluator import Evaluator, scorable
from occtrain.engine.export import export_engine, load_world_model
from occtrain.engine.world_engine import WorldModelEngine
from occtrain.formats.occ3d import FUTURE_STEPS

#: Optimizer steps of the loss check, the items per task the scorers see, and how long a
#: generated text may run (an untrained tiny model's runs to the limit).
STEPS, SAMPLES, MAX_NEW_TEXT_TOKENS = 3, 1, 16


#: The test file that holds each family to the contract on its own tiny run.
HELD_BY = {
    "occllama": "tests/e2e/test_pipeline.py",
    "occllm": "tests/e2e/test_occllm_recipe.py",
    "occvla": "tests/e2e/test_occvla_recipe.py",
    "sparseoccvla": "tests/e2e/test_sparseoccvla_recipe.py",
    "tiny_columns": "tests/e2e/test_plugin_family.py",
}


def check_contract(run_dir: Path, stage: str, tmp: Path) -> None:
    """Every clause of the module docstring, on ``run_dir/stage``'s world-model export, over
    the world the run trained on."""
    data_root = Path(OmegaConf.load(run_dir / "pipeline.yaml").data.root)
    engine = load_world_model(run_dir / stage / "export").eval().with_settings(max_new_text_tokens=MAX_NEW_TEXT_TOKENS)
    engine.prepare_inputs(data_root, tmp / "cache")
    index = DatasetIndex.open(data_root)
    clips = list(frame_clips(index, "train", engine.tasks.context_frames, FUTURE_STEPS, partial_history=False))
    _tasks_build(engine, index, clips)
    _scorers_score(engine, data_root, tmp)
    _export_round_trip(engine, clips, stage, tmp)
    _inputs_served(engine, index)
    _steps_lower_the_loss(engine, clips)


def _tasks_build(engine: WorldModelEngine, index: DatasetIndex, clips: list) -> None:
    lacking = index.available_tasks()
    for task in get_world(engine.family).tasks:
        if lacking.get(task):
            continue
        built = [parts for clip in clips for parts in engine.task_items(task, clip)]
        assert built, f"{engine.family}: task '{task}' built no parts on any of {len(clips)} train clips"


def _trained(engine: WorldModelEngine) -> list[str]:
    weights = {t: w for t, w in engine.tasks.weights.items() if w > 0}
    return scorable(engine.task_specs, weights)


def _scorers_score(engine: WorldModelEngine, data_root: Path, tmp: Path) -> None:
    world = get_world(engine.family)
    tasks = _trained(engine)
    assert tasks, f"{engine.family}: its stage trained no task with a scorer"
    priors = Priors.of(data_root, tmp / "shared")  # the per-voxel prior, a baseline as eval sets it
    evaluator = Evaluator(tasks, engine.task_specs, priors=priors, hooks=world.eval_hooks)
    evaluator.run(engine, data_root, "val", batch_size=SAMPLES, samples=SAMPLES)
    computed = evaluator.compute("val")
    for task in tasks:
        for make in scorer_factories(world.tasks[task]):
            # A scorer's subset metrics (turning clips, ...) may see none of a few items: it
            # scores when some metric it names comes out of the evaluation, none infinite.
            names = list(make().metrics)
            values = [v for k, v in computed.items() for n in names if k.startswith(f"val/{n}")]
            assert values, f"{engine.family}: the '{task}' scorer ({', '.join(names)}) scored nothing"
            assert not any(math.isinf(v) for v in values), f"{engine.family}: a '{task}' score is infinite"


def _a_batch(engine: WorldModelEngine, clips: list) -> dict:
    batch, names = engine.task_batch(clips[:2], {"ann": [c.ann for c in clips[:2]]}, seed=0)
    assert batch is not None, f"{engine.family}: no clip of two has a task its stage trained ({names})"
    return batch


def _export_round_trip(engine: WorldModelEngine, clips: list, stage: str, tmp: Path) -> None:
    again = load_world_model(export_engine(engine, tmp / "again", stage)).eval()
    batch = _a_batch(engine, clips)
    with torch.no_grad():
        before, after = engine.world(batch).logits, again.world(batch).logits
    assert torch.equal(before, after), f"{engine.family}: its export loads back to other outputs"


def _inputs_served(engine: WorldModelEngine, index: DatasetIndex) -> None:
    _, token = next(iter(index.samples("val")))
    for given in get_world(engine.family).sample_inputs:
        row = engine.read(given.name, token)
        assert torch.is_tensor(row) and row.numel() > 0, f"{engine.family}: input '{given.name}' served nothing"


def _steps_lower_the_loss(engine: WorldModelEngine, clips: list) -> None:
    torch.manual_seed(0)
    engine.train()
    params = [p for p in engine.world.parameters() if p.requires_grad]
    assert params, f"{engine.family}: its world model has nothing to train"
    optimizer = torch.optim.AdamW(params, lr=1e-3)
    batch = _a_batch(engine, clips)
    losses = []
    for _ in range(STEPS + 1):
        loss = engine.world(batch).loss
        losses.append(float(loss.detach()))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    engine.eval()
    assert losses[-1] < losses[0], f"{engine.family}: {STEPS} steps on one batch did not lower its loss {losses}"

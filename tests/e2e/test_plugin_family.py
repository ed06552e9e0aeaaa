"""Proof by plugin: a family written in tests/ (``plugins/tiny_family.py``: a continuous
scene encoder, an input of its own, its own task and scorer, its own planner) runs
pretrain -> instruct -> planner -> distill through the CLI, ``occtrain eval`` and the
Python API, with no file of occtrain changed. docs/adding-a-family.md follows these steps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from conftest import run_cli
from family_contract import check_contract

RECIPE = """
name: tiny
plugins: [plugins.tiny_family]
runs_root: {runs}
data:
  root: {data}
  shards: {shards}
  synth: {{train_scenes: 2, val_scenes: 1, frames_per_scene: 12, seed: 3}}
  batch_size: 2
  samples_per_shard: 8
  shuffle_buffer: 4
trainer: {{max_steps: 3, val_check_interval: 3, limit_val_batches: 1, ckpt_every_n_steps: 3}}
stages:
  - name: pretrain
    kind: pretrain
    model:
      family: tiny_columns
      llm: {{hidden_size: 32, num_layers: 1, num_heads: 2, intermediate_size: 64, text_vocab_size: 300}}
      val_samples: 3
  - name: instruct
    kind: instruct
    consumes: [pretrain]
    model: {{use_lora: false, val_samples: 3}}
  - name: planner
    kind: planner
    consumes: [instruct]
    model: {{hidden: 16}}
  - name: distill
    kind: distill
    consumes: [instruct]
    model:
      student: {{hidden_size: 16, num_layers: 1, num_heads: 2, intermediate_size: 32}}
      tasks: {{weights: {{car_columns: 1}}}}
      val_samples: 3
"""


@pytest.fixture(scope="module")
def tiny_run(synth_dataset, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("plugin")
    recipe = root / "tiny.yaml"
    recipe.write_text(RECIPE.format(runs=root / "runs", data=synth_dataset, shards=root / "shards"))
    res = run_cli("run", str(recipe))
    assert res.returncode == 0, res.stderr[-3000:]
    return root / "runs" / "tiny"


@pytest.mark.slow
def test_the_plugin_family_trains_every_stage_kind(tiny_run):
    stages = json.loads((tiny_run / "manifest.json").read_text())["stages"]
    assert [s["status"] for s in stages.values()] == ["done"] * 4
    pretrain, instruct, planner, distill = (
        stages[n]["metrics"] for n in ("pretrain", "instruct", "planner", "distill")
    )
    # Its own scorer and the shared ones it names, on its continuous scenes.
    assert "val/car_columns_acc" in pretrain and "val/baseline_commonest_car_columns_acc" in pretrain
    assert pretrain["val/forecast_occworld_frames_1s"] > 0 and "val/baseline_copy_forecast_occworld_mIoU_1s" in pretrain
    # Every forecast baseline, on the same frames, with its movable-class mIoU.
    for name in ("forecast", "baseline_copy_reconstruction_forecast", "baseline_cv_moved_forecast"):
        assert pretrain[f"val/{name}_occworld_frames_1s"] == pretrain["val/forecast_occworld_frames_1s"]
        assert f"val/{name}_occworld_movable_mIoU_1s" in pretrain
    assert instruct["val/qa_questions"] > 0
    # Its own planner, beside constant velocity.
    assert "val/head_L2_stp3_avg" in planner and "val/constant_velocity_L2_stp3_avg" in planner
    assert distill["student_params"] < distill["teacher_params"] and "val/teacher_car_columns_acc" in distill
    # Its own input, which neither core nor the engine names, encoded once into the
    # stage's cache and read by its Visibility parts: one row of 100 column shares a frame.
    from safetensors.torch import load_file

    (cached,) = (tiny_run / "pretrain" / "cache").glob("*/visible_columns.safetensors")
    rows = load_file(str(cached))
    assert len(rows) == 36 and {tuple(r.shape) for r in rows.values()} == {(100,)}
    shares = torch.stack(list(rows.values()))
    assert 0 < shares.mean() < 1 and shares.min() >= 0 and shares.max() <= 1
    # No scene tokenizer to copy: its encoder has no weights.
    assert not (tiny_run / "pretrain" / "export" / "scene_tokenizer").exists()
    assert json.loads((tiny_run / "pretrain" / "export" / "config.json").read_text())["family"] == "tiny_columns"


@pytest.mark.slow
def test_occtrain_eval_scores_the_plugin_family(tiny_run):
    res = run_cli("eval", str(tiny_run / "instruct"), "--tasks", "car_columns,forecasting", "--samples", "3")
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((tiny_run / "instruct" / "eval" / "val" / "metrics.json").read_text())
    assert {"car_columns_acc", "forecast_occworld_mIoU_1s", "plan_alternate_L2_uniad_1s"} <= metrics.keys()
    # Its planner registers no loader (WorldSpec.load_planner), so eval refuses it in one line.
    res = run_cli("eval", str(tiny_run / "planner"))
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr[-3000:]
    assert "cannot rebuild a 'tiny_columns' planner" in res.stderr and not (tiny_run / "planner" / "eval").exists()


@pytest.mark.slow
def test_the_python_api_loads_the_plugin_familys_model(tiny_run, synth_dataset):
    import occtrain
    import plugins.tiny_family  # noqa: F401 - registers the family, as an installed plugin's entry point would

    model = occtrain.load(tiny_run / "instruct" / "export")
    assert model.family == "tiny_columns" and model.operations == ["describe_scene"]
    clip = model.clip(synth_dataset)
    assert model.describe_scene(clip).endswith("columns hold a car")
    with pytest.raises(AttributeError, match="has no operation 'plan'"):
        model.plan(clip)


def test_an_installed_plugin_registers_through_its_entry_point(monkeypatch):
    from importlib.metadata import EntryPoint

    import occtrain.core.registry as registry

    point = EntryPoint(name="tiny", value="plugins.tiny_family", group=registry.ENTRY_POINT_GROUP)
    registry.families()  # the shipped families, found by walking occtrain.families
    monkeypatch.setattr(registry, "entry_points", lambda group: [point] if group == registry.ENTRY_POINT_GROUP else [])
    monkeypatch.setattr(registry, "_loaded", False)
    monkeypatch.setitem(registry._FAMILIES, "tiny_columns", None)  # restored (removed) afterwards
    del registry._FAMILIES["tiny_columns"]
    import sys

    monkeypatch.delitem(sys.modules, "plugins.tiny_family", raising=False)
    families = registry.families()
    assert "tiny_columns" in families and {"occllama", "occllm", "occvla"} <= set(families)
    assert families["tiny_columns"].world.inputs == ()


def test_registering_a_family_leaves_every_existing_stage_hash_unchanged(tmp_path):
    """A stage's config hash covers only what it uses: another family, or another tokenizer
    architecture, registered later changes no finished run's hash."""
    from dataclasses import dataclass

    from conftest import REPO
    from occtrain.config import load_config
    from occtrain.config.recipe import RecipeConfig
    from occtrain.core.registry import _FAMILIES, _TOKENIZERS, FamilySpec, TokenizerArch, WorldSpec, register_family
    from occtrain.run.planning import plan_stages
    from plugins.tiny_family import TASKS, ColumnTasks, ColumnWorldModel

    def hashes(recipe: str) -> dict[str, str]:
        planned = plan_stages(load_config(RecipeConfig, REPO / "recipes" / recipe), recipe)
        return {p.spec.name: p.config_hash for p in planned}

    recipes = ("quickstart.yaml", "occllm.yaml", "occvla.yaml", "occllama.yaml")
    before = {r: hashes(r) for r in recipes}

    @dataclass
    class OtherWorld:
        width: int = 3

        def validate(self, where, inputs):
            pass

    @dataclass
    class OtherTokenizer:
        size: int = 4

        def validate(self, where):
            pass

    try:
        register_family(
            FamilySpec(
                name="another",
                paper="x",
                tokenizers=(TokenizerArch("another_vae", OtherTokenizer, object),),
                world=WorldSpec(
                    model=ColumnWorldModel, task_config=ColumnTasks, tasks=TASKS, world_config=OtherWorld, inputs=()
                ),
            )
        )
        after = {r: hashes(r) for r in recipes}
    finally:
        _FAMILIES.pop("another", None)
        _TOKENIZERS.pop("another_vae", None)
    assert after == before


# ----------------------------------------------------------------------------- names plugins share

#: The test-only plugins below import; each test's registry fixture forgets them afterwards.
PLUGINS = ("plugins.broken_plugin", "plugins.clashing_family", "plugins.clashing_kind", "plugins.overriding_family")
NOTE = (
    "note: plugin plugins.overriding_family overrides the family 'occllama' of occtrain.families.occllama "
    "(shipped with occtrain)\n"
)


@pytest.fixture
def registry(monkeypatch):
    """The family registry with every shipped family loaded, restored after the test: what
    the test's plugins registered or overrode is undone, and their modules forgotten."""
    import sys

    import occtrain.core.registry as registry

    registry.families()
    for name in ("_FAMILIES", "_TOKENIZERS", "_ORIGINS", "_OVERRIDDEN"):
        monkeypatch.setattr(registry, name, dict(getattr(registry, name)))
    yield registry
    for module in PLUGINS:
        sys.modules.pop(module, None)


def install(monkeypatch, registry, module: str) -> None:
    """``module`` as an installed package's ``occtrain.families`` entry point 'mine', found
    by the next discovery."""
    from importlib.metadata import EntryPoint

    point = EntryPoint(name="mine", value=module, group=registry.ENTRY_POINT_GROUP)
    monkeypatch.setattr(registry, "entry_points", lambda group: [point] if group == registry.ENTRY_POINT_GROUP else [])
    monkeypatch.setattr(registry, "_loaded", False)


@pytest.mark.parametrize(
    "module, says",
    [
        (
            "plugins.broken_plugin",
            "(plugins.broken_plugin) failed while being imported: RuntimeError: the broken plugin's settings are "
            "missing",
        ),
        (
            "plugins.clashing_family",
            "(plugins.clashing_family): family 'occllama' of plugin plugins.clashing_family is already registered by "
            "occtrain.families.occllama (shipped with occtrain); register it with override=True to replace it",
        ),
    ],
    ids=["raises", "family-name-shipped"],
)
def test_an_entry_point_that_fails_is_one_line_naming_it(registry, monkeypatch, module, says):
    import sys

    from occtrain.errors import ConfigError

    shipped = registry.get_family("occllama")
    install(monkeypatch, registry, module)
    with pytest.raises(ConfigError) as err:
        registry.families()
    assert str(err.value) == f"the occtrain.families entry point 'mine' {says}"
    assert err.value.__cause__ is None and err.value.__suppress_context__  # no chained traceback to print
    assert registry.get_family("occllama") is shipped and module not in sys.modules


def test_an_entry_point_that_overrides_a_shipped_family_says_so_in_one_note(registry, monkeypatch, capsys):
    install(monkeypatch, registry, "plugins.overriding_family")
    assert registry.families()["occllama"].paper == "OccLLaMA, as a plugin retrained it"
    assert capsys.readouterr() == ("", NOTE)
    registry.families()  # discovered once per process: one note
    assert capsys.readouterr() == ("", "")


def test_a_recipe_plugin_that_overrides_a_shipped_family_says_so_once_even_imported_twice(registry, capsys):
    import sys

    from occtrain.run.planning import load_plugins

    load_plugins(["plugins.overriding_family"], "r.yaml")
    assert capsys.readouterr() == ("", NOTE)
    # The same module again (imported afresh: a new spec object from the same registrant) is no news.
    del sys.modules["plugins.overriding_family"]
    load_plugins(["plugins.overriding_family"], "r.yaml")
    assert capsys.readouterr() == ("", "")
    assert registry.get_family("occllama") is sys.modules["plugins.overriding_family"].OCCLLAMA


def test_the_very_same_registration_again_is_harmless(registry, capsys):
    from occtrain.stages import get_kind, register

    shipped, kind = registry.get_family("occllama"), get_kind("tokenizer")
    assert registry.register_family(shipped) is shipped and registry.get_family("occllama") is shipped
    assert register(kind) is kind and get_kind("tokenizer") is kind
    assert capsys.readouterr() == ("", "")


def test_a_tokenizer_arch_of_another_family_is_refused_unless_overridden(registry, capsys):
    from occtrain.core.registry import FamilySpec, TokenizerArch, register_family
    from occtrain.errors import ConfigError

    shipped = registry.tokenizer_archs()["occworld_vqvae"]
    mine = FamilySpec(
        name="mine", paper="x", tokenizers=(TokenizerArch("occworld_vqvae", shipped.config, shipped.model),)
    )
    with pytest.raises(
        ConfigError,
        match=(
            f"^tokenizer arch 'occworld_vqvae' of plugin {__name__} is already registered by "
            "occtrain.families.occworld "
            r"\(shipped with occtrain\); register it with override=True to replace it$"
        ),
    ):
        register_family(mine)
    assert "mine" not in registry.families() and registry.tokenizer_family("occworld_vqvae") == "occworld"
    register_family(mine, override=True)
    assert registry.tokenizer_family("occworld_vqvae") == "mine"
    assert capsys.readouterr().err == (
        f"note: plugin {__name__} overrides the tokenizer arch 'occworld_vqvae' of occtrain.families.occworld (shipped "
        "with occtrain)\n"
    )


def test_a_stage_kind_of_another_module_is_refused_unless_overridden(registry, monkeypatch, capsys):
    from dataclasses import replace

    import occtrain.stages as stages
    from occtrain.errors import ConfigError

    shipped = stages.get_kind("tokenizer")
    monkeypatch.setitem(stages._KINDS, "tokenizer", shipped)  # restored after the test
    mine = replace(shipped, monitor="val/mine")
    with pytest.raises(
        ConfigError,
        match=f"^stage kind 'tokenizer' of plugin {__name__} is already registered by occtrain.stages.tokenizer ",
    ):
        stages.register(mine)
    assert stages.get_kind("tokenizer") is shipped
    assert stages.register(mine, override=True) is mine and stages.get_kind("tokenizer") is mine
    assert capsys.readouterr().err == (
        f"note: plugin {__name__} overrides the stage kind 'tokenizer' of occtrain.stages.tokenizer (shipped with "
        "occtrain)\n"
    )


def test_the_family_keeps_the_contract(tiny_run, tmp_path):
    """Its tasks build, its scorers score, its export round-trips, its inputs are served and
    a few steps lower its loss, checked as every family's are (tests/family_contract.py)."""
    import plugins.tiny_family  # noqa: F401 - registers the family in this process

    check_contract(tiny_run, "pretrain", tmp_path)

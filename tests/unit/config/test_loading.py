from pathlib import Path

import pytest

from occtrain.config import DataConfig, DatasetFile, TrainerConfig, load_config
from occtrain.errors import ConfigError


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_yaml_and_overrides_merge_onto_defaults(tmp_path):
    f = write(tmp_path, "trainer/cpu.yaml", "max_steps: 7\ndevices: 2\n")
    cfg = load_config(TrainerConfig, f, ["max_steps=11", "strategy=ddp"])
    assert (cfg.max_steps, cfg.devices, cfg.strategy, cfg.accelerator) == (11, 2, "ddp", "cpu")


def test_unknown_key_in_file_names_file_and_suggests(tmp_path):
    f = write(tmp_path, "trainer/cpu.yaml", "max_step: 7\n")
    with pytest.raises(ConfigError) as err:
        load_config(TrainerConfig, f)
    assert str(err.value) == f"unknown key 'max_step' in {f}; did you mean 'max_steps'?"


def test_unknown_nested_override_key_suggests(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_config(DatasetFile, None, ["data.synth.train_scene=3"])
    assert "unknown key 'data.synth.train_scene'" in str(err.value)
    assert "did you mean 'train_scenes'?" in str(err.value)


def test_wrong_type_names_key_and_source(tmp_path):
    f = write(tmp_path, "data/x.yaml", "batch_size: lots\n")
    with pytest.raises(ConfigError) as err:
        load_config(DataConfig, f)
    msg = str(err.value)
    assert "batch_size" in msg and str(f) in msg and "\n" not in msg
    with pytest.raises(ConfigError) as err:
        load_config(TrainerConfig, None, ["max_steps=abc"])
    assert "max_steps" in str(err.value) and "override 'max_steps=abc'" in str(err.value)


def test_section_may_name_another_yaml_file(tmp_path):
    data = write(tmp_path, "configs/data/tiny.yaml", "root: somewhere\nsynth:\n  train_scenes: 1\n")
    top = write(tmp_path, "recipe.yaml", f"data: {data}\n")
    cfg = load_config(DatasetFile, top, ["data.batch_size=5"])
    assert (cfg.data.root, cfg.data.synth.train_scenes, cfg.data.batch_size) == ("somewhere", 1, 5)


def test_bad_yaml_and_missing_file_are_one_line(tmp_path):
    f = write(tmp_path, "trainer/bad.yaml", "max_steps: [1,\n")
    with pytest.raises(ConfigError, match=r"not valid YAML"):
        load_config(TrainerConfig, f)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(TrainerConfig, tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="must look like key=value"):
        load_config(TrainerConfig, None, ["max_steps"])


def test_result_is_read_only():
    from omegaconf.errors import ReadonlyConfigError

    cfg = load_config(TrainerConfig)
    before = cfg.max_steps
    with pytest.raises(ReadonlyConfigError):
        cfg.max_steps = before + 3
    assert cfg.max_steps == before


def test_override_may_name_a_section_file(tmp_path):
    from occtrain.config.recipe import RecipeConfig

    gpu = write(tmp_path, "configs/trainer/gpu.yaml", "accelerator: gpu\ndevices: 4\n")
    cfg = load_config(RecipeConfig, None, ["name=x", f"trainer={gpu}", "trainer.devices=2"])
    assert (cfg.trainer.accelerator, cfg.trainer.devices, cfg.trainer.max_steps) == ("gpu", 2, 100)
    bad = write(tmp_path, "configs/trainer/bad.yaml", "acelerator: gpu\n")
    with pytest.raises(
        ConfigError, match=r"unknown key 'trainer.acelerator' in .*bad.yaml; did you mean 'accelerator'\?"
    ):
        load_config(RecipeConfig, None, ["name=x", f"trainer={bad}"])


def test_a_recipe_extends_another_with_its_stages_after_that_ones(tmp_path):
    from occtrain.config.recipe import RecipeConfig
    from occtrain.run.planning import load_recipe

    sub = tmp_path / "base"
    sub.mkdir()
    (sub / "data.yaml").write_text("root: somewhere\nbatch_size: 3\n")
    (sub / "base.yaml").write_text(
        "name: base\ndata: data.yaml\ntrainer: {max_steps: 7}\nstages:\n"
        "  - {name: a, kind: tokenizer, model: {arch: occworld_vqvae}}\n"
    )
    (tmp_path / "more.yaml").write_text(
        "extends: base/base.yaml\nname: more\ntrainer: {max_steps: 9}\nstages:\n"
        "  - {name: b, kind: tokenizer, model: {arch: occworld_vqvae}}\n"
    )
    cfg = load_config(RecipeConfig, tmp_path / "more.yaml")
    assert [s.name for s in cfg.stages] == ["a", "b"] and cfg.name == "more"
    # The base's includes resolve against the base's own folder; this recipe's keys win.
    assert cfg.data.root == "somewhere" and cfg.data.batch_size == 3 and cfg.trainer.max_steps == 9
    # Stages of the extended recipe are addressed by name in overrides like the recipe's own.
    recipe, _ = load_recipe(tmp_path / "more.yaml", ["stages.a.trainer.max_steps=2"])
    assert recipe.stages[0].trainer["max_steps"] == 2


def test_a_recipe_that_extends_itself_round_about_is_one_line(tmp_path):
    from occtrain.config.recipe import RecipeConfig

    (tmp_path / "x.yaml").write_text("extends: y.yaml\nname: x\n")
    (tmp_path / "y.yaml").write_text("extends: x.yaml\nname: y\n")
    with pytest.raises(ConfigError, match="extends x.yaml, which extends it back"):
        load_config(RecipeConfig, tmp_path / "x.yaml")

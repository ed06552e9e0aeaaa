"""Runner mechanics with a tiny test-only stage kind: skip, config change, restart, failure, handoff."""

from __future__ import annotations

import json

import pytest
import torch

from conftest import write_hand_dataset
from occtrain.errors import ConfigError, OcctrainError
from occtrain.formats.exports import read_export, write_export
from occtrain.run.runner import StageFailed, run
from plugins.probe_stage import PROBE


@pytest.fixture
def probe_kind():
    return PROBE


@pytest.fixture
def recipe(tmp_path):
    data = write_hand_dataset(tmp_path / "ds", train=1, val=1, frames=6)
    text = f"""
name: probe
plugins: [plugins.probe_stage]
runs_root: {tmp_path / "runs"}
data:
  root: {data}
  batch_size: 2
  samples_per_shard: 4
  history: 1
  future: 1
trainer:
  max_steps: 6
  val_check_interval: 3
  limit_val_batches: 2
  ckpt_every_n_steps: 2
  log_every_n_steps: 1
stages:
  - name: first
    kind: probe
    model: {{width: 4}}
    optim: {{lr: 0.05}}
  - name: second
    kind: probe
    consumes: [first]
    model: {{width: 4}}
    trainer: {{max_steps: 4}}
"""
    path = tmp_path / "probe.yaml"
    path.write_text(text)
    return path


def test_runs_skips_and_hands_off(probe_kind, recipe, tmp_path, capsys):
    run_dir = run(recipe)
    assert run_dir == tmp_path / "runs" / "probe"
    manifest = json.loads((run_dir / "manifest.json").read_text())
    for name in ("first", "second"):
        entry = manifest["stages"][name]
        assert entry["status"] == "done" and entry["attempts"] == 1
        assert (run_dir / name / "export" / "model.safetensors").is_file()
        assert (run_dir / name / "checkpoints" / "last.ckpt").is_file()
        assert (run_dir / name / "logs" / "csv" / "metrics.csv").is_file()
        assert json.loads((run_dir / name / "metrics.json").read_text())["val/acc"] == entry["metrics"]["val/acc"]
    assert 0.0 <= manifest["stages"]["first"]["metrics"]["val/acc"] <= 1.0
    assert read_export(run_dir / "second" / "export")[1]["init_from"] == "first"  # handoff through export/
    assert (run_dir / "pipeline.yaml").read_text().startswith("name: probe")
    stamp = (run_dir / "first" / "export" / "model.safetensors").stat().st_mtime_ns
    capsys.readouterr()
    run(recipe)
    out = capsys.readouterr().err
    assert "first" in out and "skipped" in out
    assert (run_dir / "first" / "export" / "model.safetensors").stat().st_mtime_ns == stamp
    assert json.loads((run_dir / "manifest.json").read_text())["stages"]["second"]["attempts"] == 1


def test_changed_config_is_refused_then_restart_retrains(probe_kind, recipe):
    run_dir = run(recipe)
    with pytest.raises(ConfigError) as err:
        run(recipe, ["stages[0].optim.lr=0.01"])
    assert (
        str(err.value) == "stage 'first' is done but its config changed (optim.lr); "
        "`--restart first` retrains it and the stages after it"
    )
    before = json.loads((run_dir / "manifest.json").read_text())["stages"]
    second_export = (run_dir / "second" / "export" / "model.safetensors").read_bytes()
    run(recipe, ["stages[0].optim.lr=0.01"], restart="first")
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["stages"]["first"]["config"]["optim"]["lr"] == 0.01
    # 'second' was reset (one attempt, not two) and retrained after 'first', on the new export.
    second = manifest["stages"]["second"]
    assert second["attempts"] == 1 and second["started"] > before["second"]["ended"]
    assert (
        second["config"]["consumes"]["first"]
        == manifest["stages"]["first"]["config_hash"]
        != before["first"]["config_hash"]
    )
    assert (run_dir / "second" / "export" / "model.safetensors").read_bytes() != second_export


def test_failure_is_recorded_in_one_line(probe_kind, recipe):
    with pytest.raises(StageFailed) as err:
        run(recipe, ["stages[1].model.fail=true"])
    assert str(err.value).startswith("stage 'second' failed: RuntimeError: probe exploded (traceback in ")
    manifest = json.loads((recipe.parent / "runs/probe/manifest.json").read_text())
    assert manifest["stages"]["first"]["status"] == "done"
    assert manifest["stages"]["second"]["status"] == "failed"
    assert manifest["stages"]["second"]["error"] == "RuntimeError: probe exploded"


@pytest.mark.parametrize(
    "override, message",
    [
        ("stages[1].kind=prbe", "unknown stage kind 'prbe'"),
        ("stages[0].consumes=[second]", "consumes 'second', which is not an earlier stage (it runs later)"),
        ("stages[0].model.widht=3", "unknown key 'stages[0].model.widht' in"),
        ("stages[0].trainer.max_step=3", "did you mean 'max_steps'?"),
    ],
)
def test_bad_recipes_are_one_line(probe_kind, recipe, override, message):
    with pytest.raises(ConfigError) as err:
        run(recipe, [override])
    assert message in str(err.value) and "\n" not in str(err.value)


def test_only_needs_its_inputs(probe_kind, recipe):
    with pytest.raises(ConfigError, match="consumes the export of 'first', which is not done"):
        run(recipe, only="second")
    run(recipe, only="first")
    manifest = json.loads((recipe.parent / "runs/probe/manifest.json").read_text())
    assert manifest["stages"]["first"]["status"] == "done" and manifest["stages"]["second"]["status"] == "pending"


def test_export_is_safetensors_and_json(tmp_path):
    state = {"w": torch.arange(6.0).reshape(2, 3)}
    write_export(tmp_path / "export", state, {"k": 1})
    write_export(tmp_path / "export", {"w": torch.zeros(1)}, {"k": 2})  # replaced whole
    got, cfg = read_export(tmp_path / "export")
    assert cfg == {"k": 2} and torch.equal(got["w"], torch.zeros(1))
    assert sorted(p.name for p in (tmp_path / "export").iterdir()) == ["config.json", "model.safetensors"]
    assert [p.name for p in tmp_path.iterdir()] == ["export"]  # no temp leftovers


# ----------------------------------------------------------------------------- the Stage interface


def test_a_kind_that_is_not_a_stage_is_refused_before_training(recipe, tmp_path):
    """A registered kind whose module is a plain LightningModule, or a Stage without
    ``export``, is refused when the recipe is planned: nothing is trained or written."""
    import lightning as L

    from occtrain.stages import Stage, StageKind, register
    from plugins.probe_stage import ProbeConfig

    class NotAStage(L.LightningModule):
        pass

    class NoExport(Stage):
        pass

    for name, module in (("plain_module", NotAStage), ("no_export", NoExport)):
        register(StageKind(name=name, model_schema=ProbeConfig, data_kind="frames", module=module))
        text = recipe.read_text().replace(
            "kind: probe\n    model: {width: 4}\n    optim", f"kind: {name}\n    model: {{width: 4}}\n    optim", 1
        )
        (tmp_path / f"{name}.yaml").write_text(text)
        with pytest.raises(ConfigError, match=f"stage kind '{name}' .* not a concrete occtrain.stages.Stage"):
            run(tmp_path / f"{name}.yaml")
        assert not (tmp_path / "runs" / "probe" / "first").exists()


def plan_text(tmp_path, stages: str):
    from occtrain.config import load_config
    from occtrain.config.recipe import RecipeConfig
    from occtrain.run.planning import plan_stages

    (tmp_path / "r.yaml").write_text(f"name: r\nstages:\n{stages}")
    return plan_stages(load_config(RecipeConfig, tmp_path / "r.yaml"), "r.yaml")


def test_consumes_are_checked_when_planning(probe_kind, tmp_path):
    stages = "  - {name: a, kind: probe}\n  - {name: b, kind: probe}\n  - {name: c, kind: probe, consumes: [a, b]}\n"
    with pytest.raises(
        ConfigError, match=r"stages\[2\] \('c'\).*: a probe stage consumes 0 to 1 earlier stage\(s\) \(probe\), got 2"
    ):
        plan_text(tmp_path, stages)


def test_a_world_model_stage_reads_only_its_kind_of_export(tmp_path):
    with pytest.raises(
        ConfigError,
        match="an? instruct stage cannot consume 'tok', a tokenizer stage; it reads pretrain or instruct or distill",
    ):
        plan_text(
            tmp_path,
            "  - {name: tok, kind: tokenizer, model: {arch: occworld_vqvae}}\n  - {name: tune, kind: instruct, "
            "consumes: [tok]}\n",
        )
    with pytest.raises(ConfigError, match=r"model.family is empty and no tokenizer stage is consumed"):
        plan_text(tmp_path, "  - {name: lm, kind: pretrain}\n")
    # A family's world model is built over what the family names: OccVLA's reads a vision stage too.
    with pytest.raises(
        ConfigError,
        match=r"a 'occvla' world model is built over tokenizer and vision \(consumes those stages\), got tokenizer",
    ):
        plan_text(
            tmp_path,
            "  - {name: tok, kind: tokenizer, model: {arch: occworld_vqvae}}\n  - {name: lm, kind: pretrain, consumes: "
            "[tok], model: {family: occvla}}\n",
        )


def test_checkpoints_load_strictly_by_key(recipe, tmp_path):
    """A checkpoint whose weights do not match the stage is an error naming the key."""
    from occtrain.config.groups import DataConfig, TrainerConfig
    from occtrain.config.recipe import StageSpec
    from occtrain.stages import StageContext
    from plugins.probe_stage import Probe, ProbeConfig

    ctx = StageContext(
        StageSpec(name="first", kind="probe"), ProbeConfig(), DataConfig(), TrainerConfig(), tmp_path, {}
    )
    stage = Probe(ctx)
    state = stage.state_dict()
    Probe(ctx).load_state_dict(state)  # the stage's own checkpoint loads
    with pytest.raises(OcctrainError, match="missing tensor 'head.bias'.*--restart first"):
        Probe(ctx).load_state_dict({k: v for k, v in state.items() if k != "head.bias"})
    with pytest.raises(OcctrainError, match="unexpected tensor 'extra.weight'"):
        Probe(ctx).load_state_dict({**state, "extra.weight": torch.zeros(1)})
    # A fresh stage of the same config (another rank, a resumed run) seeds a step alike; another data seed does not.
    assert stage.step_seed(5) == Probe(ctx).step_seed(5) != stage.step_seed(6)
    other = StageContext(
        StageSpec(name="first", kind="probe"), ProbeConfig(), DataConfig(seed=1), TrainerConfig(), tmp_path, {}
    )
    assert Probe(other).step_seed(5) != stage.step_seed(5)


def test_a_stage_sets_its_own_batch_size_but_not_the_dataset(probe_kind, tmp_path):
    a, b = plan_text(tmp_path, "  - {name: a, kind: probe}\n  - {name: b, kind: probe, data: {batch_size: 8}}\n")
    assert (a.data.batch_size, b.data.batch_size) == (2, 8)
    assert a.config["data"]["batch_size"] == 2 and b.config["data"]["batch_size"] == 8  # part of its config hash
    with pytest.raises(ConfigError, match=r"stages\[0\].data.root in r.yaml: a stage sets only batch_size"):
        plan_text(tmp_path, "  - {name: a, kind: probe, data: {root: elsewhere}}\n")


# ----------------------------------------------------------------------------- write faults and files


def _hashes(root) -> dict[str, bytes]:
    import hashlib

    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).digest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_disk_full_at_a_checkpoint_is_one_line_and_leaves_the_run_consistent(probe_kind, recipe, monkeypatch):
    import errno
    import os

    import occtrain.formats.io

    real_replace = os.replace

    def full(src, dst):
        if str(dst).endswith(".ckpt"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(occtrain.formats.io.os, "replace", full)
    with pytest.raises(StageFailed) as err:
        run(recipe)
    run_dir = recipe.parent / "runs" / "probe"
    ckpt_dir = run_dir / "first" / "checkpoints"
    assert str(err.value) == (
        f"stage 'first' failed: cannot write {ckpt_dir / 'last.ckpt'}: the disk is full; free space and rerun "
        "(a run resumes where it stopped)"
    )
    assert list(ckpt_dir.iterdir()) == [] if ckpt_dir.exists() else True  # no partial checkpoint, no temp file
    stage = json.loads((run_dir / "manifest.json").read_text())["stages"]["first"]
    assert stage["status"] == "failed" and stage["error"].startswith("cannot write")

    monkeypatch.setattr(occtrain.formats.io.os, "replace", real_replace)  # space freed: the rerun finishes
    run(recipe)
    assert json.loads((run_dir / "manifest.json").read_text())["stages"]["first"]["status"] == "done"


def test_a_read_only_run_directory_is_one_line_and_writes_nothing(probe_kind, recipe, monkeypatch):
    import errno

    import occtrain.formats.io

    run(recipe)
    run_dir = recipe.parent / "runs" / "probe"
    before = _hashes(run_dir)

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(occtrain.formats.io.tempfile, "mkstemp", read_only)
    with pytest.raises(OcctrainError) as err:
        run(recipe, ["stages[1].optim.lr=0.5"], restart="second")
    assert str(err.value) == (  # a restart writes its pipeline.yaml once the old one is set aside
        f"cannot write {run_dir / 'manifest.json'}: the file system is read-only; "
        "point the run (--run-dir) or --out at a writable place"
    )
    assert _hashes(run_dir) == before


def test_written_files_have_the_permissions_of_a_plain_write(probe_kind, recipe):
    import os

    umask = os.umask(0)
    os.umask(umask)
    run_dir = run(recipe)
    for path in (
        run_dir / "manifest.json",
        run_dir / "dashboard.html",
        run_dir / "pipeline.yaml",
        run_dir / "first" / "metrics.json",
        run_dir / "first" / "checkpoints" / "last.ckpt",
    ):
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask, path


def test_an_unreadable_last_checkpoint_falls_back_to_the_one_before(tmp_path, capsys):
    from occtrain.stages.checkpoints import PREVIOUS_CKPT, last_checkpoint

    ckpt = tmp_path / "checkpoints"
    ckpt.mkdir()
    torch.save({"global_step": 2}, ckpt / PREVIOUS_CKPT)
    (ckpt / "last.ckpt").write_bytes(b"PK\x03\x04 truncated")
    said: list[str] = []
    assert last_checkpoint(tmp_path, said.append) == ckpt / PREVIOUS_CKPT
    assert len(said) == 1 and said[0].startswith(f"{ckpt / 'last.ckpt'} is unreadable (")
    (ckpt / PREVIOUS_CKPT).write_bytes(b"")
    assert last_checkpoint(tmp_path, said.append) is None and "starts afresh" in said[-1]


# ----------------------------------------------------------------------------- overrides and notes


def test_stages_are_addressed_by_name_or_index(probe_kind, recipe):
    from occtrain.run.planning import load_recipe

    for key in ("stages.second.optim.lr=0.125", "stages.1.optim.lr=0.125", "stages[1].optim.lr=0.125"):
        cfg, _ = load_recipe(recipe, [key])
        assert cfg.stages[1].optim.lr == 0.125 and cfg.stages[0].optim.lr == 0.05


def test_a_shadowed_trainer_override_is_said_once(probe_kind, recipe, capsys):
    run_dir = run(recipe, ["trainer.max_steps=2"])
    err = capsys.readouterr().err
    assert (
        err.count("note") == 1
        and "trainer.max_steps=2 applies to every stage except second, which set their own" in err
    )
    manifest = json.loads((run_dir / "manifest.json").read_text())["stages"]
    assert (
        manifest["first"]["config"]["trainer"]["max_steps"] == 2
        and manifest["second"]["config"]["trainer"]["max_steps"] == 4
    )


def test_a_refused_run_writes_nothing(probe_kind, recipe):
    run_dir = run(recipe)
    before = _hashes(run_dir)
    with pytest.raises(ConfigError):
        run(recipe, ["stages.first.optim.lr=0.5", "trainer.log_every_n_steps=3"])
    assert _hashes(run_dir) == before


def _tree(root):
    """sha256 of every file under ``root`` by relative path (what a restart must keep)."""
    import hashlib

    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _stages(run_dir):
    return json.loads((run_dir / "manifest.json").read_text())["stages"]


def test_a_restart_that_fails_before_its_first_checkpoint_puts_the_old_stages_back(probe_kind, recipe):
    run_dir = run(recipe)
    trees = {name: _tree(run_dir / name) for name in ("first", "second")}
    entries = _stages(run_dir)
    with pytest.raises(StageFailed) as err:
        run(recipe, ["stages[0].model.fail=true"], restart="first")
    assert "the stages --restart replaced (first, second) are back as they were" in str(err.value)
    assert f"traceback is in {run_dir / 'restart-traceback.txt'}" in str(err.value)
    assert "probe exploded" in (run_dir / "restart-traceback.txt").read_text()
    assert {name: _tree(run_dir / name) for name in ("first", "second")} == trees
    assert _stages(run_dir) == entries and not (run_dir / ".replaced").exists()
    run(recipe)  # and the run goes on from them: both done, nothing retrains
    assert _stages(run_dir) == entries


def test_a_restart_past_its_first_checkpoint_replaces_the_old_stages(probe_kind, recipe):
    run_dir = run(recipe)
    old = (run_dir / "second" / "export" / "model.safetensors").read_bytes()
    with pytest.raises(StageFailed):
        run(recipe, ["stages[0].optim.lr=0.01", "stages[1].model.fail=true"], restart="first")
    stages = _stages(run_dir)
    assert stages["first"]["status"] == "done" and stages["first"]["config"]["optim"]["lr"] == 0.01
    assert stages["second"]["status"] == "failed" and not (run_dir / "second" / "export").exists()
    assert not (run_dir / ".replaced").exists()
    run(recipe, ["stages[0].optim.lr=0.01"])
    assert (run_dir / "second" / "export" / "model.safetensors").read_bytes() != old


def test_a_restart_killed_before_it_settled_is_put_back_by_the_next_run(probe_kind, recipe, capsys):
    from occtrain.formats.manifest import Manifest

    run_dir = run(recipe)
    tree, entries = _tree(run_dir / "second"), _stages(run_dir)
    Manifest.load(run_dir).set_aside(["second"])  # as `--restart second` does, then kill -9
    (run_dir / "second" / "logs").mkdir(parents=True)  # what the killed attempt had begun
    capsys.readouterr()
    run(recipe)
    out = capsys.readouterr().err
    assert "the stages --restart replaced (second) are back as they were" in out
    assert _tree(run_dir / "second") == tree and _stages(run_dir) == entries


def test_a_failed_restart_leaves_pipeline_yaml_as_it_was_and_one_that_takes_rewrites_it(probe_kind, recipe):
    run_dir = run(recipe)
    before = (run_dir / "pipeline.yaml").read_text()
    with pytest.raises(StageFailed, match="are back as they were"):
        run(recipe, ["stages[0].model.fail=true"], restart="first")
    assert (run_dir / "pipeline.yaml").read_text() == before  # the recipe of the stages that were put back
    run(recipe, ["stages[0].optim.lr=0.01"], restart="first")
    assert "lr: 0.01" in (run_dir / "pipeline.yaml").read_text()


def test_a_restart_killed_before_it_settled_gets_its_pipeline_yaml_back_too(probe_kind, recipe):
    from occtrain.formats.manifest import Manifest

    run_dir = run(recipe)
    before = (run_dir / "pipeline.yaml").read_text()
    Manifest.load(run_dir).set_aside(["second"])  # as `--restart second` does, then:
    (run_dir / "pipeline.yaml").write_text("name: probe\n# the killed attempt's recipe\n")
    Manifest.load(run_dir).settle_aside()  # what the next run does first
    assert (run_dir / "pipeline.yaml").read_text() == before


@pytest.mark.parametrize("at_step, says", [(0, "before its first checkpoint"), (3, "at step 2")])
def test_a_stop_signal_says_where_a_rerun_starts(probe_kind, recipe, monkeypatch, at_step, says):
    """SIGTERM in the stage's training: the line promises a resume from a checkpoint only
    when one exists (every 2 steps here), and names its step."""
    import os
    import signal

    from occtrain.run.control import Interrupted
    from plugins.probe_stage import Probe

    real = Probe.training_step

    def step(self, batch, i):
        if self.global_step == at_step:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(self, batch, i)

    monkeypatch.setattr(Probe, "training_step", step)
    run_dir = recipe.parent / "runs" / "probe"
    with pytest.raises(Interrupted) as stop:
        run(recipe, ["trainer.max_steps=6"], only="first")
    ckpt = run_dir / "first" / "checkpoints" / "last.ckpt"
    if at_step == 0:
        assert not ckpt.exists()
        assert str(stop.value) == (
            f"stage 'first' of {run_dir} interrupted by SIGTERM before its first checkpoint; rerun the same command "
            "to start it over"
        )
    else:
        assert str(stop.value) == (
            f"stage 'first' of {run_dir} interrupted by SIGTERM; rerun the same command to resume it from its "
            f"checkpoint at step 2 ({ckpt})"
        )
    assert says in str(stop.value)


def test_a_base_recipe_run_again_keeps_the_stages_a_recipe_extending_it_trained(probe_kind, recipe, tmp_path, capsys):
    """recipes/closed_loop.yaml extends the quickstart in its run directory: the quickstart run
    again over it kept only its own stages in pipeline.yaml, and eval of the extending recipe's
    stage then found no spec for it."""
    from occtrain.config import load_config
    from occtrain.config.recipe import RecipeConfig
    from occtrain.run.done_stage import done_stage

    extended = tmp_path / "extended.yaml"
    extended.write_text(
        f"extends: {recipe.name}\nstages:\n  - {{name: third, kind: probe, consumes: [second], model: {{width: 4}}}}\n"
    )
    run_dir = run(extended)
    run(recipe)
    assert "pipeline.yaml keeps stage 'third', which an earlier recipe trained here" in capsys.readouterr().err
    kept = load_config(RecipeConfig, run_dir / "pipeline.yaml")
    assert [s.name for s in kept.stages] == ["first", "second", "third"]
    assert done_stage(run_dir / "third", "occtrain eval", "scores", lambda module: True).spec.consumes == ["second"]
    run(extended)  # and the extending recipe still finds its stages as it left them
    assert json.loads((run_dir / "manifest.json").read_text())["stages"]["third"]["attempts"] == 1


def test_a_restart_killed_before_its_first_checkpoint_is_said_so_by_validate_and_eval(probe_kind, recipe, capsys):
    """kill -9 during `--restart second`: the done stage lies aside until the next run puts it
    back. validate said [running], eval advised finishing the killed attempt's pipeline."""
    from occtrain.cli import main
    from occtrain.formats.manifest import Manifest
    from occtrain.run.done_stage import done_stage

    run_dir = run(recipe)
    manifest = Manifest.load(run_dir)
    manifest.set_aside(["second"])  # what `--restart second` does before it trains ...
    manifest.mark_running("second", "0123456789abcdef", {})  # ... and it was killed in its first step
    (run_dir / "pipeline.yaml").write_text(recipe.read_text())
    capsys.readouterr()
    assert main(["validate", str(recipe)]) == 0
    assert "[done: a killed --restart set it aside; the next run puts it back]" in capsys.readouterr().out
    with pytest.raises(ConfigError) as err:
        done_stage(run_dir / "second", "occtrain eval", "scores", lambda module: True)
    assert str(err.value) == (
        f"{run_dir / 'second'}: a --restart of the run was killed before its first checkpoint and set stage 'second' "
        f"aside in {run_dir / '.replaced'}; the next `occtrain run` over {run_dir} puts it back as it was (any "
        "recipe: the run settles it first), or rerun the --restart to retrain it"
    )
    run(recipe)
    entry = json.loads((run_dir / "manifest.json").read_text())["stages"]["second"]
    assert entry["status"] == "done" and entry["attempts"] == 1
    assert done_stage(run_dir / "second", "occtrain eval", "scores", lambda module: True).spec.name == "second"

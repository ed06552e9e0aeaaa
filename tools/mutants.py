"""Mutation check of the suite: does each test fail when the thing it names is broken?

Each mutant is one small change to the code under test, the kind of bug a test exists to
catch (resuming from scratch, running one process where two were asked for, ...). For each,
this script copies the working tree to a temporary directory, applies the change there, and
runs the tests meant to catch it against the copy; a mutant is *killed* when they fail.
Before that it runs the same tests on the unchanged copy, which must pass: a test that
fails anyway kills nothing.

    python tools/mutants.py                 # every mutant: a table of which test kills which
    python tools/mutants.py --list          # the mutants and their tests, nothing run
    python tools/mutants.py --only scaled-ddp-loss --only one-process

It takes about half an hour on 2 cores (several tests train through the CLI), so it is not
part of ``pytest``; ``tests/tools/test_mutants.py`` checks that every change still applies to the
current code. Exit status 1 when a mutant survives or a baseline fails.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutant:
    """``old`` -> ``new`` in ``file`` (``old`` occurs there exactly once); ``tests`` must fail."""

    name: str
    what: str
    file: str
    old: str
    new: str
    tests: tuple[str, ...]


MUTANTS = (
    Mutant(
        "resume-from-scratch",
        "a cut-off stage retrains from step 0 (and still says it resumes)",
        "src/occtrain/run/execution.py",
        "trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)",
        "trainer.fit(module, datamodule=datamodule, ckpt_path=None, weights_only=True)",
        (
            "tests/e2e/test_interruptions.py::test_kill_9_then_resume_gives_the_uninterrupted_weights",
            "tests/e2e/test_interruptions.py::test_a_stop_signal_interrupts_in_one_line_and_a_rerun_resumes",
            "tests/e2e/test_occllm_recipe.py::test_the_msvae_tokenizer_resumes_bit_exact_after_kill_9",
            "tests/e2e/test_pipeline_faults.py::test_kill_9_at_a_random_step_of_every_stage_resumes_bit_exact",
        ),
    ),
    Mutant(
        "one-process",
        "trainer.devices=2 runs one process",
        "src/occtrain/stages/trainer.py",
        "        devices=cfg.devices,\n",
        "        devices=1,\n",
        (
            "tests/e2e/test_interruptions.py::test_cpu_ddp_two_processes",
            "tests/e2e/test_distributed.py::test_ddp_validation_of_an_odd_split_equals_one_process",
        ),
    ),
    Mutant(
        "every-rank-validates-everything",
        "each DDP rank validates the whole split",
        "src/occtrain/data/shards/positions.py",
        "    mine: list[int | None] = list(range(rank, total, world))\n",
        "    mine: list[int | None] = list(range(total))\n",
        ("tests/e2e/test_distributed.py::test_ddp_validation_of_an_odd_split_equals_one_process",),
    ),
    Mutant(
        "scaled-ddp-loss",
        "the tokenizer's loss is 1.5x under DDP",
        "src/occtrain/models/tokenizers/occworld_vqvae.py",
        'losses = {"loss": total, ',
        'losses = {"loss": total * (1.5 if torch.distributed.is_initialized() else 1.0), ',
        ("tests/unit/stages/test_optim_ddp_step.py::test_ddp_step_equals_single_process_step",),
    ),
    Mutant(
        "bear-by-heading-flipped",
        "the meta-action rule's bear-by-heading branch picks the wrong side",
        "src/occtrain/data/meta_actions.py",
        'return "bear left" if heading_change_deg > 0 else "bear right"',
        'return "bear right" if heading_change_deg > 0 else "bear left"',
        ("tests/unit/data/synth/test_synth.py::test_meta_action_follows_the_documented_rule",),
    ),
    Mutant(
        "wrong-1s-frame",
        "the 1 s forecast horizon reads the 0.5 s frame",
        "src/occtrain/metrics/conventions.py",
        "FORECAST_HORIZONS = (1, 3, 5)",
        "FORECAST_HORIZONS = (0, 3, 5)",
        ("tests/unit/commands/test_score.py::test_forecast_hand_case",),
    ),
    Mutant(
        "empty-generation",
        "greedy text generation stops at once",
        "src/occtrain/core/decoding.py",
        "    for _ in range(answer.max_new_tokens):\n        tok = yield from s.pick(s.vocab.text_range)",
        "    for _ in range(0):\n        tok = yield from s.pick(s.vocab.text_range)",
        (
            "tests/e2e/test_occvla_recipe.py::test_the_reloaded_model_generates_the_same_text_with_and_without_occupancy",
        ),
    ),
    Mutant(
        "check-stops-at-first-problem",
        "data check reports only a file's first problem",
        "src/occtrain/commands/data_check.py",
        "    found = schema_problems(data, schema, limit=MAX_PER_FILE + 1)",
        "    found = schema_problems(data, schema, limit=1)",
        (
            "tests/e2e/test_bad_inputs.py::test_bad_input_is_one_line_and_changes_nothing[check-ann-lists-every-problem]",
            "tests/e2e/test_bad_inputs.py::test_bad_input_is_one_line_and_changes_nothing[check-qa-lists-every-problem]",
        ),
    ),
    Mutant(
        "restart-resets-one-stage",
        "--restart retrains the named stage but keeps the later ones",
        "src/occtrain/run/runner.py",
        "_prepare(recipe, manifest, [p.spec.name for p in planned if p.spec.name in restarted], held)",
        "_prepare(recipe, manifest, [str(restart)], held)",
        ("tests/unit/run/test_runner.py::test_changed_config_is_refused_then_restart_retrains",),
    ),
    Mutant(
        "kl-without-t-squared",
        "the distillation KL is not scaled by T^2",
        "src/occtrain/models/distill_losses.py",
        'reduction="batchmean") * t * t',
        'reduction="batchmean")',
        ("tests/unit/stages/test_planner_and_distill_parts.py::test_distillation_losses_by_hand",),
    ),
    Mutant(
        "no-shuffle",
        "the training stream is not shuffled",
        "src/occtrain/data/shards/positions.py",
        "    if shuffle_buffer <= 1:\n",
        "    if True:\n",
        ("tests/unit/data/shards/test_shards.py::test_train_pipeline_streams_forever_and_shuffles",),
    ),
    Mutant(
        "epochs-unshuffled",
        "the default epoch order is the samples as stored",
        "src/occtrain/data/shards/positions.py",
        '        random.Random(f"samples:{seed}:{epoch}").shuffle(order)\n',
        "        pass\n",
        (
            "tests/unit/data/shards/test_shards.py::test_the_default_order_is_a_fresh_permutation_of_every_sample_each_epoch",
        ),
    ),
    Mutant(
        "workers-read-everything",
        "each validation loader worker reads every sample",
        "src/occtrain/data/shards/positions.py",
        "    return mine[worker::workers]\n",
        "    return mine\n",
        ("tests/unit/data/shards/test_shards.py::test_frames_round_trip_through_dataloader_with_two_workers",),
    ),
    Mutant(
        "ranks-compute-what-they-saw",
        "each process computes only the metrics it updated itself",
        "src/occtrain/metrics/__init__.py",
        "    if metrics and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:\n",
        "    if False:\n",
        ("tests/unit/metrics/test_occupancy.py::test_two_process_ddp_equals_single_process",),
    ),
    Mutant(
        "ranks-read-everything",
        "each DDP rank trains on every sample of the global batch",
        "src/occtrain/data/shards/positions.py",
        "        if within // batch_size == rank and step % workers == worker:\n",
        "        if step % workers == worker:\n",
        ("tests/unit/data/shards/test_shards.py::test_two_ranks_of_b_train_on_the_batches_of_one_process_of_2b",),
    ),
    Mutant(
        "loader-restarts-its-epoch",
        "a resumed stage's data starts again at the first sample",
        "src/occtrain/data/datamodule.py",
        "        self.source.start, self._start = self._start, 0\n",
        "        self.source.start, self._start = 0, 0\n",
        (
            "tests/unit/data/shards/test_shards.py::test_an_epoch_resumed_mid_way_with_workers_sees_each_sample_once",
            "tests/e2e/test_distributed.py::test_a_ddp_epoch_killed_mid_way_resumes_without_repeating_or_skipping_a_sample",
        ),
    ),
    Mutant(
        "fsdp-does-not-shard",
        "trainer.strategy=fsdp leaves the world model whole on every rank",
        "src/occtrain/stages/pretrain_instruct.py",
        '        shard_world_model(world, mesh["data_parallel"])\n',
        "        pass\n",
        ("tests/e2e/test_sharded.py::test_sharded_training_equals_ddp_with_the_same_global_batch",),
    ),
    Mutant(
        "uniform-task-draw",
        "tasks are drawn uniformly, whatever their weights",
        "src/occtrain/core/shared_tasks.py",
        "size=len(names), replace=False, p=p / p.sum())",
        "size=len(names), replace=False)",
        ("tests/unit/families/occllama/test_tasks.py::test_sampling_is_deterministic_and_follows_weights",),
    ),
    Mutant(
        "cider-as-fraction",
        "CIDEr reported divided by 10",
        "src/occtrain/metrics/captions.py",
        'scores["CIDEr"] = float(Cider().compute_score(gts, res)[0])',
        'scores["CIDEr"] = float(Cider().compute_score(gts, res)[0]) / 10',
        ("tests/unit/metrics/test_qa_and_captions.py::test_caption_metric_by_hand",),
    ),
    Mutant(
        "deletion-escapes-the-run",
        "the one door for deletions no longer checks the target lies inside its directory",
        "src/occtrain/formats/io.py",
        'if target.name in ("", ".", "..") or where == root_path or not where.is_relative_to(root_path):',
        "if False:",
        ("tests/unit/formats/test_io.py::test_a_deletion_that_reaches_outside_the_run_is_refused",),
    ),
    Mutant(
        "stage-name-unchecked",
        "a stage's name is not checked to be one folder name",
        "src/occtrain/run/planning.py",
        '    check_name(spec.name, f"stages[{i}].name", source, "a stage")\n',
        "",
        (
            "tests/e2e/test_bad_inputs.py::test_bad_input_is_one_line_and_changes_nothing[stage-name-escapes]",
            "tests/e2e/test_bad_inputs.py::test_bad_input_is_one_line_and_changes_nothing[restart-an-escaping-stage]",
        ),
    ),
    Mutant(
        "restart-deletes-at-once",
        "--restart deletes the stages it retrains instead of setting them aside",
        "src/occtrain/formats/manifest.py",
        "                    os.rename(run_dir / name, aside / name)\n",
        "                    remove_inside(run_dir / name, run_dir)\n",
        (
            "tests/unit/run/test_runner.py::test_a_restart_that_fails_before_its_first_checkpoint_puts_the_old_stages_back",
        ),
    ),
)


def working_tree(dest: Path) -> None:
    """Copy the files git sees (tracked and untracked, not ignored) to ``dest``."""
    files = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            capture_output=True,
            check=True,
        )
        .stdout.decode()
        .split("\0")
    )
    for rel in filter(None, files):
        src = REPO / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def apply(mutant: Mutant, root: Path) -> None:
    path = root / mutant.file
    text = path.read_text()
    count = text.count(mutant.old)
    if count != 1:
        raise SystemExit(
            f"mutant '{mutant.name}': {mutant.file} holds its original text {count} times, not once; update "
            "tools/mutants.py"
        )
    path.write_text(text.replace(mutant.old, mutant.new))


def run_tests(root: Path, tests: tuple[str, ...]) -> tuple[int, float, str]:
    """pytest on ``tests`` in the copy at ``root``, importing occtrain from the copy; in one
    process, since with -x pytest-xdist reports a failure as an interruption (exit code 2)."""
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(root / "src"), os.environ.get("PYTHONPATH", "")]))
    )
    started = time.time()
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-n", "0", "-p", "no:cacheprovider", *tests],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
    )
    tail = (res.stdout + res.stderr).strip().splitlines()
    return res.returncode, time.time() - started, tail[-1] if tail else ""


def check_imports_copy(root: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(root / "src"))
    where = subprocess.run(
        [sys.executable, "-c", "import occtrain; print(occtrain.__file__)"],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    if not where.startswith(str(root)):
        raise SystemExit(
            f"the copy imports occtrain from {where}, not from {root}/src; a mutant there would change nothing"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", default=[], help="run this mutant (repeatable)")
    parser.add_argument("--list", action="store_true", help="list the mutants and their tests")
    parser.add_argument("--no-baseline", action="store_true", help="skip running the tests on the unchanged code first")
    args = parser.parse_args(argv)
    chosen = [m for m in MUTANTS if not args.only or m.name in args.only]
    unknown = set(args.only) - {m.name for m in MUTANTS}
    if unknown:
        parser.error(f"no mutant {sorted(unknown)[0]!r}; --list shows them")
    if args.list:
        for m in chosen:
            print(f"{m.name}: {m.what} ({m.file})")
            for t in m.tests:
                print(f"    {t}")
        return 0

    rows, survivors = [], 0
    with tempfile.TemporaryDirectory(prefix="occtrain-mutants-") as tmp:
        clean = Path(tmp) / "clean"
        working_tree(clean)
        check_imports_copy(clean)
        for m in chosen:
            base = "skipped"
            if not args.no_baseline:
                code, seconds, tail = run_tests(clean, m.tests)
                base = "passes" if code == 0 else f"FAILS ({tail})"
            copy = Path(tmp) / m.name
            shutil.copytree(clean, copy)
            apply(m, copy)
            for test in m.tests:
                code, seconds, tail = run_tests(copy, (test,))
                killed = code == 1  # tests ran and failed; 2+ is a collection or usage error
                survivors += not killed or base.startswith("FAILS")
                verdict = "killed" if killed else f"SURVIVED ({tail})" if code == 0 else f"error {code} ({tail})"
                rows.append((m.name, m.what, test.removeprefix("tests/"), base, verdict, seconds))
                print(f"{m.name:32s} {verdict:10s} {seconds:6.0f}s  {test}", file=sys.stderr, flush=True)
            shutil.rmtree(copy)

    print("| mutant | the change | test | unchanged code | mutant |")
    print("|---|---|---|---|---|")
    for name, what, test, base, verdict, seconds in rows:
        print(f"| `{name}` | {what} | `{test}` | {base} | {verdict} ({seconds:.0f} s) |")
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main())

"""Several processes through the real CLI: DDP validation of an odd-sized split equals one
process exactly, and two torchrun nodes train like one process with the same global batch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from conftest import REPO, free_port, kill_at_checkpoint, run_cli_process, write_hand_dataset
from occtrain.formats.metrics_file import read_metrics
from occtrain.stages.callbacks import MEASURED

pytestmark = pytest.mark.slow

#: OccWorld's VQ-VAE at test size; nothing that depends on the per-rank batch (no EMA
#: statistics, code restarts or sampled Lovasz), so DDP and one process compute one loss.
RECIPE = """
name: dist
runs_root: {runs}
data: {{root: {data}, batch_size: 2, samples_per_shard: 4, history: 1, future: 1, shuffle_buffer: 8}}
trainer: {{max_steps: 4, val_check_interval: 4, limit_val_batches: -1, ckpt_every_n_steps: 2, log_every_n_steps: 1}}
stages:
  - name: tokenizer
    kind: tokenizer
    model:
      arch: occworld_vqvae
      occworld_vqvae: {{num_codes: 16, code_dim: 8, class_embed_dim: 4, base_channels: 8, channel_mult: [1, 1, 1],
                        strides: [4, 5], num_res_blocks: 1, latent_attention: false, z_channels: 8, lovasz_weight: 0.0}}
    optim: {{lr: {lr}, weight_decay: 0.0}}
"""


#: A stage without discrete steps (no nearest-code choice that a float's last bit can flip),
#: so two ranks and one process stay on the same path: an embedding and a classifier.
PROBE_RECIPE = """
name: dist
plugins: [plugins.probe_stage]
runs_root: {runs}
data: {{root: {data}, batch_size: 2, samples_per_shard: 4, history: 1, future: 1, shuffle_buffer: 8}}
trainer: {{max_steps: 6, val_check_interval: 6, limit_val_batches: -1, ckpt_every_n_steps: 2, log_every_n_steps: 1}}
stages:
  - name: probe
    kind: probe
    model: {{width: 6}}
    # A large epsilon: Adam's step on a near-zero gradient is about lr x its sign, so a
    # rounding difference there would move a weight by a whole step (a real effect of Adam,
    # not of how the batch is split, which is what this test is about).
    optim: {{lr: 0.05, weight_decay: 0.0, eps: 1.0e-3}}
"""


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    # 9 val frames: an odd split, which two ranks cannot halve.
    return write_hand_dataset(tmp_path_factory.mktemp("dist") / "ds", train=2, val=1, frames=9)


def _recipe(tmp_path: Path, world: Path, lr: float) -> Path:
    path = tmp_path / "dist.yaml"
    path.write_text(RECIPE.format(runs=tmp_path / "runs", data=world, lr=lr))
    return path


def _torchrun(args: list[str], nodes: int, per_node: int, port: int) -> list[subprocess.Popen]:
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]))
    )
    procs = []
    for node in range(nodes):
        cmd = [
            sys.executable,
            "-m",
            "torch.distributed.run",
            f"--nnodes={nodes}",
            f"--nproc-per-node={per_node}",
            f"--node-rank={node}",
            "--master-addr=127.0.0.1",
            f"--master-port={port}",
            "-m",
            "occtrain",
            *args,
        ]
        procs.append(
            subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        )
    return procs


def _finish(procs: list[subprocess.Popen]) -> list[tuple[int, str]]:
    out = []
    for p in procs:
        _, err = p.communicate(timeout=600)
        out.append((p.returncode, err))
    return out


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    # Lightning gives each of 2 DDP processes one of the 2 cores; one process would use
    # both, and a convolution summed in another order can flip a near-tie argmax of an
    # untrained model. One thread everywhere: every sample meets the very same arithmetic.
    monkeypatch.setenv("OMP_NUM_THREADS", "1")


def test_ddp_validation_of_an_odd_split_equals_one_process(tmp_path, world):
    # lr 0: both runs validate the very same weights, in batches of one sample (a batch
    # of two rounds differently from two of one). Rank 1 holds 4 of the 9 frames: its
    # first batch is padding alone, which must count for nothing.
    recipe = _recipe(tmp_path, world, lr=0.0)
    one = run_cli_process("run", str(recipe), "data.batch_size=1", "--run-dir", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr[-3000:]
    two = run_cli_process(
        "run",
        str(recipe),
        "data.batch_size=1",
        "trainer.devices=2",
        "trainer.strategy=ddp",
        "--run-dir",
        str(tmp_path / "two"),
        timeout=600,
    )
    assert two.returncode == 0, two.stderr[-3000:]
    # Two processes, each validating its own share of the 9 frames (5 and 4), not all of them.
    (one_attempt,) = json.loads((tmp_path / "one" / "manifest.json").read_text())["stages"]["tokenizer"]["history"]
    (two_attempt,) = json.loads((tmp_path / "two" / "manifest.json").read_text())["stages"]["tokenizer"]["history"]
    assert (one_attempt["world_size"], one_attempt["val_samples_per_rank"]) == (1, [9])
    assert (two_attempt["world_size"], two_attempt["val_samples_per_rank"]) == (2, [5, 4])
    one_file, two_file = (read_metrics(tmp_path / run / "tokenizer" / "metrics.json") for run in ("one", "two"))
    single, ddp = one_file.metrics, two_file.metrics
    assert single.keys() == ddp.keys()
    # Both measured every val frame, once: the provenance counts the two ranks' shares together.
    assert one_file.provenance.coverage["validation"] == two_file.provenance.coverage["validation"] == [9, 9]
    for key in single:
        if key.endswith(MEASURED):
            continue  # measurements of the machine, not results
        if "IoU" in key:  # from integer counts, gathered across ranks: exactly equal
            assert ddp[key] == single[key], key
        else:  # float sums, added in another order
            assert ddp[key] == pytest.approx(single[key], rel=1e-6), key
    assert "sync_dist" not in two.stderr


def test_two_torchrun_nodes_train_like_one_process(tmp_path, world):
    recipe = tmp_path / "probe.yaml"
    recipe.write_text(PROBE_RECIPE.format(runs=tmp_path / "runs", data=world))
    one = run_cli_process("run", str(recipe), "--run-dir", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr[-3000:]

    # Two node ranks of one process each, batch 1 per rank: the same global batch of 2.
    args = [
        "run",
        str(recipe),
        "trainer.num_nodes=2",
        "trainer.strategy=ddp",
        "data.batch_size=1",
        "--run-dir",
        str(tmp_path / "two"),
    ]
    results = _finish(_torchrun(args, nodes=2, per_node=1, port=free_port()))
    for code, err in results:
        assert code == 0, err[-3000:]
    manifest = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert manifest["stages"]["probe"]["attempts"] == 1 and manifest["stages"]["probe"]["status"] == "done"
    # Two processes (one per node), each training on one sample a step: 6 steps.
    (attempt,) = manifest["stages"]["probe"]["history"]
    assert attempt["world_size"] == 2 and attempt["train_samples_per_rank"] == [6, 6]
    for _, err in results:
        assert "sync_dist" not in err and "Warning" not in err, err[-3000:]
    assert sum(err.count("done    probe") for _, err in results) == 1  # one process reports

    # Equal up to the order floats are summed in (gradients averaged over ranks vs over
    # one batch), which AdamW amplifies a little on tiny gradients: far below one step's
    # update (lr 5e-2). A run that saw other batches (one sample a step) is far off.
    def weights(run: str) -> dict[str, torch.Tensor]:
        return load_file(tmp_path / run / "probe" / "export" / "model.safetensors")

    def gap(a: dict, b: dict) -> float:
        assert a.keys() == b.keys()
        return max(float((a[k] - b[k]).abs().max()) for k in a)

    same_batches = gap(weights("two"), weights("one"))
    assert same_batches < 1e-4  # measured 6e-6 to 1e-5 (Adam's normalisation of float-order differences)
    other = run_cli_process("run", str(recipe), "data.batch_size=1", "--run-dir", str(tmp_path / "other"))
    assert other.returncode == 0, other.stderr[-3000:]
    assert gap(weights("other"), weights("one")) > 10 * same_batches


def test_a_ddp_epoch_killed_mid_way_resumes_without_repeating_or_skipping_a_sample(tmp_path, world):
    """Two ranks, two loader workers each, one sample per rank a step: the 18 train frames
    are one epoch of 9 steps (no shuffle buffer, so an epoch is each sample once). Killed
    (-9) after a checkpoint mid-epoch and resumed, the samples of every step equal an
    uninterrupted run's, and together they are each train frame exactly once."""
    recipe = tmp_path / "probe.yaml"
    recipe.write_text(PROBE_RECIPE.format(runs=tmp_path / "runs", data=world))
    args = [
        "run",
        str(recipe),
        "trainer.devices=2",
        "trainer.strategy=ddp",
        "trainer.max_steps=9",
        "trainer.val_check_interval=9",
        "data.batch_size=1",
        "data.num_workers=2",
        "data.shuffle_buffer=1",
    ]

    def steps(seen: Path) -> dict[int, list[str]]:
        """Each step's global batch (rank 0's samples, then rank 1's), as last recorded."""
        per_rank = []
        for rank in (0, 1):
            rows = [json.loads(line) for line in Path(f"{seen}.rank{rank}").read_text().splitlines()]
            per_rank.append({row["step"]: row["keys"] for row in rows})  # a resumed step overwrites
        assert per_rank[0].keys() == per_rank[1].keys()
        return {step: per_rank[0][step] + per_rank[1][step] for step in sorted(per_rank[0])}

    whole = run_cli_process(
        *args,
        "--run-dir",
        str(tmp_path / "whole"),
        env={"OCCTRAIN_PROBE_SEEN": str(tmp_path / "whole.seen")},
        timeout=600,
    )
    assert whole.returncode == 0, whole.stderr[-3000:]
    last = tmp_path / "cut" / "probe" / "checkpoints" / "last.ckpt"
    cut = {"OCCTRAIN_PROBE_SEEN": str(tmp_path / "cut.seen"), "OCCTRAIN_PROBE_STEP_DELAY": "0.5"}
    killed_at = kill_at_checkpoint([*args, "--run-dir", str(tmp_path / "cut")], last, step=4, env=cut, timeout=300)
    resumed = run_cli_process(
        *args, "--run-dir", str(tmp_path / "cut"), env={"OCCTRAIN_PROBE_SEEN": str(tmp_path / "cut.seen")}, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    (first, second) = json.loads((tmp_path / "cut" / "manifest.json").read_text())["stages"]["probe"]["history"]
    assert second["start_step"] == killed_at >= 4  # resumed mid-epoch, not restarted

    reference, got = steps(tmp_path / "whole.seen"), steps(tmp_path / "cut.seen")
    assert list(got) == list(range(9)) and got == reference
    frames = [key for batch in reference.values() for key in batch]
    assert len(frames) == len(set(frames)) == 18

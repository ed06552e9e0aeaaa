"""A tiny stage kind for runner tests, loaded through a recipe's ``plugins:`` list.

A per-voxel class embedding and a linear classifier on a subsampled grid: small enough
that a stage takes a second, deterministic enough that resumed and uninterrupted runs
can be compared weight for weight.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

from torch import nn

from occtrain.formats.exports import read_export, write_export
from occtrain.stages import Stage, StageContext, StageKind, StageReport, register
from occtrain.stages.optim import configure_adamw


@dataclass
class ProbeConfig:
    width: int = 4
    fail: bool = False


#: Seconds each training step sleeps, so that a test can stop the process mid-stage. An
#: environment variable, not a config key: it changes timing only, so a rerun without it
#: resumes the same stage (the config hash) at full speed.
STEP_DELAY = "OCCTRAIN_PROBE_STEP_DELAY"
#: A path: each rank appends the step and the sample keys of every training batch to
#: ``PATH.rank<R>`` (JSON lines), for tests of which samples training saw.
SEEN = "OCCTRAIN_PROBE_SEEN"


class Probe(Stage):
    """Per-voxel class embedding -> 1x1x1 classifier: learns the identity map of labels."""

    consumes_kinds = ("probe",)
    consumes_count = (0, 1)

    def __init__(self, ctx: StageContext):
        super().__init__(ctx)
        self.embed = nn.Embedding(18, ctx.model_cfg.width)
        self.head = nn.Linear(ctx.model_cfg.width, 18)
        self.loaded_from = ""
        if ctx.inputs:  # handoff: start from the consumed stage's export
            state, config = read_export(next(iter(ctx.inputs.values())))
            self.load_state_dict(state)
            self.loaded_from = config["stage"]

    def training_step(self, batch, _):
        time.sleep(float(os.environ.get(STEP_DELAY, 0)))
        if os.environ.get(SEEN):
            with open(f"{os.environ[SEEN]}.rank{self.global_rank}", "a") as fh:
                fh.write(json.dumps({"step": self.global_step, "keys": batch["token"]}) + "\n")
        if self.ctx.model_cfg.fail:
            raise RuntimeError("probe exploded\nsecond line")
        sem = batch["semantics"].long()[:, ::8, ::8]
        loss = nn.functional.cross_entropy(self.head(self.embed(sem)).flatten(0, -2), sem.flatten())
        self.log("train/loss", loss)
        return loss

    def validation_step(self, batch, _):
        sem = batch["semantics"].long()[:, ::8, ::8]
        acc = (self.head(self.embed(sem)).argmax(-1) == sem).float().mean()
        self.log("val/acc", acc, sync_dist=True)

    def configure_optimizers(self):
        return configure_adamw(self.parameters(), self.ctx.spec.optim, self.ctx.trainer.max_steps)

    def export(self, path: Path) -> Path:
        return write_export(path, self.state_dict(), {"stage": self.ctx.spec.name, "init_from": self.loaded_from})

    def report(self) -> StageReport:
        return StageReport("probe")


PROBE = register(StageKind(name="probe", model_schema=ProbeConfig, data_kind="frames", module=Probe, monitor="val/acc"))

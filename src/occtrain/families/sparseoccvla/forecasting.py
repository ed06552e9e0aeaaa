"""Scoring SparseOccVLA's forecaster and encoder (an evaluation hook): the points of each
future frame voxelized into the Occ3D grid and scored in the OccWorld convention (every
voxel: no camera mask, as the paper states), at 1 / 2 / 3 s, on every frame with a whole
3 s future and, separately, with the paper's frames (the first five and last seven of each
scene left out); beside the shared forecast baselines (``core.scorers.forecast_baselines``:
the exact current scene copied, the encoder's own reconstruction of it copied, OccWorld's
Copy&Paste, the exact scene moved by the ego's constant velocity, and the per-voxel prior of
the train split), on the same samples. The encoder's
reconstruction of the current frame is scored too (Table 8's "Curr")."""

from __future__ import annotations

import numpy as np
import torch

from occtrain.core.protocols import FUTURE_CLIPS, ScoringContext, WorldEngine, family_world
from occtrain.core.scorers import FORECAST_BASELINES, forecast_baselines, forecast_metric
from occtrain.data.clips import Clip, Text
from occtrain.families.sparseoccvla.tasks import FORECAST_PROMPT, context
from occtrain.families.sparseoccvla.world_model import SparseOccVLAWorldModel, scene_rows
from occtrain.formats.occ3d import FREE, FUTURE_STEPS, MOVABLE_CLASSES
from occtrain.metrics import OccupancyMetric
from occtrain.metrics.occupancy import OCC3D, OCCWORLD

#: The paper's forecast frames: a scene's first five and last seven are left out (Sec. 4.1).
SKIP_FIRST, SKIP_LAST = 5, 7
#: The two clip selections each forecast number is reported on.
SELECTIONS = ("", "trimmed_")
PREDICTIONS = ("forecast", *FORECAST_BASELINES)


def paper_frame(position: int, scene_frames: int) -> bool:
    """Whether frame ``position`` of a scene of ``scene_frames`` counts in the paper's forecast mIoU."""
    return SKIP_FIRST <= position < scene_frames - SKIP_LAST


class ForecastHead:
    """The forecaster on every frame with a whole future (see the module docstring)."""

    clips = FUTURE_CLIPS
    metrics = {
        **{f"{what}_{sel}{OCCWORLD}": forecast_metric for what in PREDICTIONS for sel in SELECTIONS},
        "reconstruction_occworld": lambda: OccupancyMetric(OCCWORLD, subsets={"movable": MOVABLE_CLASSES}),
        "reconstruction_occ3d": lambda: OccupancyMetric(OCC3D),
    }

    def applies(self, engine: WorldEngine) -> bool:
        return engine.tasks.weights.get("forecast", 0) > 0

    @torch.no_grad()
    def run(self, ev: ScoringContext, engine: WorldEngine, clips: list[Clip]) -> None:
        index, dev = ev.index, ev.device
        assert index is not None  # an evaluator's run sets it before its hooks run
        world = family_world(engine, SparseOccVLAWorldModel)
        for clip in clips:
            token, a = clip.anchor["token"], clip.anchor_index
            scene = index.scene_of(token)
            rows = scene_rows(engine)[token]
            steps = world.forecast(
                engine.encode_parts([*context(clip, engine.tasks), Text(FORECAST_PROMPT)], {a: rows})
            )
            future = clip.ann["tokens"][a + 1 : a + 1 + FUTURE_STEPS]
            n = min(len(steps), len(future))
            labels = [index.labels(scene, t) for t in [token, *future[:n]]]
            target = torch.full((1, FUTURE_STEPS, *labels[0]["semantics"].shape), FREE, dtype=torch.long)
            target[0, :n] = torch.from_numpy(np.stack([x["semantics"] for x in labels[1:]])).long()
            valid = (torch.arange(FUTURE_STEPS) < n)[None]
            pred = torch.full_like(target, FREE)
            for t, (points, classes) in enumerate(steps[:n]):
                pred[0, t] = world.voxelize(points, classes).cpu()
            current = torch.from_numpy(labels[0]["semantics"]).long()
            recon = engine.decode_scenes(rows[None])[0].cpu()
            # The ceiling: each future frame read from its own cameras (what a perfect forecast
            # in the encoder's points scores). No moved reconstruction, nor movers pasted into
            # one: the encoder reads cameras, which a moved scene has none of.
            future_recon = torch.full_like(target[0], FREE)
            if n:
                cached = scene_rows(engine)
                future_recon[:n] = engine.decode_scenes(torch.stack([cached[t] for t in future[:n]])).cpu()
            prior = ev.priors.voxels() if ev.priors.data_root is not None else None
            predictions = {
                "forecast": pred,
                **forecast_baselines(current, recon, clip.anchor, prior=prior, future_reconstruction=future_recon),
            }
            selections = [""] + (
                ["trimmed_"] if paper_frame(index.scenes[scene].index(token), len(index.scenes[scene])) else []
            )
            for what, volumes in predictions.items():
                for sel in selections:
                    ev.metric(f"{what}_{sel}{OCCWORLD}").update(volumes.to(dev), target.to(dev), valid.to(dev))
            ev.metric("reconstruction_occworld").update(recon[None].to(dev), current[None].to(dev))
            mask = torch.from_numpy(labels[0]["mask_camera"].astype(bool))[None]
            ev.metric("reconstruction_occ3d").update(recon[None].to(dev), current[None].to(dev), mask.to(dev))
            ev.keep_forecast_picture(token, pred[0].numpy(), target[0].numpy(), n)
            ev.keep_scene(
                "reconstruction",
                f"reconstruction from the cameras, sample {token[:8]}: truth and the encoder's points",
                [("truth", current.numpy()), ("encoder", recon.numpy())],
            )

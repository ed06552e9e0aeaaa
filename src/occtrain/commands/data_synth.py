"""``occtrain data synth``: the embedded synthetic world written in the Occ3D layout."""

from __future__ import annotations

from pathlib import Path

from occtrain.errors import ConfigError


def synth(out: str | Path, scenes: int, val_scenes: int, frames: int, seed: int, workers: int | None) -> None:
    """Write ``scenes`` train and ``val_scenes`` val scenes of ``frames`` frames to ``out``."""
    from occtrain.config import SynthConfig
    from occtrain.config.groups import check_seed
    from occtrain.data.synthesize import synthesize

    check_seed(seed, "--seed")  # named as the user typed it; check_synth_config would say data.synth.seed
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers}: give at least 1 process")
    cfg = SynthConfig(train_scenes=scenes, val_scenes=val_scenes, frames_per_scene=frames, seed=seed)
    synthesize(out, cfg, workers=workers)

"""``occtrain data synth``: the embedded synthetic world written in the Occ3D layout."""

from __future__ import annotations

from pathlib import Path

from occtrain.errors import ConfigError


def synth(
    out: str | Path,
    scenes: int,
    val_scenes: int,
    frames: int,
    seed: int,
    workers: int | None,
    cameras: str = "72x128",
) -> None:
    """Write ``scenes`` train and ``val_scenes`` val scenes of ``frames`` frames to ``out``,
    with ``cameras`` ("HxW") images."""
    from occtrain.config import SynthConfig
    from occtrain.config.groups import check_seed
    from occtrain.data.synthesize import synthesize

    check_seed(seed, "--seed")  # named as the user typed it; check_synth_config would say data.synth.seed
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers}: give at least 1 process")
    size = cameras.lower().split("x")
    if len(size) != 2 or not all(p.isdigit() for p in size):
        raise ConfigError(f"--cameras {cameras}: give the image size as HxW pixels, e.g. 144x256 (0x0: no cameras)")
    height, width = int(size[0]), int(size[1])
    cfg = SynthConfig(
        train_scenes=scenes,
        val_scenes=val_scenes,
        frames_per_scene=frames,
        seed=seed,
        camera_height=height,
        camera_width=width,
    )
    synthesize(out, cfg, workers=workers)

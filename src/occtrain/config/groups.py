"""Structured-config dataclasses shared by every command: data and trainer groups."""

from __future__ import annotations

from dataclasses import dataclass, field

from occtrain.errors import ConfigError


@dataclass
class SynthConfig:
    """Size and seed of the embedded synthetic world."""

    train_scenes: int = 4
    val_scenes: int = 2
    frames_per_scene: int = 40
    seed: int = 0
    #: Size of the six camera images: nuScenes' 900 x 1600 scaled by 0.08, which keeps a
    #: ViT patch grid (8 px: 9 x 16) and the rendering cheap on a CPU; 0 renders no cameras.
    camera_height: int = 72
    camera_width: int = 128


#: The largest seed numpy's generators take (``np.random.seed``, and Lightning's
#: ``seed_everything``, which seeds numpy); the smallest is 0.
SEED_MAX = 2**32 - 1


def check_seed(seed: int, key: str, where: str = "") -> None:
    """Refuse a seed numpy would refuse with a traceback (late, once training or synthesis
    began), naming ``key`` and ``where`` it is set (e.g. `` in recipes/x.yaml``)."""
    if not 0 <= seed <= SEED_MAX:
        raise ConfigError(
            f"{key} is {seed}{where}: a seed is an integer from 0 to {SEED_MAX} (2**32 - 1), as numpy's random "
            "generators take"
        )


#: The longest scene the world synthesizes (60 s at 2 Hz; nuScenes' are 20 s): its road grid
#: grows with the scene (``data.synth.scene.grid_extent``), checked on several seeds up to
#: here, and a scene's synthesis time grows faster than its length (120 frames: 10-16 s).
MAX_FRAMES_PER_SCENE = 120


def check_synth_config(cfg: SynthConfig) -> None:
    """Refuse a world that cannot be synthesized, naming the settings."""
    check_seed(cfg.seed, "data.synth.seed")
    if cfg.train_scenes < 1 or cfg.val_scenes < 0 or cfg.frames_per_scene < 1:
        raise ConfigError(
            f"synth needs at least one train scene and one frame per scene (got train_scenes={cfg.train_scenes}, "
            f"val_scenes={cfg.val_scenes}, frames_per_scene={cfg.frames_per_scene}); set --scenes/--frames (or a "
            "recipe's data.synth) to at least 1"
        )
    if cfg.frames_per_scene > MAX_FRAMES_PER_SCENE:
        raise ConfigError(
            f"data.synth.frames_per_scene={cfg.frames_per_scene}: a synthesized scene holds at most "
            f"{MAX_FRAMES_PER_SCENE} frames ({MAX_FRAMES_PER_SCENE // 2} s at 2 Hz); set --frames (or a recipe's "
            "data.synth.frames_per_scene) lower, and --scenes higher for more frames"
        )
    if (cfg.camera_height > 0) != (cfg.camera_width > 0) or min(cfg.camera_height, cfg.camera_width) < 0:
        raise ConfigError(
            f"synth.camera_height={cfg.camera_height}, synth.camera_width={cfg.camera_width}: both positive, or both 0 "
            "for no cameras"
        )


@dataclass
class DataConfig:
    """Where a dataset lives and how training reads it."""

    #: Dataset root in the Occ3D layout (annotations.json + gts/). Synthesized if absent.
    root: str = "data/synth"
    #: Webdataset shards made from ``root``; empty means ``<root>/shards``.
    shards: str = ""
    synth: SynthConfig = field(default_factory=SynthConfig)
    samples_per_shard: int = 64
    #: History and future frames of a world-model clip (paper: 4 history, 6 future at 2 Hz).
    history: int = 4
    future: int = 6
    batch_size: int = 2
    num_workers: int = 0
    #: How each seeded epoch is shuffled: -1, every sample in one permutation; 0 or 1, whole
    #: shards in a permutation; larger, those shards mixed by a buffer of this many samples.
    shuffle_buffer: int = -1
    seed: int = 0


@dataclass
class TrainerConfig:
    """The subset of ``lightning.Trainer`` arguments a recipe sets."""

    accelerator: str = "cpu"
    devices: int = 1
    num_nodes: int = 1
    #: Lightning's strategy name ("auto", "ddp", ...), or "fsdp": occtrain's sharded
    #: strategy (FSDP2 over every rank, CPU processes or GPUs; pretrain and instruct stages).
    strategy: str = "auto"
    precision: str = "32-true"
    max_steps: int = 100
    max_epochs: int = -1
    val_check_interval: int = 50
    #: Val batches per validation (teacher-forced scores); -1: the whole val split.
    limit_val_batches: int = 8
    log_every_n_steps: int = 10
    #: Save ``last.ckpt`` every this many optimizer steps so a kill loses little.
    ckpt_every_n_steps: int = 25
    gradient_clip_val: float = 1.0
    accumulate_grad_batches: int = 1
    deterministic: bool = False
    #: Compile the stage's repeated blocks with ``torch.compile`` for its training steps
    #: (the LLM's decoder layers, a tokenizer's encoder and decoder); evaluation and
    #: generation stay eager (``models.compiling``).
    compile: bool = False
    seed: int = 0
    #: Where metrics go: "csv" (always written: the dashboard and a resume read it),
    #: "tensorboard", "mlflow" (a local file store in <run>/mlruns) and "wandb" (offline).
    loggers: list[str] = field(default_factory=lambda: ["csv", "tensorboard"])


@dataclass
class DatasetFile:
    """A file that configures a dataset alone (e.g. ``configs/data/*.yaml``) under ``data:``."""

    data: DataConfig = field(default_factory=DataConfig)

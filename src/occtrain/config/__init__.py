"""Typed configuration: dataclass schemas, YAML loading, overrides and validation."""

from occtrain.config.groups import DataConfig, DatasetFile, SynthConfig, TrainerConfig
from occtrain.config.loading import load_config, read_yaml, to_container, to_object, to_yaml
from occtrain.config.recipe import RecipeConfig

__all__ = [
    "DataConfig",
    "DatasetFile",
    "SynthConfig",
    "TrainerConfig",
    "load_config",
    "read_yaml",
    "to_container",
    "to_object",
    "to_yaml",
]

#: Which schema a file under ``configs/<group>/`` follows.
GROUP_SCHEMAS: dict[str, type] = {
    "data": DataConfig,
    "trainer": TrainerConfig,
    "dataset": DatasetFile,
    # recipes live in top-level recipes/ (and its ablations/, proof/ and scale/)
    "recipe": RecipeConfig,
    "recipes": RecipeConfig,
    "ablations": RecipeConfig,
    "proof": RecipeConfig,
    "scale": RecipeConfig,
}


def schema_for(path: str, group: str | None = None) -> type:
    """The schema of a config file: ``group`` if given, else its directory name under configs/."""
    from pathlib import Path

    from occtrain.errors import ConfigError

    name = group or Path(path).parent.name
    if name not in GROUP_SCHEMAS:
        raise ConfigError(
            f"{path}: cannot tell which config group it belongs to; pass --group one of "
            f"{', '.join(sorted(GROUP_SCHEMAS))}"
        )
    return GROUP_SCHEMAS[name]


__all__ += ["GROUP_SCHEMAS", "schema_for"]

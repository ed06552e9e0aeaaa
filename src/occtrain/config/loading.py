"""Load YAML onto structured configs, apply dotlist overrides, and explain mistakes in one line.

A YAML value may name another YAML file (``data: configs/data/quickstart.yaml``) where the
schema expects a section: that file's contents are merged in at that place, so recipes
compose the pieces under ``configs/``.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from occtrain.errors import ConfigError, did_you_mean

T = TypeVar("T")


def _dataclass_fields(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def section_type(tp: Any) -> type | None:
    """The dataclass a field holds (``Optional`` too), or the element dataclass of a list field."""
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):  # Optional[X] and X | None
        held = [a for a in typing.get_args(tp) if a is not type(None)]
        return section_type(held[0]) if len(held) == 1 else None
    if origin in (list, tuple):
        args = typing.get_args(tp)
        if args and isinstance(args[0], type) and dataclasses.is_dataclass(args[0]):
            return args[0]
    return None


def _is_mapping(tp: Any) -> bool:
    """True for ``dict[...]`` and ``Optional[dict[...]]`` fields."""
    if typing.get_origin(tp) is dict or tp is dict:
        return True
    return any(typing.get_origin(a) is dict for a in typing.get_args(tp))


#: The most values a YAML text may hold once its aliases are expanded: a recipe holds a few
#: hundred, while ``a: &a [x, x, ...]`` / ``b: &b [*a, *a, ...]`` nested a few deep holds
#: billions (an alias bomb: seconds and gigabytes at the first copy of the tree).
MAX_YAML_VALUES = 10_000


def safe_yaml(text: str, where: str) -> Any:
    """``yaml.safe_load`` of ``text``, refused in one line naming ``where`` when its aliases
    expand past ``MAX_YAML_VALUES`` values or refer to themselves: counted on the parsed
    node graph, where an alias is one node however often it is used, before anything is
    built from it."""
    node = yaml.compose(text, Loader=yaml.SafeLoader)
    if node is None:
        return None
    sizes: dict[int, int] = {}

    def expanded(n: yaml.Node, open_: frozenset[int]) -> int:
        if id(n) in open_:
            raise ConfigError(f"{where}: a YAML alias refers to the value that holds it; write the value out")
        if id(n) not in sizes:
            children: list[yaml.Node] = []
            if isinstance(n, yaml.SequenceNode):
                children = list(n.value)
            elif isinstance(n, yaml.MappingNode):
                children = [x for pair in n.value for x in pair]
            inner = open_ | {id(n)}
            sizes[id(n)] = 1 + sum(expanded(c, inner) for c in children)
            if sizes[id(n)] > MAX_YAML_VALUES:
                raise ConfigError(
                    f"{where}: its YAML aliases expand to over {MAX_YAML_VALUES} values (an alias bomb?); write the "
                    "values out, or use fewer aliases of aliases"
                )
        return sizes[id(n)]

    expanded(node, frozenset())
    return yaml.SafeLoader(text).get_single_data()


def read_yaml(path: Path) -> dict:
    """Read one YAML mapping; a missing file or bad YAML is a one-line ConfigError."""
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = safe_yaml(path.read_text(), str(path))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}{where}: not valid YAML ({getattr(err, 'problem', err)})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level")
    return data


def _resolve_includes(raw: Any, cls: type, source: Path, prefix: str) -> Any:
    """Check keys against the schema and inline ``key: some/file.yaml`` sections."""
    if not isinstance(raw, dict):
        return raw
    fields = _dataclass_fields(cls)
    out = {}
    for key, value in raw.items():
        full = f"{prefix}{key}"
        if key not in fields:
            raise ConfigError(f"unknown key '{full}' in {source}{did_you_mean(str(key), list(fields))}")
        sub = section_type(fields[key])
        if sub is None and _is_mapping(fields[key]) and isinstance(value, str) and value.endswith((".yaml", ".yml")):
            value = read_yaml(_find_include(value, source))  # a free-form section kept in its own file
        elif sub is not None and isinstance(value, str) and value.endswith((".yaml", ".yml")):
            include = _find_include(value, source)
            value = _resolve_includes(read_yaml(include), sub, include, f"{full}.")
        elif sub is not None and isinstance(value, list):
            value = [_resolve_includes(v, sub, source, f"{full}[{i}].") for i, v in enumerate(value)]
        elif sub is not None:
            value = _resolve_includes(value, sub, source, f"{full}.")
        out[key] = value
    return out


def read_resolved(path: str | Path, schema: type) -> dict:
    """A config file's keys as ``load_config`` reads them (includes inlined, an extended
    recipe merged), before defaults and overrides."""
    return _resolved(Path(path), schema, ())


def _resolved(path: Path, schema: type, seen: tuple[Path, ...]) -> dict:
    """The file's keys with its includes inlined and, for a schema with ``extends``, the
    recipe it extends merged under it: that recipe's stages first, its other keys replaced
    by this file's."""
    raw = _resolve_includes(read_yaml(path), schema, path, "")
    base_name = raw.pop("extends", "") if "extends" in _dataclass_fields(schema) else ""
    if not base_name:
        return raw
    base_path = _find_include(str(base_name), path)
    if base_path.resolve() in seen:
        raise ConfigError(f"{path}: extends {base_name}, which extends it back; extend a recipe that does not")
    base = _resolved(base_path, schema, (*seen, path.resolve()))
    return {**base, **raw, "stages": [*base.get("stages", []), *raw.get("stages", [])]}


def _find_include(name: str, source: Path) -> Path:
    """Includes resolve against the current directory, then the including file's directory."""
    for candidate in (Path(name), source.parent / name):
        if candidate.is_file():
            return candidate
    raise ConfigError(f"{source}: included config file not found: {name}")


def _merge(base: DictConfig, update: Any, source: str) -> DictConfig:
    try:
        merged = OmegaConf.merge(base, update)
        assert isinstance(merged, DictConfig)  # a mapping merged into a mapping
        return merged
    except OmegaConfBaseException as err:
        key = getattr(err, "full_key", None) or "?"
        msg = str(err).splitlines()[0]
        raise ConfigError(f"invalid value for '{key}' in {source}: {msg}") from None


def _check_override_key(cls: type, dotted: str, source: str) -> type | None:
    """Check each part of a dotted key against the schema; return the section type it names."""
    cur: type | None = cls
    parts = dotted.split(".")
    for depth, part in enumerate(parts):
        if cur is None:
            return None  # inside a free-form mapping
        name = part.split("[")[0]
        fields = _dataclass_fields(cur)
        if name not in fields:
            where = ".".join(parts[:depth])
            key = f"{where}.{name}" if where else name
            raise ConfigError(f"unknown key '{key}' in {source}{did_you_mean(name, list(fields))}")
        cur = section_type(fields[name])
    return cur


def load_config(schema: type[T], path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    """Build ``schema`` from its defaults, a YAML file and ``key=value`` overrides.

    Returns a validated, read-only omegaconf object typed as ``schema``.
    """
    cfg = OmegaConf.structured(schema)
    if path is not None:
        path = Path(path)
        raw = _resolved(path, schema, ())
        cfg = _merge(cfg, raw, str(path))
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}' must look like key=value (e.g. trainer.max_steps=10)")
        key = item.split("=", 1)[0].strip()
        section = _check_override_key(schema, key, f"override '{item}'")
        raw_value = item.split("=", 1)[1]
        try:
            value = safe_yaml(raw_value, f"override '{item}'") if raw_value.strip() else ""
        except yaml.YAMLError:
            value = raw_value  # not YAML: take the text as a string
        if section is not None and isinstance(value, str) and value.endswith((".yaml", ".yml")):
            include = _find_include(value, Path(f"override '{item}'"))
            value = _resolve_includes(read_yaml(include), section, include, f"{key}.")
        try:
            OmegaConf.update(cfg, key, value, merge=True)
        except (OmegaConfBaseException, ValueError, TypeError, IndexError, KeyError) as err:
            full = getattr(err, "full_key", None) or key
            raise ConfigError(f"invalid value for '{full}' in override '{item}': {str(err).splitlines()[0]}") from None
    OmegaConf.set_readonly(cfg, True)
    return cfg  # type: ignore[return-value]


def to_yaml(cfg: Any) -> str:
    """The resolved config as YAML text."""
    if isinstance(cfg, (DictConfig, ListConfig)):
        return OmegaConf.to_yaml(cfg, resolve=True)
    return yaml.safe_dump(cfg, sort_keys=False)


def to_container(cfg: Any) -> dict:
    """A plain dict of a config (for hashing and JSON)."""
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def to_object(cfg: Any) -> Any:
    """The dataclass instance behind a structured config; anything else as it is."""
    return OmegaConf.to_object(cfg) if OmegaConf.is_config(cfg) else cfg


def validate_section(schema: type[T], raw: Any, prefix: str, source: str | Path) -> T:
    """Validate a free-form section (e.g. a stage's ``model``) against ``schema``.

    Errors name the full key path (``stages[0].model.codebook_size``) and the source file.
    """
    if isinstance(raw, (DictConfig, ListConfig)):
        raw = OmegaConf.to_container(raw, resolve=True)
    if not isinstance(raw, dict):
        raise ConfigError(f"'{prefix}' in {source} must be a mapping of keys")
    checked = _resolve_includes(raw, schema, Path(str(source)), f"{prefix}.")
    cfg = _merge(OmegaConf.structured(schema), checked, str(source))
    OmegaConf.set_readonly(cfg, True)
    return cfg  # type: ignore[return-value]

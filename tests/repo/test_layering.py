"""The package's import arrows, read from the source with ``ast``.

Layers, top to bottom: cli -> the Python API -> commands/ -> run/ -> dashboard/ -> report/ ->
stages -> engine -> families -> core -> models / metrics / data -> config/ (with progress and
kinematics) -> formats/ and the base modules (errors, version). The top floor is one way:
commands drive run, run writes the dashboard and the report's tables, and the dashboard and
the report read run directories (``formats.manifest``) without importing run or commands. A
module may import its own layer or lower ones, never a higher one; on top of that:

- nothing in ``models/``, ``core/``, ``families/`` or ``engine/`` imports Lightning;
- no stage module imports another stage module (they share the infrastructure modules of
  ``STAGE_INFRA``: the base, trainer, callbacks, checkpoints, optimizer, loggers, sharding);
- a family imports no other family (shared code moves down into ``core/`` or ``models/``);
- ``core``, ``engine``, ``stages``, ``run``, ``commands``, the API and the dashboard name
  no family: they import none, and no string in them is a family's name (they look
  families up in the registry);
- ``metrics/`` never imports ``data/`` (metrics score anyone's predictions);
- only the generator's entry points (``data/synthesize.py``, ``data/closed_loop_recording.py`` for closed-loop
  driving) import ``data/synth``;
- no module imports the package root (``occtrain/__init__.py`` sits on top: it imports, nothing imports it).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from conftest import REPO
from occtrain.core import registry

SRC = REPO / "src" / "occtrain"

#: Layer of each top-level module or package of occtrain (higher imports lower).
LAYERS = {
    "cli": 12,
    "__main__": 12,
    "api": 11,
    "commands": 10,
    "run": 9,
    "dashboard": 8,
    "report": 7,
    "stages": 6,
    "engine": 5,
    "families": 4,
    "core": 3,
    "models": 2,
    "metrics": 2,
    "data": 2,
    "config": 1,
    "progress": 1,
    "kinematics": 1,
    "formats": 0,
    "errors": 0,
    "allocator": 0,
    "ranks": 0,
    "__init__": 0,
    "version": 0,
}
#: Modules of ``stages/`` that are infrastructure, not a stage kind.
STAGE_INFRA = {
    "occtrain.stages",
    "occtrain.stages.stage",
    "occtrain.stages.callbacks",
    "occtrain.stages.checkpoints",
    "occtrain.stages.common",
    "occtrain.stages.loggers",
    "occtrain.stages.optim",
    "occtrain.stages.phases",
    "occtrain.stages.registered_schemas",
    "occtrain.stages.sharding",
    "occtrain.stages.step_progress",
    "occtrain.stages.trainer",
}
LIGHTNING_FREE = ("models", "core", "families", "engine")
#: The modules outside ``data/synth`` that may import the generator.
GENERATOR_ENTRIES = ("occtrain.data.synthesize", "occtrain.data.closed_loop_recording")
#: What may not name a family: it looks families up in the registry.
FAMILY_NEUTRAL = ("core", "engine", "stages", "run", "commands", "api", "dashboard", "report")
#: The families occtrain ships, as the registry finds them.
FAMILIES = tuple(sorted(name for name in registry.families() if (SRC / "families" / name).is_dir()))


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(me: str, is_package: bool, source: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, function-level ones included."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.level:  # relative: resolve against the importing package
                base = me.split(".")
                base = base[: len(base) - node.level + is_package]
                out.append((node.lineno, ".".join([*base, node.module])))
            else:
                out.append((node.lineno, node.module))
    return out


def top(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def check_module(me: str, where: str, source: str, is_package: bool = False) -> list[str]:
    """Every rule the module ``me`` (its ``source``) breaks, one line each."""
    found = []
    mine = top(me)
    for line, target in imports(me, is_package, source):
        if target.split(".")[0] in ("lightning", "pytorch_lightning") and mine in LIGHTNING_FREE:
            found.append(f"{where}:{line} imports {target}: {mine}/ must not depend on Lightning")
        if target == "occtrain" and me != "occtrain.__main__":
            found.append(f"{where}:{line} imports the package root: import what it needs from the module that holds it")
        if not target.startswith("occtrain."):
            continue
        theirs = top(target)
        if theirs not in LAYERS:
            continue
        if LAYERS[theirs] > LAYERS[mine]:
            found.append(
                f"{where}:{line} imports {target}: {mine} (layer {LAYERS[mine]}) points up at {theirs} (layer "
                f"{LAYERS[theirs]})"
            )
        if mine == "stages" and me not in STAGE_INFRA and target.startswith("occtrain.stages."):
            stage = ".".join(target.split(".")[:3])
            if stage not in STAGE_INFRA and stage != me:
                found.append(f"{where}:{line} imports {target}: a stage imports another stage")
        if target.startswith("occtrain.families."):
            family = target.split(".")[2]
            if mine in FAMILY_NEUTRAL:
                found.append(f"{where}:{line} imports {target}: {mine} names no family (look it up in the registry)")
            elif mine == "families" and len(me.split(".")) > 2 and me.split(".")[2] != family:
                found.append(f"{where}:{line} imports {target}: a family imports no other family")
        if mine == "metrics" and theirs == "data":
            found.append(f"{where}:{line} imports {target}: metrics/ must not import data/")
        if target.startswith("occtrain.data.synth") and not target.startswith("occtrain.data.synthesize"):
            if not (me.startswith("occtrain.data.synth.") or me in ("occtrain.data.synth", *GENERATOR_ENTRIES)):
                found.append(
                    f"{where}:{line} imports {target}: only data/synthesize.py and data/closed_loop_recording.py "
                    "may import the generator"
                )
    if mine in FAMILY_NEUTRAL:
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.lower() in FAMILIES:
                found.append(
                    f"{where}:{node.lineno} names the family '{node.value}': {mine} looks families up in the registry"
                )
    return found


def violations() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        found += check_module(
            module_name(path), str(path.relative_to(REPO)), path.read_text(), path.name == "__init__.py"
        )
    return found


def test_every_module_has_a_layer():
    tops = {top(module_name(p)) for p in SRC.rglob("*.py")}
    assert tops <= set(LAYERS), f"give these a layer in LAYERS: {sorted(tops - set(LAYERS))}"


def test_imports_point_down():
    assert violations() == []


@pytest.mark.parametrize(
    "module, source, expected",
    [
        ("models/bad.py", "import lightning as L\n", "must not depend on Lightning"),
        ("engine/bad.py", "def f():\n    from lightning.pytorch import Trainer\n", "must not depend on Lightning"),
        (
            "stages/bad.py",
            "from occtrain.stages.pretrain_instruct import WorldModelStage\n",
            "a stage imports another stage",
        ),
        ("metrics/bad.py", "from occtrain.data.schema import COMMANDS\n", "metrics/ must not import data/"),
        ("families/bad.py", "from occtrain.engine import Evaluator\n", "points up"),
        ("data/bad.py", "from occtrain.data.synth.text import caption_for_frame\n", "only data/synthesize.py"),
        (
            "families/occllm/bad.py",
            "from occtrain.families.occllama.tasks import TaskConfig\n",
            "a family imports no other family",
        ),
        ("families/occllm/bad.py", "from occtrain.stages.stage import Stage\n", "points up"),
        ("engine/bad.py", "from occtrain.families.occvla.world_model import OccVLAWorldModel\n", "names no family"),
        ("stages/bad.py", "def f(family):\n    return family == 'occllama'\n", "names the family 'occllama'"),
        ("dashboard/bad.py", "FAMILY = 'OccVLA'\n", "names the family 'OccVLA'"),
        ("core/bad.py", "import lightning\n", "must not depend on Lightning"),
        ("core/bad.py", "from occtrain.families.occllama import OCCLLAMA\n", "points up"),
        ("formats/manifest.py", "from occtrain import __version__\n", "imports the package root"),
        ("data/bad.py", "import occtrain\n", "imports the package root"),
        # The top floor, one way: cli -> api -> commands -> run -> dashboard -> report.
        ("run/bad.py", "from occtrain.commands.drive import drive\n", "points up"),
        ("dashboard/bad.py", "from occtrain.run.control import stage_lock\n", "points up"),
        ("dashboard/bad.py", "def f():\n    from occtrain.commands.evaluate import evaluate\n", "points up"),
        ("report/bad.py", "from occtrain.dashboard import write_dashboard\n", "points up"),
        ("report/bad.py", "from occtrain.run.planning import load_recipe\n", "points up"),
        ("commands/bad.py", "from occtrain.api import load\n", "points up"),
        ("api.py", "from occtrain.cli import main\n", "points up"),
        ("formats/bad.py", "from occtrain.config.loading import read_yaml\n", "points up"),
    ],
)
def test_the_checker_catches(module, source, expected):
    """Each rule fails on a planted violation (a checker that cannot fail proves nothing)."""
    me = "occtrain." + module.removesuffix(".py").replace("/", ".")
    found = check_module(me, module, source)
    assert any(expected in v for v in found), found


def test_the_checker_passes_allowed_imports():
    assert (
        check_module(
            "occtrain.stages.planner",
            "stages/planner.py",
            "from occtrain.stages.stage import Stage\nfrom occtrain.engine import Evaluator\n",
        )
        == []
    )
    assert (
        check_module(
            "occtrain.families.occllm.tasks",
            "families/occllm/tasks.py",
            "from occtrain.families.occllm.config import X\nfrom occtrain.core.shared_tasks import TaskSpec\n",
        )
        == []
    )
    assert (
        check_module(
            "occtrain.data.synthesize", "data/synthesize.py", "from occtrain.data.synth.text import caption_for_frame\n"
        )
        == []
    )


def test_no_function_outside_the_generator_runs_over_60_lines():
    """Small functions that say what they do (the synthetic world's geometry is exempt)."""
    long = []
    for path in sorted(SRC.rglob("*.py")):
        if "data/synth/" in str(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 60:
                long.append(
                    f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
                )
    assert long == []


def test_every_family_folder_is_a_registered_family():
    folders = sorted(p.name for p in (SRC / "families").iterdir() if (p / "__init__.py").is_file())
    assert folders == list(FAMILIES) and len(FAMILIES) >= 5


def test_the_plugins_use_no_private_name_of_occtrain():
    """A family or stage kind written outside occtrain (tests/plugins/) needs only public names."""
    private = []
    for path in sorted((REPO / "tests" / "plugins").glob("*.py")):
        tree = ast.parse(path.read_text())
        modules = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        modules = {m for m in modules if not m.startswith("_")}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("occtrain"):
                private += [f"{path.name}:{node.lineno} {a.name}" for a in node.names if a.name.startswith("_")]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                if isinstance(node.value, ast.Name) and node.value.id in modules:
                    private.append(f"{path.name}:{node.lineno} {node.value.id}.{node.attr}")
    assert private == []


def unmirrored_tests(unit: Path, src: Path) -> list[str]:
    """Test files under ``unit`` whose place does not name what they test: each folder must be
    a package of ``src`` and each ``test_X.py`` (or ``test_X_aspect.py``) must test its
    module ``X.py``, or the package itself when X is the package's name."""
    found = []
    for test in sorted(unit.rglob("test_*.py")):
        package = src / test.parent.relative_to(unit)
        name = test.stem.removeprefix("test_")
        if not (package / "__init__.py").is_file():
            found.append(f"{test.relative_to(unit)}: no package {package.relative_to(src.parent)}")
            continue
        parts = name.split("_")
        prefixes = {"_".join(parts[:k]) for k in range(1, len(parts) + 1)}
        if name != package.name and not any((package / f"{p}.py").is_file() for p in prefixes):
            found.append(f"{test.relative_to(unit)}: names no module of {package.relative_to(src.parent)}")
    return found


def test_unit_tests_mirror_the_package():
    """A contributor goes from a module to its tests by path: tests/unit/ is laid out like src/occtrain/."""
    assert unmirrored_tests(REPO / "tests" / "unit", SRC) == []


def test_the_mirror_check_catches(tmp_path):
    src, unit = tmp_path / "src", tmp_path / "unit"
    for folder in (src / "data", unit / "data", unit / "nowhere"):
        folder.mkdir(parents=True)
    (src / "__init__.py").touch()
    (src / "data" / "__init__.py").touch()
    (src / "data" / "layout.py").touch()
    for test in ("data/test_layout.py", "data/test_layout_errors.py", "data/test_data.py", "data/test_shards.py"):
        (unit / test).touch()
    (unit / "nowhere" / "test_x.py").touch()
    assert unmirrored_tests(unit, src) == [
        "data/test_shards.py: names no module of src/data",
        "nowhere/test_x.py: no package src/nowhere",
    ]

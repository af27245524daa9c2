"""The code's layout: the method's stages import one way, the ROS side's folders show its parts,
no module outgrows one responsibility, and no module re-exports another's names.

These read the sources only (no import, no build), so they run in well under a second.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.package

REPO = Path(__file__).resolve().parents[2]

# The method's stages, lowest first: a stage may import only the stages before it.
CORE_STAGES = ("geometry", "memory", "correction", "io", "inference", "free_space", "costmap", "outputs",
               "torch_path", "measures")
# What every stage may use: the plumbing at the top of convbki_core.
CORE_PLUMBING = {"compiled", "devices", "paths"}
# The top of convbki_core: what a user imports, the composition and the plumbing; nothing else.
CORE_TOP = {"__init__", "compiled", "devices", "paths", "config", "parts", "mapper", "map_contents", "offline",
            "warm_up"}
# Above every stage: data, the simulator, training and the programs.
CORE_ABOVE = ("datasets", "synth", "training", "tools")
# The node's parts, lowest first; each may use the node's top-level plumbing (params, settings,
# dds, ros_args) but never the node itself (node, main).
ROS_PARTS = ("inputs", "outputs", "files", "mapping")
ROS_NODE = {"node", "main"}
MODULE_BYTES = 24_000


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports, at its top or inside a function."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
    return found


def _part(package: str, name: str) -> str | None:
    """The package or top-level module of ``package`` that an imported ``name`` falls in."""
    parts = name.split(".")
    return parts[1] if parts[0] == package and len(parts) > 1 else None


def _project_modules() -> list[Path]:
    roots = [REPO / "convbki_core", REPO / "convbki_ros", REPO / "test", REPO / "scripts", REPO / "launch"]
    return [REPO / "setup.py", *(path for root in roots for path in root.rglob("*.py"))]


def test_the_method_stages_import_one_way() -> None:
    """Each stage of convbki_core imports only the stages below it and the plumbing; no stage
    imports the composition (mapper, config, parts, ...) or what sits above the stages."""
    for index, stage in enumerate(CORE_STAGES):
        allowed = set(CORE_STAGES[:index + 1]) | CORE_PLUMBING
        for path in (REPO / "convbki_core" / stage).rglob("*.py"):
            used = {_part("convbki_core", name) for name in _imports(path)} - {None}
            assert used <= allowed, f"{path.relative_to(REPO)} imports {sorted(used - allowed)}"


def test_the_top_of_the_method_holds_its_public_api_and_plumbing_only() -> None:
    """convbki_core's top level: at most 10 modules, the expected ones; every stage and every
    package above them is a package; the stage packages' ``__init__`` re-export nothing."""
    core = REPO / "convbki_core"
    top = {path.stem for path in core.glob("*.py")}
    assert top == CORE_TOP and len(top) <= 10, sorted(top)
    packages = {path.parent.name for path in core.glob("*/__init__.py")}
    assert packages == set(CORE_STAGES) | set(CORE_ABOVE), sorted(packages)
    for stage in CORE_STAGES:
        tree = ast.parse((core / stage / "__init__.py").read_text())
        assert ast.get_docstring(tree), f"{stage} says what it is"
        assert all(isinstance(node, ast.Expr) for node in tree.body), f"{stage}/__init__.py holds code"


def test_the_ros_side_shows_inputs_mapping_outputs_and_files() -> None:
    """convbki_ros groups the node's modules in inputs, mapping, outputs and files; a part
    imports only the parts below it (inputs < outputs < files < mapping) and never the node."""
    ros = REPO / "convbki_ros"
    assert {path.parent.name for path in ros.glob("*/__init__.py")} == set(ROS_PARTS) | {"tools"}
    for index, part in enumerate(ROS_PARTS):
        forbidden = set(ROS_PARTS[index + 1:]) | ROS_NODE | {"tools"}
        for path in (ros / part).rglob("*.py"):
            used = {_part("convbki_ros", name) for name in _imports(path)} - {None}
            assert not used & forbidden, f"{path.relative_to(REPO)} imports {sorted(used & forbidden)}"


def test_no_module_of_the_project_is_over_24_kB() -> None:
    """Modules are split by responsibility before they grow past 24 kB (code and tests)."""
    large = {str(path.relative_to(REPO)): path.stat().st_size for path in _project_modules()
             if path.stat().st_size > MODULE_BYTES}
    assert not large, large


def test_the_library_imports_neither_ros_nor_its_own_programs() -> None:
    """The core never imports ROS or the ROS side; the core's library never imports its own
    programs (``convbki_core.tools``); the programs call the library, never the other way."""
    for path in (REPO / "convbki_core").rglob("*.py"):
        names = _imports(path)
        assert not any(name.split(".")[0] in ("rclpy", "convbki_ros") for name in names), path
        if "tools" not in path.relative_to(REPO).parts:
            assert not any(name.startswith("convbki_core.tools") for name in names), path


def test_the_core_tests_run_without_ros() -> None:
    """test/core and the helpers it uses import neither rclpy nor convbki_ros: the method's
    tests run where no ROS 2 is installed."""
    tests = REPO / "test"
    for path in [*(tests / "core").glob("*.py"), tests / "helpers.py", tests / "reference.py",
                 tests / "kitti_fixture.py", tests / "conftest.py"]:
        names = _imports(path)
        assert not any(name.split(".")[0] in ("rclpy", "convbki_ros", "ros_helpers", "mapper_rig")
                       for name in names), path


def test_the_architecture_drawing_matches_the_folders() -> None:
    """docs/architecture.md's drawing of the modules lists exactly the modules on disk (a
    package's ``__init__.py`` is implied by its folder line), so a newcomer can trust it."""
    text = (REPO / "docs" / "architecture.md").read_text()
    drawing = text.split("## Layout\n", 1)[1].split("```\n", 2)[1]
    drawn, folders = set(), []
    for line in drawing.splitlines():
        name = line.strip().split(" ")[0]
        depth = (len(line) - len(line.lstrip())) // 2
        folders = folders[:depth]
        if name.endswith("/"):
            folders.append(name.rstrip("/"))
            drawn.add("/".join([*folders, "__init__.py"]))
        elif name.endswith(".py"):
            drawn.add("/".join([*folders, name]))
    on_disk = {str(path.relative_to(REPO)) for package in ("convbki_core", "convbki_ros")
               for path in (REPO / package).rglob("*.py")}
    assert drawn == on_disk, {"not drawn": sorted(on_disk - drawn), "not on disk": sorted(drawn - on_disk)}


def _defined_names(module: str) -> set[str]:
    """The names a module defines at its top (functions, classes, assignments), read from its source."""
    path = REPO.joinpath(*module.split(".")).with_suffix(".py")
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(target.id for target in targets if isinstance(target, ast.Name))
    return names


def test_the_public_api_table_names_where_each_name_is_defined() -> None:
    """Each row of docs/architecture.md's public API table names a module that defines what it
    lists; a name said to be importable from ``convbki_core`` is in its table of public names."""
    import re

    text = (REPO / "docs" / "architecture.md").read_text()
    table = text.split("### The public Python API\n", 1)[1].split("\n\n", 2)[1]
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert len(rows) >= 10
    public = ast.literal_eval(re.search(r"_PUBLIC = (\{.*?\})", (REPO / "convbki_core" / "__init__.py").read_text(),
                                        re.S).group(1))
    for row in rows:
        names_cell, where = row.split("|")[1:3]
        names = re.findall(r"`(\w+)`", names_cell)
        modules = re.findall(r"`(convbki_core[\w.]*)`", where)
        defining = modules[-1]
        assert set(names) <= _defined_names(defining), row
        if modules[0] == "convbki_core":
            assert all(f"convbki_core.{public[name]}" == defining for name in names), row

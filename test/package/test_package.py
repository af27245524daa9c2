"""Packaging: the package builds with colcon as ``ros.ament_python`` and every executable
runs the way ``ros2 run convbki_ros <exe>`` runs it (through the ament index), and as
``python -m <module>``.

The package is copied into a temporary colcon workspace and built there with the colcon
next to this interpreter (the venv's), so the repo's own build/ and install/ are untouched.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import yaml
from ros_helpers import require_current_install

pytestmark = pytest.mark.package

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "convbki_ros"

# Every executable the package installs: exe -> (module, flags its --help must explain).
EXECUTABLES: dict[str, tuple[str, tuple[str, ...]]] = {
    "mapper": ("convbki_ros.main", ("--ros-args", "--params-file")),
    "kitti_to_bag": ("convbki_ros.tools.kitti_to_bag", (
        "--dataset", "--sequence", "--out", "--predictions-dir", "--probabilities-dir",
        "--frames", "--storage", "mcap", "sqlite3")),
    "play_bag": ("convbki_ros.tools.play_bag", ("BAG", "--rate", "--clock", "--remap")),
    "evaluate": ("convbki_core.tools.evaluate", (
        "--dataset", "--sequence", "--predictions-dir", "--probabilities-dir", "--kernel",
        "--frames", "--report", "--write-labels", "--save-map")),
    "train": ("convbki_core.tools.train", (
        "--dataset", "--sequences", "--kernel", "--out", "--frames-per-sample", "--epochs",
        "--lr")),
    "synth": ("convbki_core.tools.synth", ("--out", "--sequence", "--frames", "--seed")),
    "label_noise": ("convbki_core.tools.label_noise", (
        "--dataset", "--sequence", "--out", "--input-miou", "--seed", "--predictions-dir", "--frames")),
    "bench": ("convbki_core.tools.bench", ("--config", "--repeat", "--json")),
    "map_tool": ("convbki_core.tools.map_tool", (
        "info", "merge", "export-ply", "--json", "--out", "--force", "--max-variance", "--quiet")),
    "realtime_check": ("convbki_ros.tools.realtime_check", (
        "--frames", "--rate", "--publish-period", "--dataset", "--listeners", "--busy-cores",
        "--publication-mode")),
}

# The paper's SemanticKITTI set-up: the window around the sensor, and the grid (which the
# kernel file decides; the shipped kernels are trained for it). The node's other defaults are
# checked against its declarations (convbki_ros.params), not repeated here.
PAPER_WINDOW = [-40.0, -40.0, -2.6, 40.0, 40.0, 2.6]
PAPER_GRID = {"num_classes": 20, "resolution": 0.2, "filter_size": 5}

# Arguments that parse (used with a bad flag added).
VALID_ARGS = {
    "mapper": ["--ros-args", "--params-file", str(REPO / "config" / "mapper.yaml")],
    "kitti_to_bag": ["--dataset", "ds", "--sequence", "0", "--out", "bag"],
    "play_bag": ["bag"],
    "evaluate": ["--dataset", "ds", "--sequence", "8", "--report", "r.json"],
    "train": ["--dataset", "ds", "--sequences", "0", "--out", "k.yaml"],
    "synth": ["--out", "ds"],
    "label_noise": ["--dataset", "ds", "--sequence", "5", "--out", "o"],
    "bench": ["--repeat", "1"],
    "map_tool": ["info", "map.npz"],
    "realtime_check": ["--frames", "10", "--listeners", "map,variance", "--busy-cores", "1"],
}

# Top-level entries of the repo that are not part of the package source.
NOT_PACKAGE = {".venv", "build", "install", "log", ".git", "out", ".pytest_cache",
               ".hypothesis", "tmp"}

TIMEOUT = 120


def _colcon() -> str:
    """The colcon next to this interpreter (so scripts get this python's shebang)."""
    local = Path(sys.executable).parent / "colcon"
    found = str(local) if local.exists() else shutil.which("colcon")
    if found is None:
        pytest.skip("colcon is not installed (run `make setup`)")
    return found


def _ignore(directory: str, names: list[str]) -> set[str]:
    ignored = {n for n in names if n == "__pycache__" or n.endswith((".pyc", ".egg-info"))}
    if Path(directory).resolve() == REPO:
        ignored |= NOT_PACKAGE.intersection(names)
    return ignored


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A colcon workspace tmp/src/convbki_ros holding a copy of the package, built."""
    ws = tmp_path_factory.mktemp("ws")
    shutil.copytree(REPO, ws / "src" / PACKAGE, ignore=_ignore, symlinks=True)
    # The kernels' compilation at install (a minute) is checked on the repo's own install/, which
    # `make setup` builds with the same colcon command.
    env = dict(os.environ, COLCON_HOME=str(ws / ".colcon"), CONVBKI_SKIP_WARM_UP="1")
    build = subprocess.run(
        [_colcon(), "build", "--base-paths", "src"], cwd=ws, env=env,
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert build.returncode == 0, f"colcon build failed:\n{build.stdout}\n{build.stderr}"
    return ws


@pytest.fixture(scope="module")
def ros_env(workspace: Path) -> dict[str, str]:
    """The environment `source install/setup.bash` gives: ament index and PYTHONPATH."""
    prefix = workspace / "install" / PACKAGE
    site = sysconfig.get_path("purelib", vars={"base": str(prefix), "platbase": str(prefix)})
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(
        [str(prefix)] + [p for p in [os.environ.get("AMENT_PREFIX_PATH", "")] if p])
    env["PYTHONPATH"] = os.pathsep.join(
        [site] + [p for p in [os.environ.get("PYTHONPATH", "")] if p])
    return env


def _ros_run(env: dict[str, str], cwd: Path, exe: str, *args: str) -> subprocess.CompletedProcess:
    """What `ros2 run convbki_ros <exe>` does: look the package up on the ament index."""
    from ament_index_python.packages import get_package_prefix

    old = os.environ.get("AMENT_PREFIX_PATH")
    os.environ["AMENT_PREFIX_PATH"] = env["AMENT_PREFIX_PATH"]
    try:
        prefix = Path(get_package_prefix(PACKAGE))
    finally:
        if old is None:
            del os.environ["AMENT_PREFIX_PATH"]
        else:
            os.environ["AMENT_PREFIX_PATH"] = old
    return subprocess.run(
        [str(prefix / "lib" / PACKAGE / exe), *args], cwd=cwd, env=env,
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=TIMEOUT,
    )


def test_colcon_identifies_ament_python(tmp_path: Path) -> None:
    out = subprocess.run(
        [_colcon(), "--log-base", os.devnull, "list", "--base-paths", str(REPO)],
        cwd=tmp_path, env=dict(os.environ, COLCON_HOME=str(tmp_path)),
        capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=TIMEOUT,
    )
    assert out.returncode == 0, out.stderr
    name, _, kind = out.stdout.split("\t")[:3] if "\t" in out.stdout else ("", "", "")
    assert (name, kind.strip()) == (PACKAGE, "(ros.ament_python)"), out.stdout


def test_ament_index_finds_installed_package(
    workspace: Path, ros_env: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    prefix = workspace / "install" / PACKAGE
    assert (prefix / "share/ament_index/resource_index/packages" / PACKAGE).is_file()
    monkeypatch.setenv("AMENT_PREFIX_PATH", ros_env["AMENT_PREFIX_PATH"])
    assert Path(get_package_prefix(PACKAGE)) == prefix
    share = Path(get_package_share_directory(PACKAGE))
    assert share == prefix / "share" / PACKAGE
    assert (share / "package.xml").read_text() == (REPO / "package.xml").read_text()
    for pattern in ("config/*.yaml", "config/kernels/*.yaml"):
        shipped = sorted(p.name for p in REPO.glob(pattern))
        installed = sorted(p.name for p in share.glob(pattern))
        assert installed == shipped, pattern
    assert "mapper.yaml" in [p.name for p in share.glob("config/*.yaml")]
    rviz = yaml.safe_load((share / "rviz" / "convbki.rviz").read_text())
    displays = {d["Name"]: d for d in rviz["Visualization Manager"]["Displays"]}
    # RViz shows the bounded view by default, so it stays interactive on a map of any size.
    assert displays["Semantic map (view)"]["Topic"]["Value"] == "/semantic_map/view"
    assert displays["Semantic map (view)"]["Enabled"] is True
    assert displays["Semantic map (view)"]["Color Transformer"] == "RGB8"
    assert displays["Whole map"]["Topic"]["Value"] == "/semantic_map" and displays["Whole map"]["Enabled"] is False
    assert displays["Variance"]["Topic"]["Value"] == "/semantic_map/variance"
    assert rviz["Visualization Manager"]["Global Options"]["Fixed Frame"] == "map"
    # colcon's install step compiled the installed copy's kernels into its cache: a node started
    # from that install is ready at once (the repo's install/, current with the sources).
    require_current_install()
    repo_site = sysconfig.get_path("purelib", vars={"base": str(REPO / "install" / PACKAGE),
                                                    "platbase": str(REPO / "install" / PACKAGE)})
    package = Path(repo_site) / "convbki_core"
    cached = {f"{path.parent.parent.name}.{path.name.split('.')[0]}" for path in package.glob("*/__pycache__/*.nbi")}
    assert {"inference.update", "geometry.volume", "free_space.ray_walk", "free_space.update", "memory.window",
            "memory.store", "outputs.records", "inference.statistics"} <= cached, cached

    # With the install sourced, the installed copy of the code is what imports.
    where = subprocess.run(
        [sys.executable, "-c", "import convbki_ros, convbki_core; "
         "print(convbki_ros.__file__); print(convbki_core.__file__)"],
        cwd=workspace, env=ros_env, capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert where.returncode == 0, where.stderr
    for line in where.stdout.split():
        assert Path(line).is_relative_to(prefix), where.stdout


def test_every_executable_installed(workspace: Path) -> None:
    libexec = workspace / "install" / PACKAGE / "lib" / PACKAGE
    for exe in EXECUTABLES:
        path = libexec / exe
        assert path.is_file(), f"{path} missing"
        assert os.access(path, os.X_OK), f"{path} is not executable"


@pytest.mark.parametrize("exe", sorted(EXECUTABLES))
def test_installed_executable_help(exe: str, ros_env: dict[str, str], tmp_path: Path) -> None:
    result = _ros_run(ros_env, tmp_path, exe, "--help")
    assert result.returncode == 0, result.stderr
    for flag in EXECUTABLES[exe][1]:
        assert flag in result.stdout, f"{exe} --help does not mention {flag}"
    if exe == "mapper":
        from convbki_ros.params import PARAMETERS

        for spec in PARAMETERS:
            assert spec.name in result.stdout, f"mapper --help does not explain parameter {spec.name}"


@pytest.mark.parametrize("exe", sorted(EXECUTABLES))
def test_installed_executable_rejects_bad_flag(
    exe: str, ros_env: dict[str, str], tmp_path: Path
) -> None:
    result = _ros_run(ros_env, tmp_path, exe, "--no-such-flag", *VALID_ARGS[exe])
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "--no-such-flag" in result.stderr.strip().splitlines()[-1]


# Arguments naming input that does not exist (or an output that cannot be written).
MISSING_INPUT = {
    "kitti_to_bag": ["--dataset", "nowhere", "--sequence", "0", "--out", "bag"],
    "play_bag": ["nowhere.bag"],
    "evaluate": ["--dataset", "nowhere", "--sequence", "8", "--report", "r.json"],
    "train": ["--dataset", "nowhere", "--sequences", "0", "--out", "k.yaml"],
    "synth": ["--out", "a_file"],
    "map_tool": ["info", "nowhere.npz"],
}


@pytest.mark.parametrize("exe", sorted(MISSING_INPUT))
def test_installed_executable_names_missing_input_in_one_line(
    exe: str, ros_env: dict[str, str], tmp_path: Path
) -> None:
    (tmp_path / "a_file").write_text("not a folder")
    result = _ros_run(ros_env, tmp_path, exe, *MISSING_INPUT[exe])
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{exe}: ") and ("nowhere" in last or "a_file" in last), result.stderr
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "k.yaml").exists() and not (tmp_path / "bag").exists()


# Each module run as `python -m <module> --help` runs it (runpy, the machinery of -m), one
# module after another in one interpreter: a process per module would import torch ten times.
_MODULE_HELP = """
import contextlib, io, json, runpy, sys
helps = {}
for module in sys.argv[1:]:
    sys.argv = [module, "--help"]
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_module(module, run_name="__main__", alter_sys=True)
        code = None
    except SystemExit as stop:
        code = stop.code
    helps[module] = (code, out.getvalue())
print(json.dumps(helps))
"""


def test_module_help(tmp_path: Path) -> None:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [env.get("PYTHONPATH")] if p])
    modules = [module for module, _ in EXECUTABLES.values()]
    result = subprocess.run(
        [sys.executable, "-c", _MODULE_HELP, *modules], cwd=tmp_path, env=env,
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert result.returncode == 0, result.stderr
    helps = json.loads(result.stdout.strip().splitlines()[-1])
    for module, flags in EXECUTABLES.values():
        code, text = helps[module]
        assert code in (0, None), f"python -m {module} --help exited {code}"
        for flag in flags:
            assert flag in text, f"python -m {module} --help does not mention {flag}"


def test_venv_runs_modules_from_any_directory(tmp_path: Path) -> None:
    """`make setup` puts the repo on the venv's import path (a .pth file)."""
    if Path(sys.prefix).resolve() != (REPO / ".venv").resolve():
        pytest.skip("not running in the repo's .venv")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run(
        [sys.executable, "-m", "convbki_ros.main", "--help"], cwd=tmp_path, env=env,
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert result.returncode == 0, result.stderr
    assert "usage: mapper" in result.stdout


def test_mapper_params_file_documents_every_declared_parameter() -> None:
    """config/mapper.yaml sets every parameter to its declared default, with the declared type (a
    ROS parameter declared as double rejects an int), except those it must leave unset: the
    kernel's grid (set, they would override the kernel file) and the optional sensor mount.
    Both are documented there as comments."""
    from convbki_ros.params import KERNEL_DECIDES as DECIDED
    from convbki_ros.params import NOT_SET, PARAMETERS

    text = (REPO / "config" / "mapper.yaml").read_text()
    params = yaml.safe_load(text)["/**"]["ros__parameters"]
    declared = {spec.name: spec.default for spec in PARAMETERS}
    left_unset = {name for name, default in declared.items() if default is NOT_SET} | set(DECIDED)
    assert set(DECIDED) == set(PAPER_GRID)
    assert set(params) == set(declared) - left_unset
    for name in left_unset:
        assert f"# {name}: " in text, f"config/mapper.yaml does not document {name}"
    for name, value in params.items():
        assert value == declared[name] and type(value) is type(declared[name]), name
        if isinstance(value, list):
            assert all(type(v) is float for v in value), name


def test_mapper_defaults_are_the_papers() -> None:
    """The node's declared defaults give the paper's set-up, and rclpy's own parser (the one
    --params-file uses) reads config/mapper.yaml as exactly those declared defaults."""
    from rclpy.parameter import parameter_dict_from_yaml_file, parameter_value_to_python

    from convbki_core.io.kernel_file import load_kernel_file
    from convbki_core.paths import kernel_path
    from convbki_ros.params import KERNEL_DECIDES, NOT_SET, SPECS, kernel_defaults

    assert SPECS["local_bounds"].default == PAPER_WINDOW
    assert SPECS["kernel_file"].default == ""  # "" = the shipped compound kernel
    assert kernel_defaults(load_kernel_file(kernel_path("semantic_kitti_compound"))) == PAPER_GRID
    # Without a kernel to say otherwise, the declared grid is the paper's too.
    assert {name: SPECS[name].default for name in KERNEL_DECIDES} == PAPER_GRID

    parsed = parameter_dict_from_yaml_file(str(REPO / "config" / "mapper.yaml"), use_wildcard=True)
    values = {name: parameter_value_to_python(parameter.value) for name, parameter in parsed.items()}
    expected = {name: spec.default for name, spec in SPECS.items()
                if spec.default is not NOT_SET and name not in KERNEL_DECIDES}
    assert values == expected
    assert all(type(values[name]) is type(default) for name, default in expected.items())


def test_node_reference_documents_every_parameter() -> None:
    from convbki_ros.params import PARAMETERS

    text = (REPO / "docs" / "node.md").read_text()
    rows = {line.split("|")[1].strip().strip("`") for line in text.splitlines() if line.startswith("| `")}
    assert {spec.name for spec in PARAMETERS} <= rows


def test_every_drop_reason_of_the_node_is_documented() -> None:
    """The reasons the node counts drops by (``dropped.<reason>`` on /diagnostics, the counters
    line and the drop warnings) are the ones docs/node.md lists: every reason the code passes to
    ``MapperStatus.drop``, as a literal or through a constant, is in the docs' list."""
    import ast

    from convbki_ros.inputs import sync
    from convbki_ros.mapping import intake, update_thread

    reasons = set(update_thread.DROP_REASONS.values()) | {sync.NO_MOUNT, sync.NO_MAP_TRANSFORM}
    for module in (intake, update_thread):
        for node in ast.walk(ast.parse(Path(module.__file__).read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "drop" and node.args \
                    and isinstance(node.args[0], ast.Constant):
                reasons.add(node.args[0].value)
    docs = (REPO / "docs" / "node.md").read_text()
    row = next(line for line in docs.splitlines() if line.startswith("| `dropped.<reason>` |"))
    listed = set(row.split("|")[2].split(":", 1)[1].replace("`", "").replace(" ", "").split(","))
    assert {reason.replace(" ", "") for reason in reasons} <= listed, sorted(reasons)
    assert len(reasons) >= 14


def test_every_program_takes_its_mapping_defaults_from_one_configuration() -> None:
    """One set of defaults (``MapperConfig``): the node's declared parameters, the shipped
    parameters file, ``evaluate``'s and ``train``'s flags and a mapper built without settings
    all say the same, so the programs' figures are the node's map."""
    from convbki_core.config import DEFAULTS, MapperConfig
    from convbki_core.mapper import ConvBKIMapper
    from convbki_core.tools import evaluate, train
    from convbki_ros.params import SPECS

    flat = DEFAULTS.flat()
    for name in ("prior", "free_space", "max_concentration", "forget_movers", "device", "update_path",
                 "kernel_file"):
        assert SPECS[name].default == flat[name], name
    assert SPECS["local_bounds"].default == [*flat["local_bounds"][0], *flat["local_bounds"][1]]
    assert MapperConfig.from_params_file(REPO / "config" / "mapper.yaml") == DEFAULTS
    args = evaluate.build_parser().parse_args(["--dataset", "D", "--sequence", "08", "--report", "R.json"])
    assert (args.free_space, args.max_concentration, args.forget_movers, args.prior, args.device, args.update_path) == (
        flat["free_space"], flat["max_concentration"], flat["forget_movers"], flat["prior"], flat["device"],
        flat["update_path"])
    train_args = train.build_parser().parse_args(["--dataset", "D", "--sequences", "08", "--out", "k.yaml"])
    assert train_args.device == flat["device"]
    mapper = ConvBKIMapper(DEFAULTS.replace(device="cpu", local_bounds=((-2, -2, -1), (2, 2, 1))))
    assert mapper.free_space and mapper.max_concentration == flat["max_concentration"]
    assert mapper.forgetting is not None and mapper.prior == flat["prior"]


def test_console_scripts_are_the_tools_and_nothing_re_exports_them() -> None:
    """setup.py installs exactly the executables above from their modules, and no module outside
    a ``tools`` package re-exports a tool (one import path per executable)."""
    text = (REPO / "setup.py").read_text()
    scripts = dict(line.strip().strip('",').split(" = ") for line in text.split('"console_scripts": [')[1]
                   .split("]")[0].strip().splitlines())
    assert scripts == {exe: f"{module}:main" for exe, (module, _) in EXECUTABLES.items()}
    for package in ("convbki_core", "convbki_ros"):
        for path in (REPO / package).rglob("*.py"):
            if "tools" not in path.relative_to(REPO).parts:
                source = path.read_text()
                assert ".tools." not in source or "import *" not in source, f"{path} re-exports a tool"


def test_parameters_are_listed_under_the_same_headings_everywhere() -> None:
    """Every parameter is under one heading of ``PARAMETER_GROUPS``, and config/mapper.yaml
    and docs/node.md list them under those headings, in that order."""
    from convbki_ros.params import PARAMETER_GROUPS, SPECS

    grouped = [name for _, names in PARAMETER_GROUPS for name in names]
    assert sorted(grouped) == sorted(SPECS)
    yaml_text = (REPO / "config" / "mapper.yaml").read_text()
    docs = (REPO / "docs" / "node.md").read_text()
    for title, names in PARAMETER_GROUPS:
        yaml_section = yaml_text.split(f"    # === {title} ===\n")[1].split("    # === ")[0]
        listed = [line.split(":")[0].strip(" #") for line in yaml_section.splitlines()
                  if line.strip(" #").split(":")[0] in SPECS and ":" in line]
        assert listed == list(names), title
        docs_section = docs.split(f"### {title}\n")[1].split("\n### ")[0]
        rows = [line.split("|")[1].strip().strip("`") for line in docs_section.splitlines() if line.startswith("| `")]
        assert rows == list(names), title

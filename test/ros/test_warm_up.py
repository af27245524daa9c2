"""Compiled kernels on any install: the warm-up compiles everything mapping runs, and the
package imports and starts where neither its own folder nor the home folder can be written."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# In a fresh interpreter: warm up a mapper set up as the node sets it up, count every compiled
# signature of every kernel, then map scans the way the node does (PointCloud2 in, decoded,
# labels and probabilities, window moves, outputs, a save) and count again.
NOTHING_NEW = r"""
import json, sys, tempfile, warnings
import numpy as np
import numba
from numba.core.errors import NumbaWarning

warnings.simplefilter("error", NumbaWarning)  # e.g. a kernel that cannot be cached: every start would compile it
from convbki_core.config import MapperConfig
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_core.outputs.records import change_records, packed_palette, view_records
from convbki_core.outputs.shown_map import ShownMap
from convbki_core.warm_up import warm_up
from convbki_core.costmap.profile import load_profile
from convbki_core.costmap.window_pass import grid_of_window
from convbki_core.paths import traversability_profile
from convbki_ros.outputs.cloud_encoding import encode_cloud
from convbki_ros.inputs.cloud_decoding import decode_cloud

def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("convbki_core") and not name.startswith("convbki_core.synth"):
            for attribute, value in vars(module).items():
                if isinstance(value, numba.core.dispatcher.Dispatcher):
                    found[f"{name}.{attribute}"] = len(value.signatures)
    return found

labels = load_label_map("semantic_kitti")
config = MapperConfig.paper(local_bounds=((-20, -20, -2.6), (20, 20, 2.6)), device="cpu",
                            ignore_classes=labels.ignore_classes, track_changes=True, free_space=True,
                            max_concentration=300.0)
mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
costmap_profile = load_profile(traversability_profile("car"), labels.class_names)
report = warm_up(mapper)
before = signatures()
rng = np.random.default_rng(1)
palette = packed_palette(labels.colors)
shown = ShownMap()
for scan in range(6):
    points = rng.uniform([-15, -15, -2], [15, 15, 1], (3000, 3)).astype(np.float32)
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "intensity": np.ones(3000, np.float32)}
    if scan % 2:
        columns["label"] = labels.to_raw(rng.integers(1, 20, 3000)).astype(np.uint32)
    else:
        rows = rng.uniform(0, 1, (3000, 20)).astype(np.float32)
        columns.update({f"prob_{c}": rows[:, c] for c in range(20)})
    cloud = decode_cloud(encode_cloud(scan, "velo_link", columns), 20)
    values = cloud.probabilities if cloud.probabilities is not None else labels.to_learning(cloud.labels)
    pose = np.eye(4)
    pose[:3, 3] = [1.7 * scan, 0.4 * scan, 0.1]
    mapper.integrate(cloud.points, values, pose)
    changes = mapper.take_changes()
    records = change_records(changes.removed, changes.indices, changes.alpha, mapper.resolution, palette, 0.0)
    shown.apply(np.concatenate([changes.removed, changes.indices]), records)
    view_records(mapper.window_records(palette), pose[:3, 3], 30.0, 600000)
    grid_of_window(mapper.window, mapper.resolution, costmap_profile, mapper.prior)  # the node's costmap
mapper.labels_at(points)
mapper.forget_box((-1, -1, -1), (1, 1, 1))
with tempfile.TemporaryDirectory() as folder:
    mapper.snapshot().write(folder + "/map.npz")
    mapper.load(folder + "/map.npz")
    mapper.take_changes()
after = signatures()
print(json.dumps({"seconds": report.seconds, "kernels": len(before),
                  "new": {name: after[name] - before.get(name, 0) for name in after
                          if after[name] != before.get(name, 0)}}))
"""


def test_after_the_warm_up_mapping_like_the_node_compiles_nothing():
    result = subprocess.run([sys.executable, "-c", NOTHING_NEW], capture_output=True, text=True, cwd=REPO,
                            stdin=subprocess.DEVNULL, timeout=600)
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout.strip().splitlines()[-1])
    assert outcome["kernels"] >= 20, outcome  # every module with kernels was imported
    assert outcome["new"] == {}, f"compiled after the warm-up: {outcome['new']}"


READ_ONLY_CHECK = r"""
import json
from convbki_core.compiled import kernel_cache
from convbki_core.inference.statistics import dirichlet_statistics
import numpy as np
stats = dirichlet_statistics(np.array([[1.0, 3.0], [2.0, 1.0]], np.float32))  # a compiled kernel runs
cache = kernel_cache()
print(json.dumps({"folder": cache.folder, "note": cache.note, "label": stats.label.tolist()}))
"""



# Root writes into read-only folders through two capabilities; without them (still uid 0) the
# checks meet read-only files as any user would.
WITHOUT_PERMISSION_OVERRIDE = ("setpriv", "--bounding-set", "-dac_override,-dac_read_search")
NEEDS_SETPRIV = pytest.mark.skipif(os.geteuid() == 0 and not shutil.which("setpriv"),
                                   reason="root writes into read-only folders, and setpriv is not here to stop that")


def _set_modes(folder: Path, writable: bool) -> None:
    for path in [folder, *folder.rglob("*")]:
        path.chmod((0o755 if path.is_dir() else 0o644) if writable else (0o555 if path.is_dir() else 0o444))


@pytest.fixture
def read_only_install(tmp_path):
    """(site, home): the two packages as an install lays them out and a home folder, all read-only."""
    site = tmp_path / "site-packages"
    for package in ("convbki_core", "convbki_ros"):
        shutil.copytree(REPO / package, site / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "config", site / "config")  # what the packages find beside a source tree
    home = tmp_path / "home"
    home.mkdir()
    for folder in (site, home):
        _set_modes(folder, writable=False)
    yield site, home
    for folder in (site, home):
        _set_modes(folder, writable=True)


def _run(site: Path, home: Path, *command: str, **environment: str) -> subprocess.CompletedProcess:
    """``python command`` without the right to write where the files say it may not."""
    prefix = WITHOUT_PERMISSION_OVERRIDE if os.geteuid() == 0 else ()
    env = {"PATH": os.environ["PATH"], "HOME": str(home), "PYTHONPATH": str(site), "PYTHONDONTWRITEBYTECODE": "1",
           **environment}
    return subprocess.run([*prefix, sys.executable, *command], cwd=site, env=env, capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, timeout=300)


@NEEDS_SETPRIV
def test_import_and_help_on_a_read_only_install_with_no_writable_home(tmp_path, read_only_install):
    site, home = read_only_install
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    help_run = _run(site, home, "-m", "convbki_ros.main", "--help", TMPDIR=str(temporary))
    assert help_run.returncode == 0 and "ROS 2 node convbki_mapper" in help_run.stdout, help_run.stderr
    assert help_run.stderr == "", help_run.stderr
    check = _run(site, home, "-c", READ_ONLY_CHECK, TMPDIR=str(temporary))
    assert check.returncode == 0, check.stderr
    outcome = json.loads(check.stdout)
    fallback = temporary / f"convbki_ros-kernels-{os.geteuid()}"
    assert outcome["label"] == [1, 0] and outcome["folder"] == str(fallback), outcome
    assert f"cached in {fallback}" in outcome["note"] and "set NUMBA_CACHE_DIR" in outcome["note"], outcome
    assert any(fallback.rglob("*.nbi")), "nothing was cached there"
    assert not any(site.rglob("__pycache__")) and not any(home.iterdir())


@NEEDS_SETPRIV
def test_with_nowhere_to_cache_the_kernels_compile_and_say_so(tmp_path, read_only_install):
    """No writable package folder, home or temporary folder: the kernels compile at every start."""
    site, home = read_only_install
    read_only_temporary = tmp_path / "tmp"
    read_only_temporary.mkdir(mode=0o555)
    # The temporary folder Python would use, set before the package is imported: read-only too.
    check = f"import tempfile\ntempfile.tempdir = {str(read_only_temporary)!r}\n" + READ_ONLY_CHECK
    try:
        run = _run(site, home, "-c", check)
        assert run.returncode == 0, run.stderr
        outcome = json.loads(run.stdout)
        assert outcome["label"] == [1, 0] and outcome["folder"] is None, outcome
        assert "every start compiles the kernels again" in outcome["note"], outcome
        assert not any(read_only_temporary.iterdir()) and not any(site.rglob("__pycache__"))
    finally:
        read_only_temporary.chmod(0o755)


# In a fresh interpreter where no temporary folder can be made: the warm-up, then a scan mapped,
# then the file steps the warm-up had to leave out, each followed by a count of the kernels.
NO_TEMPORARY_FOLDER = r"""
import json, sys, tempfile
import numpy as np
import numba

def no_folder(*args, **kwargs):
    raise PermissionError(13, "Permission denied")

tempfile.TemporaryDirectory = no_folder
from convbki_core import warm_up as module
from convbki_core.config import MapperConfig
from convbki_core.mapper import ConvBKIMapper

def signatures():
    found = {}
    for name, module_ in list(sys.modules.items()):
        if name.startswith("convbki_core") and not name.startswith("convbki_core.synth"):
            for attribute, value in vars(module_).items():
                if isinstance(value, numba.core.dispatcher.Dispatcher) and value.signatures:
                    found[f"{name}.{attribute}"] = len(value.signatures)
    return found

def gained(before, after):
    return sorted(name for name in after if after[name] != before.get(name, 0))

with module._scratch_folder() as scratch:
    no_scratch = scratch is None
report = module.warm_up()
warmed = signatures()
mapper = ConvBKIMapper(MapperConfig().replace(device="cpu"))
rng = np.random.default_rng(2)
points = rng.uniform([-10, -10, -2], [10, 10, 1], (3000, 3)).astype(np.float32)
mapper.integrate(points, rng.integers(1, 20, 3000), np.eye(4))
mapped = signatures()
mapper.save(sys.argv[1] + "/map.npz")
mapper.load(sys.argv[1] + "/map.npz")
mapper.export_ply(sys.argv[1] + "/map.ply")
print(json.dumps({"no_scratch": no_scratch, "seconds": report.seconds, "warmed": sorted(warmed),
                  "mapping": gained(warmed, mapped),
                  "files": gained(mapped, signatures())}))
"""


def test_the_warm_up_runs_where_no_temporary_folder_can_be_made(tmp_path):
    """A read-only system: the warm-up leaves out its file steps (it has nowhere to write) and
    still compiles every kernel: mapping a scan, then a save, a load and a PLY compile nothing
    (the file steps run the kernels the mapping steps brought)."""
    result = subprocess.run([sys.executable, "-c", NO_TEMPORARY_FOLDER, str(tmp_path)], capture_output=True,
                            text=True, cwd=REPO, stdin=subprocess.DEVNULL, timeout=600)
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout.strip().splitlines()[-1])
    modules = {name.rsplit(".", 1)[0] for name in outcome["warmed"]}
    assert {"convbki_core.inference.update", "convbki_core.free_space.update", "convbki_core.memory.window",
            "convbki_core.memory.column_classes", "convbki_core.memory.store", "convbki_core.costmap.columns",
            "convbki_core.costmap.window_pass", "convbki_core.outputs.records",
    } <= modules, modules
    assert outcome["no_scratch"] and len(outcome["warmed"]) >= 20, outcome
    assert outcome["mapping"] == [] and outcome["files"] == [], outcome

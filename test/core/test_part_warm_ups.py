"""Each part of a mapper owns its warm-up: run on a scratch window, it compiles its own kernels
(and only then are they there), the mapper's map is not touched, and after all of them mapping
scans of every kind of input compiles nothing more in the parts' modules."""

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# In a fresh interpreter: which compiled kernels each part's warm-up brings, module by module,
# then what mapping four kinds of scans adds after all of them.
SCRIPT = r"""
import json, sys
import numpy as np
import numba
from convbki_core.config import MapperConfig
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.parts import Scratch
from convbki_core.paths import kernel_path

# Every compiled kernel of every loaded convbki_core module: "stage.module:kernel" -> signatures.
def signatures():
    found = {}
    for module_name, module in list(sys.modules.items()):
        if module_name.startswith("convbki_core.") and module is not None:
            for attribute, value in vars(module).items():
                if isinstance(value, numba.core.dispatcher.Dispatcher) and value.__module__ == module_name:
                    found[f"{module_name.removeprefix('convbki_core.')}:{attribute}"] = len(value.signatures)
    return found

def modules_gained(before, after):
    return sorted({name.split(":")[0] for name in after if after[name] > before.get(name, 0)})

labels = load_label_map("semantic_kitti")
config = MapperConfig.paper(local_bounds=((-12, -12, -2.6), (12, 12, 2.6)), device="cpu",
                            ignore_classes=labels.ignore_classes, movable_classes=labels.movable_classes,
                            ground_classes=labels.ground_classes, track_changes=True, free_space=True,
                            max_concentration=300.0)
mapper = ConvBKIMapper(config, kernel_path("semantic_kitti_compound"))
report = {"parts": {}}
for name in ("window", "voxelize", "update", "free", "forgetting"):
    before = signatures()
    getattr(mapper, name).warm_up(Scratch(mapper.resolution, mapper.num_classes, mapper.prior,
                                          mapper.ignore_classes, mapper.window))
    report["parts"][name] = modules_gained(before, signatures())
report["untouched"] = [len(mapper.store), mapper.window.count(), mapper.window.origin is None,
                       mapper.scans_integrated]
before = signatures()
rng = np.random.default_rng(1)
for scan in range(4):
    points = rng.uniform([-10, -10, -2], [10, 10, 1], (3000, 3))
    if scan == 1:
        points = points.astype(np.float32)
    if scan < 2:
        values = rng.integers(1, 20, 3000)
    else:
        values = rng.uniform(0, 1, (3000, 20)).astype(np.float32)
        values /= values.sum(axis=1, keepdims=True)
    mapper.kernel.temperature = 0.5 if scan == 3 else None
    pose = np.eye(4)
    pose[:3, 3] = [1.7 * scan, 0.4 * scan, 0.3 * scan]
    mapper.integrate(points, values, pose)
report["new"] = {name: count for name, count in signatures().items() if count != before.get(name, 0)}
report["mapped"] = len(mapper.voxels())
print(json.dumps(report))
"""


def test_each_part_compiles_its_own_kernels_on_a_scratch_window_and_then_mapping_compiles_nothing():
    result = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    parts = report["parts"]
    # The window's moves bring the window's, its column classes' and the store's kernels (slabs out
    # and back, the classes kept by column).
    assert {"memory.window", "memory.column_classes", "memory.store"} <= set(parts["window"]), parts
    assert parts["voxelize"] == ["geometry.volume"], parts
    assert parts["update"] == ["inference.update"], parts
    # The rays' modules: the scan's rays, their walk, the update and the ground's surface.
    assert {"free_space.scan_rays", "free_space.ray_walk", "free_space.update", "free_space.ground"} <= set(
        parts["free"]), parts
    assert parts["forgetting"] == ["free_space.host_forgetting"], parts
    assert report["untouched"] == [0, 0, True, 0], report["untouched"]
    assert report["new"] == {}, report["new"]
    assert report["mapped"] > 1000, report


def test_the_parts_are_compiled_aside_only_when_the_cache_lacks_their_kernels(tmp_path):
    """The warm-up compiles free space and the movers' rules in a second process only when the
    cache lacks their kernels. After a warm-up every module compiled aside is found cached (numba
    keeps each stage's kernels beside that stage's modules); in an empty cache folder none is."""
    check = "from convbki_core import warm_up as w; {}print(w.aside_parts_cached())"
    warm = subprocess.run([sys.executable, "-c", check.format("w.warm_up(); ")], cwd=REPO, capture_output=True,
                          text=True, timeout=600)
    cold = subprocess.run([sys.executable, "-c", check.format("")], cwd=REPO, capture_output=True, text=True,
                          timeout=600, env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert warm.returncode == 0 and warm.stdout.split()[-1] == "True", warm.stderr
    assert cold.returncode == 0 and cold.stdout.split()[-1] == "False", cold.stderr

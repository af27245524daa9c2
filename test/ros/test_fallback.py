"""Without numba (no compiler wheel for the platform) the mapper still works, says so once, and agrees
(labels, and probabilities calibrated by a temperature)."""

import json
import subprocess
import sys

import numpy as np
from ros_helpers import REPO

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.paths import kernel_path

BOUNDS = ((-6.0, -6.0, -2.0), (6.0, 6.0, 2.0))

# Maps three scans in a fresh interpreter where `import numba` fails, prints the map as JSON.
SCRIPT = """
import json, sys
sys.modules["numba"] = None  # what a platform without numba looks like to `import numba`
import numpy as np
from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.compiled import HAVE_NUMBA
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.paths import kernel_path
rng = np.random.default_rng(4)
config = load_kernel_file(kernel_path("semantic_kitti_compound"))
config.temperature = 0.45
mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS_HERE, device="cpu"), config)
for step in range(4):
    pose = np.eye(4)
    pose[:3, 3] = [0.7 * step, 0.2 * step, 0.0]
    values = rng.integers(0, 20, 800) if step < 3 else rng.dirichlet(np.full(20, 0.3), 800).astype(np.float32)
    mapper.integrate(rng.uniform(-5, 5, (800, 3)), values, pose)
indices, alpha = mapper.items()
print(json.dumps({"have_numba": HAVE_NUMBA, "indices": indices.tolist(), "alpha": alpha.tolist()}))
""".replace("BOUNDS_HERE", repr(BOUNDS))


def test_without_numba_the_numpy_path_maps_the_same_and_logs_one_line():
    result = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    fallback = json.loads(result.stdout)
    assert fallback["have_numba"] is False
    warnings = [line for line in result.stderr.splitlines() if "numba" in line]
    assert len(warnings) == 1 and "slower" in warnings[0], result.stderr
    assert "Traceback" not in result.stderr

    rng = np.random.default_rng(4)
    config = load_kernel_file(kernel_path("semantic_kitti_compound"))
    config.temperature = 0.45  # the last scan's probabilities are calibrated by it on both paths
    compiled = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"), config)
    for step in range(4):
        pose = np.eye(4)
        pose[:3, 3] = [0.7 * step, 0.2 * step, 0.0]
        values = rng.integers(0, 20, 800) if step < 3 else rng.dirichlet(np.full(20, 0.3), 800).astype(np.float32)
        compiled.integrate(rng.uniform(-5, 5, (800, 3)), values, pose)
    indices, alpha = compiled.items()
    want = {tuple(i): a for i, a in zip(indices.tolist(), alpha)}
    got = {tuple(i): np.asarray(a, np.float32) for i, a in zip(fallback["indices"], fallback["alpha"])}
    assert len(want) > 1000 and set(got) == set(want)
    for key, value in want.items():
        np.testing.assert_allclose(got[key], value, rtol=1e-5)

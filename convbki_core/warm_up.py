"""Compile every kernel a mapper and its outputs will run before the first scan arrives.

numba compiles a kernel at its first call, once per combination of argument types (or
loads the machine code from its cache, which also takes a moment). A node that said
"ready" and then compiled on its first scans would fall seconds behind a 10 Hz LiDAR and
drop what queued meanwhile. ``warm_up`` therefore builds a throwaway mapper with the same
kernel, classes, prior, update path and device on a small window, with free space, clamping
and the movers' rules on (the node can turn them on at run time), and

1. lets each of its parts warm itself up (``ConvBKIMapper.warm_up``: the window, the
   voxeliser with every kind of input, the update backend, the free-space backend and the
   movers' rules, each on a scratch window of its own);
2. drives it through what the node's outputs and files call on a mapper: a few scans and
   window moves, the map's changes, statistics and point records, the shown map, the
   planner's costmap, queries inside and outside the window, a forgotten box, a save to a
   temporary file, its load and a PLY export.

With a cold cache the kernels of free space and the movers' rules (about half of the
compilation, which numba does on one core) are compiled in a second process meanwhile, while
this one compiles the rest on a mapper without them; then the whole run above loads them
from the cache. With a warm cache nothing is started.

The mapper itself is not touched; ``warm_up(config, kernel)`` takes the mapper's
configuration instead, so that it can run while that mapper allocates its window (a third of
a gigabyte at the paper's grid, which numpy fills without holding the GIL). On a GPU the same
run also loads the device's kernels, as nvblox warms CUDA up before it builds its node.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from convbki_core.compiled import KernelCache, kernel_cache, threading_layer
from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.costmap.columns import column_costs
from convbki_core.costmap.profile import TraversabilityProfile
from convbki_core.costmap.window_pass import grid_of_window, window_grid
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.io.map_file import read_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.memory.column_classes import classes_held
from convbki_core.memory.window import EVIDENCE
from convbki_core.outputs.records import change_records, packed_palette, view_records
from convbki_core.outputs.shown_map import ShownMap
from convbki_core.parts import Scratch

# The throwaway window: big enough for a filter of up to 31 voxels and a few moves.
HALF_EXTENT = (3.2, 3.2, 1.2)  # metres at 0.2 m; scaled with the resolution


@dataclass(frozen=True)
class WarmUpReport:
    """How long the warm-up took, where the compiled kernels are kept, and numba's threading layer."""

    seconds: float
    cache: KernelCache
    threading_layer: str | None

    def line(self) -> str:
        where = f"cached in {self.cache.place}" if self.cache.folder else "not cached"
        layer = f", threading layer {self.threading_layer}" if self.threading_layer else ""
        return f"compiled kernels ready in {self.seconds:.1f} s ({where}{layer})"


def _scene(rng: np.random.Generator, resolution: float, shift: float) -> np.ndarray:
    """A ground patch, a wall and a box in the sensor frame (m), inside the throwaway window."""
    scale = resolution / 0.2
    ground = np.column_stack([rng.uniform(-2.5, 2.5, (300, 2)) * scale, np.full(300, -0.9 * scale)])
    wall = np.column_stack([np.full(120, (1.6 + shift) * scale), rng.uniform(-2.0, 2.0, 120) * scale,
                            rng.uniform(-0.9, 0.9, 120) * scale])
    box = rng.uniform([-1.5, -1.5, -0.8], [-0.5, -0.5, 0.2], (80, 3)) * scale
    return np.concatenate([ground, wall, box])


def _labels(rng: np.random.Generator, count: int, num_classes: int, ignored: tuple[int, ...]) -> np.ndarray:
    usable = [c for c in range(num_classes) if c not in ignored] or [0]
    return rng.choice(np.asarray(usable, np.int64), count)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = [x, y, 0.0]
    return pose


def throwaway_mapper(config: MapperConfig, kernel, rules: bool = True) -> ConvBKIMapper:
    """A mapper like one made from ``config`` and ``kernel`` (its kernel, grid, prior, device and
    update path) on a small window, with free space, clamping and the movers' rules on, so
    that their kernels are compiled whatever the configuration says (``rules`` False: off)."""
    if kernel is None:
        kernel = config.kernel_path()
    if isinstance(kernel, (str, Path)):
        kernel = load_kernel_file(kernel)
    resolution = config.window.resolution or kernel.resolution
    half = np.asarray(HALF_EXTENT) * resolution / 0.2
    ignored = tuple(sorted({FREE_CLASS, *config.ignore_classes()}))
    movable = config.classes.movable_classes or (min(1, kernel.num_classes - 1),)
    small = config.replace(local_bounds=(tuple(-half), tuple(half)), ignore_classes=ignored, track_changes=True,
                           free_space=rules, max_concentration=1.0, forget_movers=rules, movable_classes=movable)
    return ConvBKIMapper(small, kernel)


# The parts compiled aside when the cache is cold: the modules that hold their kernels.
_ASIDE_MODULES = ("convbki_core.free_space.scan_rays", "convbki_core.free_space.ray_walk",
                  "convbki_core.free_space.update", "convbki_core.free_space.ground",
                  "convbki_core.free_space.host_forgetting")


def aside_parts_cached() -> bool:
    """Whether numba's cache holds the kernels of every module compiled aside. numba keeps a
    module's kernels beside it, or in a folder of its own under ``NUMBA_CACHE_DIR``: each
    module's own compiled functions say where (``cache_path``)."""
    from importlib import import_module

    from numba.core.dispatcher import Dispatcher

    for name in _ASIDE_MODULES:
        module = import_module(name)
        folders = {Path(value._cache.cache_path) for value in vars(module).values()
                   if isinstance(value, Dispatcher) and value.__module__ == name}
        stem = name.rsplit(".", 1)[1]
        if not folders or not all(any(folder.glob(f"{stem}.*.nbi")) for folder in folders):
            return False
    return True


def _compile_aside(config: MapperConfig, kernel) -> subprocess.Popen | None:
    """A process that compiles the free-space and movers' kernels into the cache
    (``warm_parts_aside``), or None: the cache is off or already holds them, or the
    configuration cannot be handed over."""
    folder = kernel_cache().folder
    if folder is None or aside_parts_cached():
        return None
    try:
        payload = pickle.dumps((config, kernel))
    except Exception:  # a kernel object that does not pickle: this process compiles everything
        return None
    from numba.core import config as numba_config

    environment = dict(os.environ)
    if numba_config.CACHE_DIR:  # the folder this process chose, where numba's own order would not find it
        environment["NUMBA_CACHE_DIR"] = numba_config.CACHE_DIR
    try:
        child = subprocess.Popen([sys.executable, "-c", "import convbki_core.warm_up as w; w.warm_parts_aside()"],
                                 stdin=subprocess.PIPE, env=environment)
        child.stdin.write(payload)
        child.stdin.close()
    except OSError:
        return None
    return child


def warm_parts_aside() -> None:
    """In the process ``_compile_aside`` starts: compile free space and the movers' rules of
    the (configuration, kernel) pickled on standard input."""
    # Ctrl-C in a terminal reaches the whole process group: the process that started this one
    # stops it, and this one must not print a traceback of its own meanwhile.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    config, kernel = pickle.loads(sys.stdin.buffer.read())
    mapper = throwaway_mapper(config, kernel)
    scratch = Scratch(mapper.resolution, mapper.num_classes, mapper.prior, mapper.ignore_classes, mapper.window)
    for part in (mapper.free, mapper.forgetting):
        if part is not None:
            part.warm_up(scratch)


def _hidden_ground(classes: int, resolution: float, prior: float, profile: TraversabilityProfile) -> None:
    """The costmap's passes for a column whose ground is hidden (a car on the road), on a window
    and on the same voxels gathered: a drive's first grids may have none, and its later ones
    then compile them."""
    alpha = np.full((classes, 4, 4, 4), np.float32(prior), np.float32)
    mask = np.zeros((4, 4, 4), np.uint8)
    alpha[1, 0, 0, 0] += 10.0  # ground (the warm-up profile's class 1) in one column
    alpha[classes - 1, 1, 0, 1] += 10.0  # an obstacle over hidden ground next to it
    mask[0, 0, 0] = mask[1, 0, 1] = EVIDENCE
    window_grid(alpha, mask, np.zeros(3, np.int64), np.array([4, 4, 4]), resolution, profile, prior,
                classes_held(alpha, prior))
    voxels = np.array([[0, 0, 0], [1, 0, 1]])
    column_costs(voxels, alpha[:, voxels[:, 0], voxels[:, 1], voxels[:, 2]].T, resolution, profile, prior)


def _exercise(mapper: ConvBKIMapper, rng: np.random.Generator, folder: Path | None) -> None:
    """What a node's outputs and files call on a mapper, once (files in ``folder``; none: no
    temporary folder can be written, and the file steps are left out: they run only kernels the
    other steps bring, so nothing compiles at the first save or load either)."""
    resolution, classes = mapper.resolution, mapper.num_classes
    palette = packed_palette(np.zeros((classes, 3), np.uint8))
    step = 6 * resolution  # a window move of six slabs
    for number, (x, y, yaw) in enumerate([(0.0, 0.0, 0.0), (step, 0.0, 0.3), (step, step, -0.2), (0.0, 0.0, 0.1)]):
        points = _scene(rng, resolution, shift=-0.4 * (number % 2))
        mapper.integrate(points, _labels(rng, len(points), classes, mapper.ignore_classes), _pose(x, y, yaw))
    probe = _scene(rng, resolution, shift=0.0)
    mapper.labels_at(probe)
    mapper.labels_at(probe + step * 40, within_window=False)
    changes = mapper.take_changes()
    shown = ShownMap()
    records = change_records(changes.removed, changes.indices, changes.alpha, resolution, palette, 0.01)
    shown.apply(np.concatenate([changes.removed, changes.indices]), records)
    shown.records()
    window = mapper.window_records(palette)
    view_records(window, np.zeros(3), 2.0, max(1, len(window) // 2))
    mapper.voxels()
    mapper.local_voxels()
    profile = TraversabilityProfile("warm-up", np.linspace(0.0, 100.0, classes), (1,))
    grid_of_window(mapper.window, resolution, profile, mapper.prior)
    _hidden_ground(classes, resolution, mapper.prior, profile)
    column_costs(*mapper.items(), resolution, profile, mapper.prior)
    half = 2 * resolution
    forgotten = mapper.forget_box((-half, -half, -half), (half, half, half))
    changes = mapper.take_changes(everything=True)
    change_records(forgotten, changes.indices, changes.alpha, resolution, palette)
    if folder is not None:
        path = folder / "map.npz"
        mapper.save(path)
        read_map(path)
        mapper.load(path)
        mapper.take_changes()
        mapper.export_ply(folder / "map.ply")
    mapper.reset()


def warm_up(mapper: ConvBKIMapper | MapperConfig | None = None, kernel=None) -> WarmUpReport:
    """Compile (or load from the cache) every kernel a mapper and its outputs will run: the
    mapper given, or one made from a configuration (and ``kernel``: None, the configuration's
    kernel file), or (none) the product's defaults on the CPU."""
    started = time.perf_counter()
    if isinstance(mapper, ConvBKIMapper):
        config, kernel = mapper.config.replace(device=str(mapper.device), update_path=mapper.update_path), mapper.kernel
    else:
        config = mapper or DEFAULTS.replace(device="cpu")
        kernel = kernel if kernel is not None else config.kernel_path()
    aside = _compile_aside(config, kernel)
    try:
        if aside is not None:  # meanwhile the rest, on a mapper without free space and movers
            plain = throwaway_mapper(config, kernel, rules=False)
            plain.warm_up()
            with _scratch_folder() as folder:
                _exercise(plain, np.random.default_rng(0), folder)
            del plain
            aside.wait()  # whatever it did not finish, the run below compiles
        throwaway = throwaway_mapper(config, kernel)
        throwaway.warm_up()
        with _scratch_folder() as folder:
            _exercise(throwaway, np.random.default_rng(0), folder)
    finally:
        if aside is not None and aside.poll() is None:
            aside.kill()
            aside.wait()
    return WarmUpReport(time.perf_counter() - started, kernel_cache(), threading_layer())


@contextmanager
def _scratch_folder() -> Iterator[Path | None]:
    """A temporary folder for the warm-up's files; None where none can be made (a read-only system)."""
    try:
        scratch = tempfile.TemporaryDirectory(prefix="convbki_warm_up_")
    except OSError:
        yield None
        return
    with scratch as folder:
        yield Path(folder)

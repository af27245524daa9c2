"""``ConvBKIMapper``: the one mapping object shared by the ROS node, ``evaluate`` and ``bench``.

One scan goes through the paper's global-mapping steps (section "Global Mapping"):

1. voxelise the scan, moved into the map frame with its pose (any SE(3)), into the input
   volume F of the window around the sensor (Eq. 3; ``parts.Voxelizer``);
2. move the local window to the sensor: the window stays resident (``window.RollingWindow``),
   only the slabs that leave it go to the global store and those that enter come back
   (the paper's query and write-back; new voxels hold the prior);
3. apply the ConvBKI update alpha += conv3d(F, K) (Eq. 4) in place with the update backend
   the configuration chose (``parts``: the compiled sparse scatter on the CPU, a device
   window on CUDA, or the paper's dense depthwise convolution, the reference);
4. with free space, add the rays' evidence that the space they cross is empty
   (``parts.HostFreeSpace`` / ``DeviceFreeSpace``), after the movers' rules (``forgetting``).

The parts are built once, in the constructor, from the ``MapperConfig``.

The map's memory (``store.max_megabytes``, ``memory.budget``): with a budget, the global store
maps as an unbounded one until its bytes (with those it lent the window) reach the budget; then
the map is full and stops growing: the voxels leaving the window go back only into chunks the
store holds or lent (old ground keeps its map when the robot comes back), the others are dropped
and counted, and past a hard ceiling of ``CEILING_FACTOR`` x the budget nothing more is written.
Mapping in the window goes on as before. ``memory_state`` says where the map stands.

Public surface: ``integrate``, ``labels_at``, ``voxels``, ``local_voxels``, ``save``,
``load``, ``export_ply``, ``reset``, ``memory_state``.

This module holds the set-up and the update (``integrate``, ``withdraw``); the mapper's other
sides are mixins it inherits, each in the module of its part: reading the map and its changes
(``map_contents.MapContents``), its files (``io.mapper_files.MapFiles``) and a SLAM's
corrections (``correction.map_corrections.MapCorrections``). Mixins, not one-line delegates:
their methods read and write the mapper's own store, window, scan log and change bookkeeping,
and as methods of one class they stay where the node and the tools call them.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from convbki_core.config import DEFAULTS, UPDATE_PATHS, MapperConfig
from convbki_core.correction.map_corrections import MapCorrections
from convbki_core.correction.scan_log import LoggedScan, ScanLog
from convbki_core.devices import resolve_device
from convbki_core.free_space.clamping import check_limit
from convbki_core.free_space.forgetting import MoverForgetting
from convbki_core.free_space.present_movers import PresentMovers, present_movers, whole_movers
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.geometry.grid import WindowGeometry, check_pose, transform_points
from convbki_core.geometry.volume import VoxelizeStats, check_scan
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.inference.layer import ConvBKILayer
from convbki_core.io.kernel_file import KernelConfig, load_kernel_file
from convbki_core.io.mapper_files import MapFiles
from convbki_core.map_contents import MapContents
from convbki_core.memory.budget import MemoryState
from convbki_core.memory.column_classes import MAX_CLASS_BITS
from convbki_core.memory.store import VoxelStore
from convbki_core.memory.window import CHANGED, EVIDENCE, RECLASSED, TOUCHED, RollingWindow
from convbki_core.parts import KernelFilters, Scratch, Voxelizer, make_free_space, make_update
from convbki_core.torch_path.window import TorchWindow

# The hard ceiling of a bounded map, as a factor of its budget. A full map still writes back into
# the chunks it holds or lent: old ground gains the voxels and classes a revisit sees, so the store
# creeps past the budget by what the window adds to old ground (the window's own voxels, compact,
# are the most a single pass adds). A quarter of the budget is room for many revisits while memory
# stays within 25% of what was asked; a budget + window-footprint rule would instead allow the
# dense window's size again (333 MB at the defaults) whatever the budget. Past it nothing is written.
# (The synthetic drive at the defaults, full from scan 450 of 800: the store peaked 1.8% past its budget.)
CEILING_FACTOR = 1.25


@dataclass
class IntegrationResult:
    """What one ``integrate`` call did."""

    stats: VoxelizeStats
    window_origin: np.ndarray
    occupied_voxels: int = 0  # voxels of F with points
    new_voxels: int = 0  # voxels that received evidence for the first time
    freed_voxels: int = 0  # voxels whose free-space evidence grew (free space on)
    # Per stage (voxelize, query: the window move, update, free: free space and the movers' rules,
    # movers: the rules alone, log, total), ms.
    timing_ms: dict[str, float] = field(default_factory=dict)



class ConvBKIMapper(MapContents, MapFiles, MapCorrections):
    """Online ConvBKI semantic mapping in a global voxel map, set up by a ``MapperConfig``
    (``config``; the product's defaults when None).

    ``kernel``: a ``ConvBKIKernel`` (training passes the one it learns), a ``KernelConfig`` or
    a kernel-file path; None: the config's ``kernel_file``. The resolution and filter size
    come from the kernel unless the config sets them (lengths are in metres, so a kernel may
    be evaluated on another grid). With free space, the rays between the sensor and its
    returns add evidence that the voxels they cross are empty, into class 0 (``free_space``);
    class 0 must be ignored. Clamping (``max_concentration``) scales down a voxel that rays
    first find empty, so a bounded number of rays can empty what a mover left
    (``clamping``). The movers' rules (``forgetting``) make the movable classes' voxels
    forget where a return shows another class and where they float over empty space.
    """

    def __init__(self, config: MapperConfig | None = None,
                 kernel: ConvBKIKernel | KernelConfig | str | Path | None = None):
        config = DEFAULTS if config is None else config
        self.config = config
        if kernel is None:
            kernel = config.kernel_path()
        if isinstance(kernel, (str, Path)):
            kernel = load_kernel_file(kernel)
        # The mapper's own kernel: a caller's kernel object keeps its device and grid.
        kernel = ConvBKIKernel.from_config(kernel) if isinstance(kernel, KernelConfig) else copy.deepcopy(kernel)
        window, free = config.window, config.free_space
        if window.resolution is not None:
            kernel.resolution = float(window.resolution)
        if window.filter_size is not None:
            if window.filter_size < 1 or window.filter_size % 2 == 0:
                raise ValueError(f"filter_size must be a positive odd integer, got {window.filter_size}")
            kernel.filter_size = int(window.filter_size)
        if not window.prior > 0:
            raise ValueError(f"prior must be positive, got {window.prior}")
        self.device = resolve_device(config.compute.device)
        self.layer = ConvBKILayer(kernel).to(self.device)
        self.geometry = WindowGeometry(kernel.resolution, tuple(window.local_bounds[0]), tuple(window.local_bounds[1]))
        self.prior = float(window.prior)
        self.frame_id = config.frame_id
        self.ignore_classes = config.ignore_classes()
        if free.enabled and FREE_CLASS not in self.ignore_classes:
            raise ValueError(f"free space is kept in class {FREE_CLASS}, which must be an ignored class "
                             f"(ignored: {list(self.ignore_classes)})")
        self.free_space = bool(free.enabled)
        ground_classes = config.ground_classes() if self.free_space else ()
        if any(not 0 < c < min(kernel.num_classes, MAX_CLASS_BITS) for c in ground_classes):
            raise ValueError(f"ground classes must be classes 1..{min(kernel.num_classes, MAX_CLASS_BITS) - 1}, "
                             f"got {list(ground_classes)}")
        self.max_concentration = check_limit(free.max_concentration)
        update_path = config.compute.update_path
        if update_path not in UPDATE_PATHS:
            raise ValueError(f"update_path must be one of {', '.join(UPDATE_PATHS)}, got {update_path!r}")
        if update_path == "auto":
            update_path = "fast" if self.device.type == "cpu" else "torch"
        self.update_path = update_path
        track_changes = config.store.track_changes
        budget_mb = float(config.store.max_megabytes)
        if not (np.isfinite(budget_mb) and budget_mb >= 0):
            raise ValueError(f"max_map_megabytes must be a finite number >= 0 (0: no bound), got {budget_mb}")
        self.store = VoxelStore(kernel.num_classes, prior=self.prior)
        self._bound_store()
        if update_path == "torch":
            self.window = TorchWindow(self.geometry.dims, kernel.num_classes, self.prior, self.store, track_changes,
                                      self.device)
        else:
            self.window = RollingWindow(self.geometry.dims, kernel.num_classes, self.prior, self.store, track_changes)
        self.scans_integrated = 0
        self.sensor_position: np.ndarray | None = None  # map frame (m), at the last scan (or from a loaded file)
        self._removed: list[np.ndarray] = []  # voxels that left the map since the changes were taken
        self._everything_changed = False  # a load replaced the map: every voxel is a change
        self._replaced_keys: np.ndarray | None = None  # voxels of a map this one replaced (linear keys)
        self.present_movers: PresentMovers | None = None  # the last scan's moving points, never in the map
        # Every integrated scan, bit for bit with its pose, so that a SLAM's correction can move it.
        log = config.scan_log
        self.scan_log = (ScanLog(int(log.max_scans), int(log.max_megabytes * 1e6)) if log.enabled else None)
        self.movable_classes = config.movable_classes()
        forgetting_classes = config.forgetting_classes()
        self.forgetting = (MoverForgetting(forgetting_classes, kernel.num_classes, self.prior, self.geometry.dims,
                                           kernel.filter_size // 2, self.resolution,
                                           config.free_space.contradiction_radius)
                           if self.free_space and forgetting_classes else None)
        if self.forgetting is not None:
            # The rules read only the class runs the window's per-column bits say are held:
            # start keeping them now, while the window is empty, not in the first scan.
            self.window.classes_by_column()
        # The parts, built once: the filters of the first scan are prepared now.
        self.filters = KernelFilters(self.layer, self.device, on_device=update_path == "torch")
        self.voxelize = Voxelizer(self.geometry, self.layer, self.ignore_classes, self.window)
        self.update = make_update(update_path, self.filters, self.layer, self.window)
        self.free = (make_free_space(self.filters, self.geometry, self.window, self.max_concentration, self.prior,
                                     ground_classes)
                     if self.free_space else None)

    # -- properties ------------------------------------------------------------------------
    @property
    def kernel(self) -> ConvBKIKernel:
        return self.layer.kernel

    @property
    def temperature(self) -> float | None:
        """The kernel's temperature of probability inputs (None: 1, the rows as given)."""
        return self.kernel.temperature

    @property
    def num_classes(self) -> int:
        return self.kernel.num_classes

    @property
    def resolution(self) -> float:
        return self.geometry.resolution

    def memory_state(self) -> MemoryState:
        """The map's memory against its budget: the store's bytes, those lent to the window, the
        budget and ceiling (0: none), whether the map is full, the voxels dropped and how often
        it became full (since the mapper was made or reset, or since its log segment's base for
        a corrected mapper). Bytes as ``VoxelStore.resident_bytes`` counts them."""
        return self.store.memory_state()

    def _bound_store(self) -> None:
        """Give the store the configured budget (``store.max_megabytes``, MB = 10^6 bytes) and its
        ceiling: every store the map lives in gets it (a reset keeps it, a correction's new map
        and a map file loaded are held to it)."""
        budget = int(float(self.config.store.max_megabytes) * 1e6)
        self.store.set_budget(budget, int(budget * CEILING_FACTOR))

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel of this mapper's parts: the window,
        the voxeliser, the update backend, the free-space backend and the movers' rules each
        run themselves on a scratch window of their own (``parts.Scratch``). The map is not
        touched; call it before mapping (``warm_up.warm_up`` also warms the outputs and files)."""
        for part in (self.window, self.voxelize, self.update, self.free, self.forgetting):
            if part is not None:
                part.warm_up(Scratch(self.resolution, self.num_classes, self.prior, self.ignore_classes, self.window))

    # -- the update ------------------------------------------------------------------------
    def integrate(self, points: np.ndarray, values: np.ndarray, pose: np.ndarray,
                  moving: np.ndarray | None = None, stamp_ns: int | None = None,
                  mount: np.ndarray | None = None, logged: LoggedScan | None = None) -> IntegrationResult:
        """Fuse one scan into the map.

        ``points`` (N, 3) in the sensor frame (m); ``values`` (N,) integer learning labels
        or (N, C) class probabilities (calibrated by the kernel's ``temperature``); ``pose``
        (4, 4) map <- sensor. Invalid points are dropped and counted in the result; an
        invalid pose raises ``ValueError`` and leaves the map untouched. ``moving`` (N,)
        bool, where the input marks moving objects: those points are evidence for this scan
        only (``present_movers``): they stay out of the map, and this scan's queries of their
        voxels read them. With labels, the points of movable classes connected to a moving
        point stay out of the map too (``whole_movers``): a mover's parts the input did not
        mark move with it.

        With the scan log on, the scan is logged as integrated (``scan_log``), with ``stamp_ns``
        (default: 0.1 s after the scan before) and ``mount`` (body <- sensor, the pose of the
        sensor on the body whose poses a SLAM corrects; default the identity); ``logged``: the
        scan as a log already holds it (a correction maps logged scans again), logged as it is.
        """
        started = time.perf_counter()
        pose = check_pose(pose)
        points, values = check_scan(points, values, self.num_classes)
        movers = None
        if moving is not None:
            moving = np.asarray(moving, bool).reshape(-1)
            if moving.shape[0] != points.shape[0]:
                raise ValueError(f"got {points.shape[0]} points but {moving.shape[0]} moving flags")
            if moving.any():
                movers = present_movers(transform_points(points[moving], pose), values[moving], self.num_classes,
                                        self.resolution, self.ignore_classes)
                moving_objects = whole_movers(points, values, moving, self.movable_classes)
                points, values = points[~moving_objects], values[~moving_objects]
        origin = self.geometry.origin_for(pose[:3, 3])
        volume = self.voxelize(points, values, pose, origin)
        voxelized = time.perf_counter()
        self.window.move_to(origin)
        if self.device.type == "cuda":  # the stages' times are the device's: the move's copies end here
            torch.cuda.synchronize(self.device)
        moved = time.perf_counter()
        result = IntegrationResult(volume.stats, origin, occupied_voxels=volume.num_voxels)
        marks = EVIDENCE | CHANGED | (TOUCHED | RECLASSED if self.free_space else 0)
        forgetting_s = 0.0  # the movers' rules count with free space (both make space empty)
        if self.forgetting is not None:
            self.forgetting.window_moved(origin, self.window.mask)
            self.forgetting.contradicted(volume, self.window)
            forgetting_s = time.perf_counter() - moved
        if volume.num_voxels:
            result.new_voxels = self.update(volume, marks)
            self.window.note_scan(volume, self.kernel.filter_size // 2)
        if self.forgetting is not None:
            started_rule = time.perf_counter()
            self.forgetting.unsupported(self.window)
            forgetting_s += time.perf_counter() - started_rule
        updated = time.perf_counter()
        if self.free is not None and volume.num_voxels:
            result.freed_voxels = self.free(points, pose, volume, origin)
        self.scans_integrated += 1
        self.sensor_position = pose[:3, 3].copy()
        self.present_movers = movers
        finished = time.perf_counter()
        if self._everything_changed and self.window.track_changes:
            self.window.forget_evicted_changes()  # every voxel is the next change: none need be kept
        if self.scan_log is not None:
            stamp = stamp_ns if stamp_ns is not None else (self.scans_integrated - 1) * 100_000_000
            self.scan_log.append(logged if logged is not None else LoggedScan.of(points, values, pose, stamp, mount))
            if self.scan_log.wants_segment():
                self._begin_log_segment()
        logged_at = time.perf_counter()
        result.timing_ms = {"voxelize": 1e3 * (voxelized - started), "query": 1e3 * (moved - voxelized),
                            "update": 1e3 * (updated - moved - forgetting_s),
                            "free": 1e3 * (finished - updated + forgetting_s), "movers": 1e3 * forgetting_s,
                            "log": 1e3 * (logged_at - finished),
                            "total": 1e3 * (logged_at - started)}
        return result

    def withdraw(self, points: np.ndarray, values: np.ndarray, pose: np.ndarray) -> int:
        """Take the class evidence of a scan integrated at ``pose`` out of the map again: Eq. 4 is
        a sum, so the update with the scan's evidence negated leaves the map as it was before the
        scan, up to float rounding (the voxels only it reached are back at the prior). Only for
        a map that is that sum alone: free space, clamping and the movers' rules read the map's
        state at each scan, so their map is not a sum (``correction`` maps scans again instead).
        Returns the voxels of the scan. The scan log, if any, is not changed."""
        if self.free_space:
            raise ValueError("withdraw needs the paper's set-up: with free space the map is not a sum of its scans")
        pose = check_pose(pose)
        points, values = check_scan(points, values, self.num_classes)
        origin = self.geometry.origin_for(pose[:3, 3])
        volume = self.voxelize(points, values, pose, origin)
        self.window.move_to(origin)
        if volume.num_voxels:
            volume.features = -volume.features
            self.update(volume, EVIDENCE | CHANGED)
        return volume.num_voxels


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

Public surface: ``integrate``, ``labels_at``, ``voxels``, ``local_voxels``, ``save``,
``load``, ``export_ply``, ``reset``.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from convbki_core.config import DEFAULTS, UPDATE_PATHS, MapperConfig
from convbki_core.correction.replay import CorrectionResult, continue_correction, pose_displacement
from convbki_core.correction.scan_log import LoggedScan, ScanLog, Segment
from convbki_core.devices import resolve_device
from convbki_core.free_space.clamping import check_limit
from convbki_core.free_space.forgetting import MoverForgetting
from convbki_core.free_space.present_movers import PresentMovers, labels_now, present_movers, whole_movers
from convbki_core.free_space.rays import (
    FREE_CLASS,
)
from convbki_core.geometry.volume import (
    VoxelizeStats,
    WindowGeometry,
    check_pose,
    check_scan,
    transform_points,
    voxel_centres,
    voxel_indices,
    voxel_keys,
    voxels_of_keys,
)
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.inference.layer import ConvBKILayer
from convbki_core.inference.statistics import dirichlet_statistics
from convbki_core.io.kernel_file import KernelConfig, kernel_config_to_dict, load_kernel_file
from convbki_core.io.map_file import (
    MAP_FORMAT,
    MAP_VERSION,
    MapSetupError,
    MapSnapshot,
    read_map,
    setup_differences,
)
from convbki_core.io.ply import write_voxels_ply
from convbki_core.memory.store import VoxelStore
from convbki_core.memory.window import CHANGED, EVIDENCE, MAX_CLASS_BITS, RECLASSED, TOUCHED, RollingWindow
from convbki_core.outputs.records import RECORD, records_from_alpha, window_records
from convbki_core.parts import KernelFilters, Scratch, Voxelizer, make_free_space, make_update
from convbki_core.torch_path.window import TorchWindow


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


@dataclass
class MapChanges:
    """What changed in the map since the changes were last taken.

    ``removed``: global indices (R, 3) of voxels that left the map (a reset, a load);
    ``indices`` (N, 3) and ``alpha`` (N, C): voxels whose concentrations changed, in order
    (a voxel may appear more than once: its last row is its state). Applying the removals
    first and then the rows to a copy of the map as it was gives the map as it is.
    """

    removed: np.ndarray
    indices: np.ndarray
    alpha: np.ndarray


@dataclass
class VoxelSet:
    """Voxels with their statistics. Centres in the map frame (m)."""

    indices: np.ndarray  # (N, 3) int64 global voxel indices
    centres: np.ndarray  # (N, 3) float32
    alpha: np.ndarray  # (N, C) float32 concentrations
    label: np.ndarray  # (N,) int64 expected class
    confidence: np.ndarray  # (N,) float32
    variance: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return int(self.indices.shape[0])


class ConvBKIMapper:
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
        self.store = VoxelStore(kernel.num_classes, prior=self.prior)
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

    # -- the scan log and corrections (a SLAM moved poses) -------------------------------------
    def base_copy(self):
        """The map as it is now, as a store of its own (a log segment's base): the global
        store's chunks shared, the window's voxels written into it. Returns (store, the memory
        it takes beside the map's store: about the window's voxels)."""
        base = self.store.copy()
        base.write(*self.window.items())
        return base, base.bytes_not_shared_with(self.store)

    def _begin_log_segment(self) -> None:
        self.scan_log.refresh_base_bytes(self.store)  # the bound counts what the older bases own by now
        base, nbytes = self.base_copy()
        self.scan_log.begin_segment(base, self.sensor_position, nbytes)

    def _restart_log(self, why: str) -> None:
        """The map changed other than by a scan (a load, a forgotten box): a correction can
        reach back to here only, from the map as it is now; ``why`` the scans before cannot move."""
        if self.scan_log is not None:
            base, nbytes = self.base_copy()
            self.scan_log.restart(base, self.sensor_position, nbytes, self.scans_integrated, why)

    def plan_correction(self, poses: dict[int, np.ndarray], tolerance: float = 0.0, reach: float | None = None,
                        log: ScanLog | None = None) -> tuple[dict[int, np.ndarray], int, float]:
        """Which logged scans a correction moves: of ``poses`` (corrected map <- sensor poses by
        the drive's scan index), those still in the log whose points within ``reach`` m (default:
        the window's half extent) move by ``tolerance`` m or more; ``log``: a copy of this
        mapper's log taken earlier (default: the log). Returns (moves, scans left alone, the
        largest displacement of a sensor in m)."""
        log = self.scan_log if log is None else log
        if log is None:
            raise ValueError("this mapper keeps no scan log: nothing can be moved")
        reach = float(np.max(np.abs(self.geometry.bounds_max))) if reach is None else reach
        logged = dict(log.scans())
        moves, skipped, largest = {}, 0, 0.0
        for index, pose in poses.items():
            if index not in logged:
                continue
            pose = check_pose(pose)
            if pose_displacement(logged[index].pose, pose, reach) < tolerance:
                skipped += 1
                continue
            moves[index] = pose
            largest = max(largest, float(np.linalg.norm(pose[:3, 3] - logged[index].pose[:3, 3])))
        return moves, skipped, largest

    def corrected(self, poses: dict[int, np.ndarray], tolerance: float = 0.0, until: int | None = None,
                  reuse: ConvBKIMapper | None = None, log: ScanLog | None = None
                  ) -> tuple[ConvBKIMapper, CorrectionResult]:
        """This map as it would be had the logged scans been integrated at corrected poses
        (``poses``: map <- sensor by the drive's scan index; scans no longer logged, or moved by
        less than ``tolerance`` m, are left alone), and what that took. The map is not changed:
        a new mapper maps every logged scan again, in the order they came, from the base of the
        log's segment that holds the first moved one (``correction``), up to scan ``until``
        (exclusive; default: every logged scan). ``reuse``: a mapper of the same set-up to map
        into instead of a new one (the one a correction replaced: its window is already in
        memory, where a new window's pages cost more than the scans). ``log``: a copy of this
        mapper's log (``ScanLog.copy``) to read instead of the log, so that this mapper may go
        on mapping meanwhile (the node's live scans). Returns (the new mapper, or this one when
        nothing moves; the result)."""
        started = time.perf_counter()
        log = self.scan_log if log is None else log
        moves, skipped, largest = self.plan_correction(poses, tolerance, log=log)
        result = CorrectionResult(scans=len(moves), largest_move=largest, skipped=skipped)
        if not moves:
            result.seconds = time.perf_counter() - started
            return self, result
        segment = log.segment_for(min(moves))
        new = reuse if reuse is not None and reuse is not self else ConvBKIMapper(self.config, self.layer.kernel)
        new.frame_id = self.frame_id
        new.start_from(segment, log)
        replayed = continue_correction(new, log, moves, segment.first_index, until)
        result.replayed = replayed
        result.seconds = time.perf_counter() - started
        return new, result

    def start_from(self, segment, log: ScanLog) -> None:
        """Make this (new) mapper the map as it was when ``segment`` of ``log`` began: its base,
        and the log's segments before it (a correction maps the scans from there again)."""
        if self.scans_integrated or len(self) or self.sensor_position is not None:
            self._clear()  # a fresh mapper is already empty: its window is not filled twice
        if segment.base is not None:
            self.store = segment.base.copy()
            self.window.store = self.store
        self.scans_integrated = segment.first_index
        if segment.base_position is not None:
            self.sensor_position = np.asarray(segment.base_position, np.float64).copy()
            self.window.move_to(self.geometry.origin_for(self.sensor_position))
        self._everything_changed = True
        self._removed = []
        self._replaced_keys = None
        if self.scan_log is not None:
            older = [s for s in log.segments() if s.first_index < segment.first_index]
            self.scan_log.frozen, self.scan_log.frozen_stamp_ns = log.frozen, log.frozen_stamp_ns
            self.scan_log.frozen_why = log.frozen_why
            self.scan_log.calibration = log.calibration
            self.scan_log.replace_from(0, [*older, Segment(segment.first_index, segment.base, segment.base_position,
                                                           segment.base_bytes)])

    # -- reading the map -------------------------------------------------------------------
    def concentrations_at(self, points_map: np.ndarray,
                          within_window: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Concentrations of the voxel under each map-frame point: (alpha (N, C) float32,
        has_evidence (N,) bool); rows are zero where the voxel holds no evidence, or (with
        ``within_window``) lies outside the current window, or the point is not finite."""
        points_map = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
        usable = np.isfinite(points_map).all(axis=1)
        indices = np.zeros((points_map.shape[0], 3), np.int64)
        indices[usable] = voxel_indices(points_map[usable], self.resolution)
        in_window = usable & self.window.inside(indices)
        alpha = np.zeros((points_map.shape[0], self.num_classes), np.float32)
        has_evidence = np.zeros(points_map.shape[0], bool)
        alpha[in_window], has_evidence[in_window] = self.window.lookup(indices[in_window])
        if not within_window:
            elsewhere = usable & ~in_window
            alpha[elsewhere], has_evidence[elsewhere] = self.store.lookup(indices[elsewhere])
        alpha[~has_evidence] = 0.0
        return alpha, has_evidence

    def labels_at(self, points_map: np.ndarray, within_window: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Expected class of the voxel under each map-frame point.

        Returns (labels (N,) int64, has_evidence (N,) bool); labels are -1 where the voxel
        holds no evidence, or (with ``within_window``) lies outside the current window. With
        free space, the class is the most likely of the others: a query point is a return,
        so the question is what the surface there is, not whether the voxel is empty. A voxel
        that holds the last scan's moving points reads as their most likely class.
        """
        alpha, has_evidence = self.concentrations_at(points_map, within_window)
        labels = np.full(alpha.shape[0], -1, np.int64)
        if self.free_space:
            alpha[:, FREE_CLASS] = 0.0
        labels[has_evidence] = dirichlet_statistics(alpha[has_evidence]).label
        if self.present_movers is not None:
            points_map = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
            usable = np.isfinite(points_map).all(axis=1)
            now = np.full(len(labels), -1, np.int64)
            held = np.zeros(len(labels), bool)
            now[usable], held[usable] = labels_now(self.present_movers, voxel_indices(points_map[usable],
                                                                                      self.resolution))
            labels[held], has_evidence = now[held], has_evidence | held
        return labels, has_evidence

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """Every voxel with evidence: (global indices (N, 3) int64, alpha (N, C) float32)."""
        # One allocation filled by both parts: a map of millions of voxels is hundreds of MB,
        # and the node does this for every map it publishes.
        stored, in_window = len(self.store), self.window.count()
        indices = np.empty((stored + in_window, 3), np.int64)
        alpha = np.empty((stored + in_window, self.num_classes), np.float32)
        self.store.items(indices[:stored], alpha[:stored])
        self.window.items(indices[stored:], alpha[stored:])
        return indices, alpha

    def voxels(self) -> VoxelSet:
        """Every voxel that ever received evidence, with its statistics."""
        return self.voxel_set(*self.items())

    def local_voxels(self) -> VoxelSet:
        """The voxels with evidence in the current window."""
        return self.voxel_set(*self.window.items())

    def window_records(self, palette: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Records (``records.RECORD``: centre, colour, class, variance, probability) of the voxels
        with evidence in the current window, computed from the window in place; ``out``: as
        many records as ``window.count()`` to fill."""
        window = self.window
        if window.origin is None:
            return np.empty(0, RECORD) if out is None else out
        if isinstance(window, TorchWindow):  # made on the device: one copy of the records
            return window.records(self.resolution, palette, out)
        count = window.count() if out is None else len(out)
        return window_records(window.alpha, window.mask, window.origin, window.dims, count, self.resolution,
                              palette, out)

    def voxel_set(self, indices: np.ndarray, alpha: np.ndarray) -> VoxelSet:
        """Statistics of the given voxels (e.g. a copy taken from ``items()``)."""
        stats = dirichlet_statistics(alpha)
        return VoxelSet(indices, voxel_centres(indices, self.resolution).astype(np.float32), alpha,
                        stats.label, stats.confidence, stats.variance)

    def __len__(self) -> int:
        return len(self.store) + self.window.count()

    # -- persistence -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every voxel, and the scan log (the kernel and settings stay)."""
        self._removed.append(self.items()[0])
        self._clear()

    def retire(self) -> None:
        """Forget every voxel and the log without reporting them as removed: a map another took
        the place of, kept only for its window (``corrected``'s ``reuse``)."""
        self._clear()
        self._removed, self._everything_changed, self._replaced_keys = [], False, None

    def _clear(self) -> None:
        self.store.clear()
        self.window.clear()
        if self.scan_log is not None:
            self.scan_log.clear()
        self.scans_integrated = 0
        self.sensor_position = None
        self.present_movers = None
        if self.forgetting is not None:
            self.forgetting.clear()

    def forget_box(self, box_min: Sequence[float], box_max: Sequence[float]) -> np.ndarray:
        """Forget the evidence of every voxel whose centre lies in the box ``box_min`` ..
        ``box_max`` (x, y, z in the map frame, m), as if it had never been observed (octomap's
        clear_bbox). Returns the global indices (n, 3) of the voxels forgotten; they are
        reported as removed by ``take_changes``."""
        box_min, box_max = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
        if box_min.shape != (3,) or box_max.shape != (3,) or not np.isfinite([box_min, box_max]).all():
            raise ValueError(f"a box needs finite x, y, z corners, got {box_min.tolist()} and {box_max.tolist()}")
        # Voxel i's centre is (i + 0.5) * resolution: the first and one past the last voxel inside.
        lo = np.ceil(box_min / self.resolution - 0.5).astype(np.int64)
        hi = np.floor(box_max / self.resolution - 0.5).astype(np.int64) + 1
        if (hi <= lo).any():
            return np.zeros((0, 3), np.int64)
        forgotten = np.concatenate([self.store.forget_box(lo, hi), self.window.forget_box(lo, hi)])
        self._removed.append(forgotten)
        if len(forgotten):
            # A correction mapping older scans again would bring the box back.
            self._restart_log("a box of the map was forgotten after them")
        return forgotten

    def take_changes(self, everything: bool = False) -> MapChanges:
        """The voxels that changed or left the map since the last call (``everything``: every
        voxel of the map, as after a load), for outputs that send only what changed."""
        removed = np.concatenate(self._removed) if self._removed else np.zeros((0, 3), np.int64)
        self._removed = []
        indices, alpha = self.window.take_changes()
        if everything or self._everything_changed:
            self._everything_changed = False
            indices, alpha = self.items()
            if self._replaced_keys is not None:  # what the map this one replaced had and this one has not
                gone = np.setdiff1d(self._replaced_keys, voxel_keys(indices), assume_unique=True)
                removed = np.concatenate([removed, voxels_of_keys(gone)])
                self._replaced_keys = None
        return MapChanges(removed, indices, alpha)

    def take_change_records(self, palette: np.ndarray, everything: bool = False) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray]:
        """``take_changes`` as (removed (R, 3), changed voxels' indices (N, 3), their records
        (``records.RECORD``)): for a window on a torch device the records are made there, so
        the changes come to the host as records, not as concentrations."""
        if isinstance(self.window, TorchWindow) and not (everything or self._everything_changed):
            removed = np.concatenate(self._removed) if self._removed else np.zeros((0, 3), np.int64)
            self._removed = []
            indices, records = self.window.take_change_records(self.resolution, palette)
            return removed, indices, records
        changes = self.take_changes(everything)
        return changes.removed, changes.indices, records_from_alpha(changes.indices, changes.alpha, self.resolution,
                                                                    palette)

    def announce_replacement(self, previous_indices: np.ndarray) -> None:
        """This map took the place of another (a correction's): the next changes are every voxel,
        and the other's voxels (``previous_indices``, (n, 3)) this map does not have as removed,
        so a copy kept from the changes becomes this map."""
        self._replaced_keys = np.unique(voxel_keys(previous_indices))
        self._everything_changed = True

    def save(self, path: str | Path) -> None:
        """Write the whole map to one self-describing file, atomically."""
        self.snapshot().write(path)

    def snapshot(self) -> MapSnapshot:
        """A copy of everything a map file holds (``items()`` returns fresh arrays), with its
        metadata: take it under a lock, ``write()`` it later."""
        indices, alpha = self.items()
        metadata = {
            "format": MAP_FORMAT,
            "version": MAP_VERSION,
            "resolution": self.resolution,
            "num_classes": self.num_classes,
            "num_voxels": int(indices.shape[0]),
            "frame_id": self.frame_id,
            "prior": self.prior,
            "local_bounds": [list(self.geometry.bounds_min), list(self.geometry.bounds_max)],
            "kernel": kernel_config_to_dict(self.kernel.to_config()),
            "scans_integrated": self.scans_integrated,
            "mapping": self.config.replace(frame_id=self.frame_id).mapping_record(self.resolution,
                                                                                  self.kernel.filter_size),
        }
        if self.sensor_position is not None:
            metadata["sensor_position"] = [float(v) for v in self.sensor_position]
        return MapSnapshot(metadata, indices, alpha, self.scan_log.copy() if self.scan_log is not None else None)

    def load(self, path: str | Path) -> dict:
        """Replace the map's voxels with those of a map file (resolution, classes and prior must
        match); the map is untouched if the file is unusable. Returns the file's metadata."""
        metadata, indices, alpha = read_map(path, with_scan_log=True)
        self.check_compatible(path, metadata)
        self.replace_with(metadata, indices, alpha)
        return metadata

    def check_compatible(self, path: str | Path, metadata: dict) -> None:
        """Raise ``MapSetupError`` unless a map file with this metadata (``read_map``) can be
        loaded into this mapper: the same classes, resolution and prior."""
        differences = setup_differences(metadata, self.resolution, self.num_classes, self.prior)
        if not differences:
            return
        first = differences[0]
        if first.what == "num_classes":
            message = f"{path}: map has {first.in_file} classes, the mapper {first.here}"
        elif first.what == "resolution":
            message = f"{path}: map resolution {first.in_file} m differs from the mapper's {first.here} m"
        else:
            message = (f"{path}: map prior {first.in_file} differs from the mapper's {first.here}: its voxels' "
                       "unobserved classes would hold the wrong concentration")
        raise MapSetupError(message, differences)

    def replace_with(self, metadata: dict, indices: np.ndarray, alpha: np.ndarray) -> None:
        """Make the map the given one (a map file's contents, ``read_map``, checked with
        ``check_compatible``). The window is placed around the sensor position the file
        recorded (else the centre of its voxels), so the map around the robot is at hand
        before the next scan."""
        self.reset()  # its voxels count as removed
        self.store.write(indices, alpha)
        self.scans_integrated = int(metadata.get("scans_integrated", 0))
        position = metadata.get("sensor_position")
        if position is None and len(indices):
            position = voxel_centres((indices.min(axis=0) + indices.max(axis=0)) // 2, self.resolution)
        if position is not None:
            self.sensor_position = np.asarray(position, np.float64)
            self.window.move_to(self.geometry.origin_for(self.sensor_position))
        if self.scan_log is not None and metadata.get("scan_log") is not None:
            self.scan_log.adopt(metadata["scan_log"])
        else:  # a file without a log: its map is where corrections begin
            self._restart_log("they came from a map file without a scan log")
        self._everything_changed = True

    def export_ply(self, path: str | Path, max_variance: float | None = None) -> int:
        """Write the map as a PLY point cloud in class colours; returns the number of voxels written."""
        return write_voxels_ply(self.voxels(), path, max_variance=max_variance)

"""The parts a ``ConvBKIMapper`` builds once from its configuration, so that ``integrate``
reads as the paper's steps: voxelise (Eq. 3) -> move the window -> update (Eq. 4) -> free
space.

* ``Voxelizer``: a scan into the window's input volume F, compiled when numba is here;
* the update backends: ``FastUpdate`` (the compiled sparse scatter into a host window),
  ``DenseUpdate`` (the paper's depthwise conv3d, the reference) and ``TorchUpdate`` (a
  window resident on a torch device);
* the free-space backends: ``HostFreeSpace`` (rays counted and applied in one compiled pass,
  with clamping) and ``DeviceFreeSpace`` (rays counted on the host, applied on the device);
* ``KernelFilters``: the kernel's filters prepared for all of them, rebuilt only when the
  kernel's lengths change (training changes them between scans).

Each part owns its warm-up: ``part.warm_up(scratch)`` runs the part's own code on a
``Scratch``, a small window of the kind the mapper holds, so that every kernel the part will
run is compiled (or loaded from numba's cache) with the argument types it will see, before
the first scan, while the mapper's own window is not touched. ``ConvBKIMapper.warm_up`` runs
them all.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.free_space.clamping import clamp_torch
from convbki_core.free_space.device_rays import count_rays_on_device
from convbki_core.free_space.ray_walk import scratch_counts
from convbki_core.free_space.scan_rays import beyond_window, scan_rays, window_exits
from convbki_core.free_space.update import FREE_CLASS, free_space_update, free_taps
from convbki_core.geometry.grid import WindowGeometry, transform_points, unravel_linear
from convbki_core.geometry.volume import SparseVolume, voxelize, voxelize_scan
from convbki_core.inference.layer import ConvBKILayer
from convbki_core.inference.update import FilterPlan, dense_volume, scatter_volume
from convbki_core.memory.store import VoxelStore
from convbki_core.memory.window import CHANGED, EVIDENCE, RECLASSED, TOUCHED, RollingWindow
from convbki_core.torch_path.window import TorchFilters, TorchWindow, torch_free_space, torch_update

# Every mark an update sets (with free space, TOUCHED and RECLASSED too): the warm-ups update with all of them.
ALL_MARKS = EVIDENCE | CHANGED | TOUCHED | RECLASSED


class Scratch:
    """Where a part runs for its warm-up: a small window of the same kind as ``like`` (host
    arrays, or torch tensors on its device), with the mapper's classes and prior, its own
    store, and one scan (a ground patch, a wall and a box in front of the sensor) voxelised
    into it. numba compiles a kernel once per combination of argument types, not of sizes,
    so what a part runs here is what it will run on the mapper's window."""

    HALF_EXTENT = (16, 16, 6)  # voxels each side of the sensor: room for the scan and a few slabs of moves

    def __init__(self, resolution: float, num_classes: int, prior: float, ignore_classes: tuple[int, ...],
                 like: RollingWindow):
        half = np.asarray(self.HALF_EXTENT) * resolution
        self.geometry = WindowGeometry(resolution, tuple(-half), tuple(half))
        self.num_classes, self.prior, self.ignore_classes = num_classes, prior, ignore_classes
        store = VoxelStore(num_classes, prior=prior)
        dims = self.geometry.dims
        self.window = (TorchWindow(dims, num_classes, prior, store, True, like.device)
                       if isinstance(like, TorchWindow) else RollingWindow(dims, num_classes, prior, store, True))
        rng = np.random.default_rng(0)
        scale = resolution / 0.2
        ground = np.column_stack([rng.uniform(-2.5, 2.5, (300, 2)) * scale, np.full(300, -0.9 * scale)])
        wall = np.column_stack([np.full(120, 1.6 * scale), rng.uniform(-2.0, 2.0, 120) * scale,
                                rng.uniform(-0.9, 0.9, 120) * scale])
        box = rng.uniform([-1.5, -1.5, -0.8], [-0.5, -0.5, 0.2], (80, 3)) * scale
        self.points = np.concatenate([ground, wall, box])  # sensor frame (m), float64
        usable = [c for c in range(num_classes) if c not in ignore_classes] or [0]
        self.labels = rng.choice(np.asarray(usable, np.int64), len(self.points))
        rows = rng.uniform(0.0, 1.0, (len(self.points), num_classes)).astype(np.float32)
        self.probabilities = rows / rows.sum(axis=1, keepdims=True)
        self.pose = np.eye(4)
        self.origin = self.geometry.origin_for(self.pose[:3, 3])
        self.window.move_to(self.origin)
        self.volume = voxelize(self.points, self.labels, self.origin, dims, resolution, num_classes, ignore_classes)
        self._hold_the_scan()

    def _hold_the_scan(self) -> None:
        """The scan's evidence in the window (without its spread): moves then carry voxels."""
        x, y, z = np.mod(unravel_linear(self.volume.linear, self.volume.dims) + self.origin, self.geometry.dims).T
        evidence = self.volume.features.T + self.prior
        if isinstance(self.window, TorchWindow):
            x, y, z = (torch.as_tensor(axis, device=self.window.device) for axis in (x, y, z))
            evidence = torch.as_tensor(evidence, device=self.window.device)
        self.window.alpha[:, x, y, z] = evidence
        self.window.mask[x, y, z] = EVIDENCE | CHANGED

    def origins(self) -> list[np.ndarray]:
        """Window origins for moves: a few slabs along each axis and back, then home again."""
        step = np.asarray(self.HALF_EXTENT) // 3
        return [self.origin + step * np.asarray(move) for move in ((1, 0, 0), (1, 1, 0), (1, 1, 1), (0, -1, 1),
                                                                    (0, 0, 0))]


class KernelFilters:
    """The layer's kernel as the scatter, the free-space pass and the device window read it."""

    def __init__(self, layer: ConvBKILayer, device: torch.device, on_device: bool):
        self.layer, self.device, self.on_device = layer, device, on_device
        self._key: tuple | None = None
        self.refresh()

    def refresh(self) -> KernelFilters:
        """Rebuild what the kernel's current lengths give, when they changed; returns self."""
        kernel = self.layer.kernel
        with torch.no_grad():
            key = (kernel.kind, kernel.resolution, kernel.filter_size,
                   *(parameter.detach().cpu().numpy().tobytes() for parameter in kernel.parameters()))
            if self._key != key:
                self.plan = FilterPlan.from_filters(kernel.filters().detach().cpu().numpy()[:, 0])
                self.free_filter = kernel.free_filter().detach().cpu().numpy()
                self.free_taps = free_taps(self.free_filter)
                self.torch_filters = TorchFilters(self.plan, self.device) if self.on_device else None
                self._key = key
        return self


class Voxelizer:
    """A scan (sensor-frame points, labels or probabilities, pose) into the input volume F of
    the window starting at ``origin``: one compiled pass, or numpy without numba."""

    def __init__(self, geometry: WindowGeometry, layer: ConvBKILayer, ignore_classes: tuple[int, ...],
                 window: RollingWindow | TorchWindow):
        self.geometry, self.layer, self.ignore_classes, self.window = geometry, layer, ignore_classes, window

    def __call__(self, points: np.ndarray, values: np.ndarray, pose: np.ndarray, origin: np.ndarray) -> SparseVolume:
        # Probability rows are calibrated by the kernel's temperature here, so every update
        # backend receives the same F; labels are never touched.
        return self._voxelize(points, values, pose, origin, self.layer.kernel.temperature)

    def _voxelize(self, points, values, pose, origin, temperature: float | None) -> SparseVolume:
        classes = self.layer.kernel.num_classes
        if HAVE_NUMBA:
            return voxelize_scan(points, values, pose, origin, self.geometry.dims, self.geometry.resolution,
                                 classes, self.ignore_classes, self.window.slot, temperature)
        return voxelize(transform_points(points, pose), values, origin, self.geometry.dims, self.geometry.resolution,
                        classes, self.ignore_classes, temperature)

    def warm_up(self, scratch: Scratch) -> None:
        """Every input a scan can bring: float64 and float32 points, labels and probability rows,
        probabilities tempered or not (the temperature is an argument of the compiled pass)."""
        small = Voxelizer(scratch.geometry, self.layer, self.ignore_classes, scratch.window)
        for points in (scratch.points, scratch.points.astype(np.float32)):
            small._voxelize(points, scratch.labels, scratch.pose, scratch.origin, None)
            for temperature in (None, 0.5):
                small._voxelize(points, scratch.probabilities, scratch.pose, scratch.origin, temperature)


class FastUpdate:
    """alpha += conv3d(F, K) as the compiled sparse scatter into the host window."""

    name = "fast"

    def __init__(self, filters: KernelFilters, window: RollingWindow):
        self.filters, self.window = filters, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return scatter_volume(volume, self.filters.refresh().plan, self.window.alpha, self.window.mask, marks)

    def warm_up(self, scratch: Scratch) -> None:
        FastUpdate(self.filters, scratch.window)(scratch.volume, ALL_MARKS)


class DenseUpdate:
    """alpha += conv3d(F, K) as the paper writes it: the dense depthwise convolution."""

    name = "dense"

    def __init__(self, layer: ConvBKILayer, window: RollingWindow):
        self.layer, self.window = layer, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return dense_volume(volume, self.layer, self.window.alpha, self.window.mask, marks)

    def warm_up(self, scratch: Scratch) -> None:
        DenseUpdate(self.layer, scratch.window)(scratch.volume, ALL_MARKS)


class TorchUpdate:
    """alpha += conv3d(F, K) into a window resident on the torch device."""

    name = "torch"

    def __init__(self, filters: KernelFilters, window: TorchWindow):
        self.filters, self.window = filters, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return torch_update(volume, self.filters.refresh().torch_filters, self.window, marks)

    def warm_up(self, scratch: Scratch) -> None:
        """On a GPU this also loads the device's kernels, as nvblox warms CUDA up before it starts."""
        TorchUpdate(self.filters, scratch.window)(scratch.volume, ALL_MARKS)


class _FreeSpace:
    """What both free-space backends hold: the filters, the window, clamping and the ray counts."""

    def __init__(self, filters: KernelFilters, geometry: WindowGeometry, window: RollingWindow | TorchWindow,
                 max_concentration: float, prior: float, ground_classes: tuple[int, ...] = ()):
        self.filters, self.geometry, self.window = filters, geometry, window
        self.max_concentration, self.prior = max_concentration, prior
        self.ground_classes = tuple(ground_classes)  # their voxels take no free evidence
        self.counts = self._scratch_counts()
        if self.ground_classes:
            # Which voxels are ground is derived from the held class runs only: the window
            # keeps its per-column class bits from now on, while it is empty.
            window.classes_by_column()

    def _scratch_counts(self):
        return scratch_counts(self.geometry.dims)

    def warm_up(self, scratch: Scratch) -> None:
        """The rays of the scratch scan, with this backend's clamping and ground classes."""
        small = type(self)(self.filters, scratch.geometry, scratch.window, self.max_concentration, self.prior,
                           self.ground_classes)
        small(scratch.points, scratch.pose, scratch.volume, scratch.origin)


class HostFreeSpace(_FreeSpace):
    """The rays of a scan as free evidence (class 0) in the host window, with clamping."""

    def __call__(self, points: np.ndarray, pose: np.ndarray, volume: SparseVolume, origin: np.ndarray) -> int:
        offsets, tap_weights = self.filters.refresh().free_taps
        ends, weights, through = scan_rays(points, pose, volume, self.geometry.resolution)
        sensor = pose[:3, 3] / self.geometry.resolution
        return free_space_update(sensor, ends, weights, offsets, tap_weights, origin, self.geometry.dims,
                                 self.window.alpha, self.window.mask, self.counts, through, self.max_concentration,
                                 self.prior, self.ground_classes, self.window.classes_by_column())


class DeviceFreeSpace(_FreeSpace):
    """The rays walked, counted and applied in the device window. The rays to the scan's
    returns start from the occupied voxels the update already sent there; only the voxels where
    rays to returns beyond the window leave it are sent."""

    def _scratch_counts(self) -> torch.Tensor:
        return torch.zeros(tuple(int(d) for d in self.geometry.dims), dtype=torch.float32, device=self.window.device)

    def __call__(self, points: np.ndarray, pose: np.ndarray, volume: SparseVolume, origin: np.ndarray) -> int:
        device = self.window.device
        resolution = self.geometry.resolution
        if volume.on_device is None:  # not through the torch update (a warm-up's scratch scan)
            volume.on_device = (torch.as_tensor(unravel_linear(volume.linear, volume.dims) + volume.origin,
                                                device=device), torch.as_tensor(volume.features, device=device))
        occupied, features = volume.on_device
        exits, rays = window_exits(pose[:3, 3] / resolution, beyond_window(points, pose, volume, resolution),
                                   volume.origin, volume.dims)
        ends = torch.cat([occupied, torch.as_tensor(exits, device=device)])
        weights = torch.cat([features.sum(dim=1), torch.as_tensor(rays, device=device)])
        through = torch.arange(len(ends), device=device) >= len(occupied)  # the rays that go on beyond it
        counts = count_rays_on_device(pose[:3, 3] / resolution, ends, weights, through, self.counts)
        before = self.window.alpha[FREE_CLASS].clone() if self.max_concentration else None
        freed = torch_free_space(counts, self.filters.refresh().free_filter, self.window, self.ground_classes)
        counts.zero_()
        if before is not None:
            clamp_torch(self.window.alpha, before, self.max_concentration, self.prior)
        return freed


def make_update(path: str, filters: KernelFilters, layer: ConvBKILayer, window):
    """The update backend of an update path (``fast``, ``dense`` or ``torch``)."""
    if path == "fast":
        return FastUpdate(filters, window)
    if path == "dense":
        return DenseUpdate(layer, window)
    return TorchUpdate(filters, window)


def make_free_space(filters: KernelFilters, geometry: WindowGeometry, window, max_concentration: float,
                    prior: float, ground_classes: tuple[int, ...] = ()):
    """The free-space backend of a window: on the device for a ``TorchWindow``, else on the host."""
    backend = DeviceFreeSpace if isinstance(window, TorchWindow) else HostFreeSpace
    return backend(filters, geometry, window, max_concentration, prior, ground_classes)

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

Each part is warmed up by running it: ``warm_up`` drives a throwaway mapper, which holds the
same parts, through every call, so each kernel compiles with the argument types it will see.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.clamping import clamp_torch
from convbki_core.compiled import HAVE_NUMBA
from convbki_core.free_space import FREE_CLASS, count_rays, free_space_update, free_taps, scan_rays, scratch_counts
from convbki_core.layer import ConvBKILayer
from convbki_core.torch_window import TorchFilters, TorchWindow, torch_free_space, torch_update
from convbki_core.update import FilterPlan, dense_volume, scatter_volume
from convbki_core.volume import SparseVolume, WindowGeometry, transform_points, voxelize, voxelize_scan
from convbki_core.window import RollingWindow


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
        kernel = self.layer.kernel
        # Probability rows are calibrated by the kernel's temperature here, so every update
        # backend receives the same F; labels are never touched.
        if HAVE_NUMBA:
            return voxelize_scan(points, values, pose, origin, self.geometry.dims, self.geometry.resolution,
                                 kernel.num_classes, self.ignore_classes, self.window.slot, kernel.temperature)
        return voxelize(transform_points(points, pose), values, origin, self.geometry.dims, self.geometry.resolution,
                        kernel.num_classes, self.ignore_classes, kernel.temperature)


class FastUpdate:
    """alpha += conv3d(F, K) as the compiled sparse scatter into the host window."""

    name = "fast"

    def __init__(self, filters: KernelFilters, window: RollingWindow):
        self.filters, self.window = filters, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return scatter_volume(volume, self.filters.refresh().plan, self.window.alpha, self.window.mask, marks)


class DenseUpdate:
    """alpha += conv3d(F, K) as the paper writes it: the dense depthwise convolution."""

    name = "dense"

    def __init__(self, layer: ConvBKILayer, window: RollingWindow):
        self.layer, self.window = layer, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return dense_volume(volume, self.layer, self.window.alpha, self.window.mask, marks)


class TorchUpdate:
    """alpha += conv3d(F, K) into a window resident on the torch device."""

    name = "torch"

    def __init__(self, filters: KernelFilters, window: TorchWindow):
        self.filters, self.window = filters, window

    def __call__(self, volume: SparseVolume, marks: int) -> int:
        return torch_update(volume, self.filters.refresh().torch_filters, self.window, marks)


class _FreeSpace:
    """What both free-space backends hold: the filters, the window, clamping and the ray counts."""

    def __init__(self, filters: KernelFilters, geometry: WindowGeometry, window: RollingWindow | TorchWindow,
                 max_concentration: float, prior: float):
        self.filters, self.geometry, self.window = filters, geometry, window
        self.max_concentration, self.prior = max_concentration, prior
        self.counts = scratch_counts(geometry.dims)


class HostFreeSpace(_FreeSpace):
    """The rays of a scan as free evidence (class 0) in the host window, with clamping."""

    def __call__(self, points: np.ndarray, pose: np.ndarray, volume: SparseVolume, origin: np.ndarray) -> int:
        offsets, tap_weights = self.filters.refresh().free_taps
        ends, weights, through = scan_rays(points, pose, volume, self.geometry.resolution)
        sensor = pose[:3, 3] / self.geometry.resolution
        return free_space_update(sensor, ends, weights, offsets, tap_weights, origin, self.geometry.dims,
                                 self.window.alpha, self.window.mask, self.counts, through, self.max_concentration,
                                 self.prior)


class DeviceFreeSpace(_FreeSpace):
    """The rays counted on the host (the traversal is sequential), applied in the device window."""

    def __call__(self, points: np.ndarray, pose: np.ndarray, volume: SparseVolume, origin: np.ndarray) -> int:
        ends, weights, through = scan_rays(points, pose, volume, self.geometry.resolution)
        sensor = pose[:3, 3] / self.geometry.resolution
        counts = count_rays(sensor, ends, weights, through, self.geometry.dims, self.counts)
        before = self.window.alpha[FREE_CLASS].clone() if self.max_concentration else None
        freed = torch_free_space(counts, self.filters.refresh().free_filter, self.window)
        counts.fill(0.0)
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
                    prior: float):
    """The free-space backend of a window: on the device for a ``TorchWindow``, else on the host."""
    backend = DeviceFreeSpace if isinstance(window, TorchWindow) else HostFreeSpace
    return backend(filters, geometry, window, max_concentration, prior)

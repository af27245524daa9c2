"""The window on a torch device (a GPU, or the CPU in tests): the torch update path.

The same torus as ``window.RollingWindow`` (global voxel g lives at g mod dims), but the
concentrations alpha[c, x, y, z] and the byte mask stay on the device for the whole drive:
an update sends only the scan's occupied voxels there, and a window move sends only the
slabs that leave it to the host store and the slabs that enter back. Nothing of the size of
the window crosses between host and device per scan.

The update is the ConvBKI convolution written as a scatter from the occupied voxels: every
(voxel, class) pair with evidence adds F[v, c] * K[c, tap] at v + half - tap, for the taps
whose weight is not zero, with one ``index_add_``. Its cost follows the scan, not the
window (the dense conv3d reads and writes every voxel of the window). Voxels are marked as
on the CPU path: the union of the supports (non-zero taps) of the classes present, so the
torch and CPU paths keep the same voxels.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.free_space.ground import ground_marks
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.geometry.grid import unravel_linear
from convbki_core.geometry.volume import SparseVolume
from convbki_core.inference.update import FilterPlan
from convbki_core.memory.column_classes import class_bits
from convbki_core.memory.store import VoxelStore
from convbki_core.memory.window import CHANGED, EVIDENCE, RECLASSED, TOUCHED, RollingWindow
from convbki_core.outputs.records import RECORD, records_from_alpha


class TorchWindow(RollingWindow):
    """``RollingWindow`` whose arrays are torch tensors on ``device``."""

    def __init__(self, dims: np.ndarray, num_classes: int, prior: float, store: VoxelStore,
                 track_changes: bool = False, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        super().__init__(dims, num_classes, prior, store, track_changes)

    def _allocate(self) -> None:
        shape = tuple(int(d) for d in self.dims)
        self.alpha = torch.full((self.num_classes, *shape), float(self.prior), dtype=torch.float32, device=self.device)
        self.mask = torch.zeros(shape, dtype=torch.uint8, device=self.device)

    @property
    def nbytes(self) -> int:
        return (self.alpha.numel() * self.alpha.element_size() + self.mask.numel() + self.slot.nbytes)

    def count(self) -> int:
        return int(torch.count_nonzero(self.mask)) if self.origin is not None else 0

    def _grid(self, lo: np.ndarray, hi: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Broadcastable torus index tensors of the global box [lo, hi)."""
        px, py, pz = (torch.as_tensor(axis, device=self.device) for axis in self._physical(lo, hi))
        return px[:, None, None], py[None, :, None], pz[None, None, :]

    def _evict(self, lo: np.ndarray, hi: np.ndarray, keep: bool = True) -> np.ndarray:
        gx, gy, gz = self._grid(lo, hi)
        mask = self.mask[gx, gy, gz]
        local = torch.nonzero(mask)
        indices = local.cpu().numpy() + lo
        if local.shape[0] and keep:
            x, y, z = gx[local[:, 0], 0, 0], gy[0, local[:, 1], 0], gz[0, 0, local[:, 2]]
            rows = self.alpha[:, x, y, z].T.cpu().numpy()
            marks = mask[local[:, 0], local[:, 1], local[:, 2]].cpu().numpy() if self.track_changes else None
            self._write_back(indices, rows, marks)  # the host window's admission: a full store drops the same
        self.alpha[:, gx, gy, gz] = float(self.prior)
        self.mask[gx, gy, gz] = 0
        self._columns_left(*self._physical(lo, hi))
        return indices

    def _load(self, lo: np.ndarray, hi: np.ndarray) -> None:
        linear, alpha = self.store.take_window(lo, hi - lo)
        if linear.size == 0:
            return
        on_host = (unravel_linear(linear, hi - lo) + lo) % self.dims
        physical = torch.as_tensor(on_host, device=self.device)
        x, y, z = physical[:, 0], physical[:, 1], physical[:, 2]
        self.alpha[:, x, y, z] = torch.as_tensor(alpha, device=self.device).T
        self.mask[x, y, z] = EVIDENCE
        self._columns_loaded(on_host, alpha)

    def _in_host_memory(self) -> bool:
        return self.device.type == "cpu"

    def _host_alpha(self) -> np.ndarray:
        return self.alpha.numpy()

    def clear(self) -> None:
        self.alpha.fill_(float(self.prior))
        self.mask.fill_(0)
        self.origin = None
        self._evicted_changes.clear()
        self._columns_cleared()

    def _gather(self, select: int, clear: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(global indices, alpha) of the voxels with a bit of ``select``; then clear ``clear``."""
        physical = torch.nonzero(self.mask & select)
        x, y, z = physical[:, 0], physical[:, 1], physical[:, 2]
        rows = self.alpha[:, x, y, z].T.cpu().numpy()
        if clear:
            self.mask[x, y, z] &= 0xFF ^ clear
        physical = physical.cpu().numpy()
        return self.origin + (physical - self.origin) % self.dims, rows

    def records(self, resolution: float, palette: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``records.window_records`` made on the device (the statistics in the compiled
        outputs' arithmetic: float32, classes summed in order, the first largest class), in the
        same torus order; one copy of the records, not of the concentrations, to the host."""
        physical = torch.nonzero(self.mask)
        if out is not None and len(out) != physical.shape[0]:
            raise ValueError(f"output has {len(out)} records, the window {physical.shape[0]} voxels")
        records = self._records_at(physical, resolution, palette)
        if out is None:
            return records
        out[:] = records
        return out

    def take_change_records(self, resolution: float, palette: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``take_changes`` as (global indices, records): the window's changed voxels become
        records on the device (records and indices come to the host, not concentrations); those
        that left the window with changes are already on the host."""
        if not self.track_changes:
            raise RuntimeError("this window does not track changes (track_changes=False)")
        parts = [(indices, records_from_alpha(indices, rows, resolution, palette))
                 for indices, rows in self._evicted_changes]
        self._evicted_changes = []
        if self.origin is not None:
            physical = torch.nonzero(self.mask & CHANGED)
            records = self._records_at(physical, resolution, palette)
            self.mask[physical[:, 0], physical[:, 1], physical[:, 2]] &= 0xFF ^ CHANGED
            parts.append((self.origin + (physical.cpu().numpy() - self.origin) % self.dims, records))
        if not parts:
            return np.zeros((0, 3), np.int64), np.zeros(0, RECORD)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def _records_at(self, physical: torch.Tensor, resolution: float, palette: np.ndarray) -> np.ndarray:
        """The records of the window's voxels at ``physical`` (N, 3) on the device."""
        count = physical.shape[0]
        x, y, z = physical[:, 0], physical[:, 1], physical[:, 2]
        values = self.alpha[:, x, y, z]
        total, top = values[0].clone(), values[0].clone()
        best = torch.zeros(count, dtype=torch.int64, device=self.device)
        for c in range(1, values.shape[0]):
            total += values[c]
            larger = values[c] > top
            top = torch.where(larger, values[c], top)
            best = torch.where(larger, c, best)
        expected = torch.where(total > 0, top / total, 0.0)
        variance = expected * (1.0 - expected) / (1.0 + total)
        origin = torch.as_tensor(self.origin, device=self.device)
        dims = torch.as_tensor(self.dims, device=self.device)
        centres = ((origin + torch.remainder(physical - origin, dims)).to(torch.float64) + 0.5) * float(resolution)
        colours = torch.as_tensor(np.asarray(palette, np.uint32).astype(np.int64), device=self.device)[best]
        words = torch.stack([*centres.to(torch.float32).view(torch.int32).T, colours.to(torch.int32),
                             best.to(torch.int32), variance.view(torch.int32), expected.view(torch.int32)], dim=1)
        return words.cpu().numpy().view(RECORD).reshape(count)

    def take_changes(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.track_changes:
            raise RuntimeError("this window does not track changes (track_changes=False)")
        parts = self._evicted_changes
        self._evicted_changes = []
        if self.origin is not None:
            parts.append(self._gather(CHANGED, clear=CHANGED))
        if not parts:
            return np.zeros((0, 3), np.int64), np.zeros((0, self.num_classes), np.float32)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def lookup(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        physical = torch.as_tensor(np.asarray(indices, np.int64) % self.dims, device=self.device)
        x, y, z = physical[:, 0], physical[:, 1], physical[:, 2]
        return self.alpha[:, x, y, z].T.cpu().numpy(), (self.mask[x, y, z] != 0).cpu().numpy()

    def items(self, indices: np.ndarray | None = None,
              alpha: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if self.origin is None:
            if indices is not None and alpha is not None:
                return indices, alpha
            return np.zeros((0, 3), np.int64), np.zeros((0, self.num_classes), np.float32)
        found, rows = self._gather(0xFF)
        if indices is not None and alpha is not None:
            indices[:], alpha[:] = found, rows
            return indices, alpha
        return found, rows


class TorchFilters:
    """A kernel's filters as the torch scatter reads them, on the window's device."""

    def __init__(self, plan: FilterPlan, device: torch.device):
        num_classes, size = plan.filters.shape[0], plan.filters.shape[1]
        half = size // 2
        taps = np.argwhere(plan.support.reshape(num_classes, size, size, size) != 0)  # (class, i, j, k)
        self.tap_class = torch.as_tensor(taps[:, 0], device=device)
        # conv3d's tap [i, j, k] carries F[v] to v + half - (i, j, k).
        self.tap_offset = torch.as_tensor(half - taps[:, 1:], device=device)
        self.tap_weight = torch.as_tensor(plan.filters[taps[:, 0], taps[:, 1], taps[:, 2], taps[:, 3]],
                                          device=device)
        # Per class, its taps: [starts[c], starts[c + 1]).
        counts = np.bincount(taps[:, 0], minlength=num_classes)
        self.starts = np.concatenate([[0], np.cumsum(counts)])


def torch_update(volume: SparseVolume, filters: TorchFilters, window: TorchWindow, marks: int) -> int:
    """Add conv3d(F, K) of the scan's occupied voxels into the device window; returns the
    number of voxels that received evidence for the first time."""
    device = window.device
    dims = torch.as_tensor(window.dims, device=device)
    origin = torch.as_tensor(volume.origin, device=device)
    occupied = torch.as_tensor(unravel_linear(volume.linear, volume.dims) + volume.origin, device=device)
    features = torch.as_tensor(volume.features, device=device)
    volume.on_device = occupied, features
    voxel, cls = torch.nonzero(features, as_tuple=True)  # the (voxel, class) pairs with evidence
    # Every tap of every pair: for pair p with class c, the taps starts[c] .. starts[c + 1].
    starts = torch.as_tensor(filters.starts, device=device)
    per_pair = starts[cls + 1] - starts[cls]
    pair = torch.repeat_interleave(torch.arange(len(cls), device=device), per_pair)
    first = torch.cumsum(per_pair, 0) - per_pair
    tap = starts[cls][pair] + torch.arange(len(pair), device=device) - first[pair]
    target = occupied[voxel[pair]] + filters.tap_offset[tap]
    inside = ((target >= origin) & (target < origin + dims)).all(dim=1)
    target, tap, pair = target[inside], tap[inside], pair[inside]
    physical = torch.remainder(target, dims)
    flat = (physical[:, 0] * dims[1] + physical[:, 1]) * dims[2] + physical[:, 2]
    num_voxels = int(torch.prod(dims))
    values = features[voxel[pair], cls[pair]] * filters.tap_weight[tap]
    window.alpha.view(-1).index_add_(0, cls[pair] * num_voxels + flat, values)
    touched = torch.unique(flat)
    mask = window.mask.view(-1)
    new = int(torch.count_nonzero(mask[touched] == 0))
    mask[touched] |= marks
    return new


def torch_free_space(counts: np.ndarray, free_filter: np.ndarray, window: TorchWindow,
                     ground_classes: tuple[int, ...] = ()) -> int:
    """Add a scan's ray counts (host (X, Y, Z), torus order, as the free-space pass counts them)
    as free evidence in the device window: through the free filter, at the voxels with
    evidence that this scan's class evidence did not reach and whose most likely occupied
    class is not one of ``ground_classes`` (derived for the whole window: cheap on a GPU);
    clears ``TOUCHED``. Returns the number of voxels whose free concentration grew."""
    device = window.device
    evidence = torch.as_tensor(counts, device=device)
    size = free_filter.shape[0]
    if np.count_nonzero(free_filter) > 1 or free_filter[size // 2, size // 2, size // 2] != 1:
        # Spread in window-local order (zero padding at the window's faces), then back to the torus.
        shift = tuple(int(s) for s in (-window.origin) % window.dims)
        local = torch.roll(evidence, shift, dims=(0, 1, 2))
        kernel = torch.as_tensor(free_filter, device=device)[None, None]
        local = torch.nn.functional.conv3d(local[None, None], kernel, padding=size // 2)[0, 0]
        evidence = torch.roll(local, tuple(-s for s in shift), dims=(0, 1, 2))
    takes = ((window.mask & EVIDENCE) != 0) & ((window.mask & TOUCHED) == 0) & (evidence > 0)
    if ground_classes:
        takes &= ~ground_marks(window.alpha, class_bits(ground_classes), int(window.origin[2]), window.prior)
    window.alpha[FREE_CLASS] += torch.where(takes, evidence, torch.zeros((), device=device))
    window.mask |= takes.to(torch.uint8) * CHANGED
    window.mask &= 0xFF ^ (TOUCHED | RECLASSED)  # the ground is derived for the whole window above
    return int(torch.count_nonzero(takes))

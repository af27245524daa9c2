"""The active window: the local map around the sensor, dense, in memory, on a torus.

The paper fetches the local window from the global map before every update and writes it
back after. Here the window stays resident as dense concentrations alpha[c, x, y, z]
(class-major) plus a byte mask of voxels that hold evidence; global voxel g lives at
index g mod dims (a torus), so when the sensor moves only the slabs that leave the
window are written to the global ``VoxelStore`` and the slabs that enter are read from it.
Voxels without evidence hold the prior, so an update is a plain in-place addition.

Every voxel with evidence is in exactly one place: in the window (mask set) or in the store.
A store that is full (its memory budget, ``budget``) may drop voxels leaving the window: they
leave the map, and with ``track_changes`` are reported as removed (``take_dropped``).

The mask's main bits: ``EVIDENCE`` (the voxel holds evidence) and ``CHANGED`` (its
concentrations changed since the map's changes were last taken). With ``track_changes``,
a changed voxel that leaves the window before its change is taken is remembered, so
``take_changes`` misses nothing; outputs that send only what changed are built on it.

Once a reader asks (``classes_by_column``), the window also keeps per column the classes that
may be above the prior there (``column_classes``). The gather of the voxels the mask selects
(``gather_window``), compiled, is here too.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.grid import unravel_linear, voxel_keys
from convbki_core.memory.column_classes import MAX_CLASS_BITS, _note_scan_classes, classes_held, row_class_bits
from convbki_core.memory.store import VoxelStore

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

# Bits of the window's byte mask: the voxel holds evidence; its concentrations changed since
# the map's changes were last taken (``RollingWindow.take_changes``); it received class
# evidence from the scan being integrated (set and cleared within one update, with free space).
EVIDENCE = 1
CHANGED = 2
TOUCHED = 4
# Kept for free space (``free_space``): the voxel holds the ground's surface, so rays leave
# it; its classes, or those of a voxel next to it along z, changed (a scan's update, it came
# from the store, the window moved along z, clamping) since that bit was derived.
GROUND = 16
RECLASSED = 32


def box_difference(first_lo: np.ndarray, first_hi: np.ndarray, second_lo: np.ndarray,
                   second_hi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Disjoint boxes (lo, hi exclusive) covering ``first`` minus ``second`` (at most 6 boxes)."""
    boxes = []
    lo, hi = first_lo.copy(), first_hi.copy()
    for axis in range(3):
        if second_hi[axis] <= lo[axis] or second_lo[axis] >= hi[axis]:  # no overlap at all
            return [*boxes, (lo, hi)]
        if lo[axis] < second_lo[axis]:
            below_hi = hi.copy()
            below_hi[axis] = second_lo[axis]
            boxes.append((lo.copy(), below_hi))
            lo[axis] = second_lo[axis]
        if hi[axis] > second_hi[axis]:
            above_lo = lo.copy()
            above_lo[axis] = second_hi[axis]
            boxes.append((above_lo, hi.copy()))
            hi[axis] = second_hi[axis]
    return boxes


class RollingWindow:
    """Dense window of ``dims`` voxels over the global grid, backed by a ``VoxelStore``."""

    def __init__(self, dims: np.ndarray, num_classes: int, prior: float, store: VoxelStore,
                 track_changes: bool = False):
        self.dims = np.asarray(dims, np.int64)
        self.num_classes = int(num_classes)
        self.prior = np.float32(prior)
        self.store = store
        self._allocate()
        # Scratch table for the compiled voxeliser (voxel -> row of F), -1 between scans.
        self.slot = np.full(int(np.prod(self.dims)), -1, np.int32)
        self.origin: np.ndarray | None = None
        # Changed voxels that left the window before their change was taken: (indices, alpha),
        # kept only for a map whose changes are taken (``track_changes``), or they would pile up.
        self.track_changes = bool(track_changes)
        self._evicted_changes: list[tuple[np.ndarray, np.ndarray]] = []
        self._dropped: list[np.ndarray] = []  # voxels a full store dropped, untaken (with track_changes)
        # Per column (X, Y) uint64: bit c set where class c may be above the prior somewhere in
        # the column; None until a reader asks for it (``classes_by_column``).
        self._class_columns: np.ndarray | None = None
        self._column_scratch: np.ndarray | None = None  # (2, X, Y) zeros for ``note_scan``

    def _allocate(self) -> None:
        """The window's arrays: concentrations at the prior, no evidence. Every page is written
        now (np.zeros alone maps them lazily), so the first scan does not pay for the faults."""
        self.alpha = np.full((self.num_classes, *self.dims.tolist()), self.prior, np.float32)
        self.mask = np.full(self.dims.tolist(), 0, np.uint8)

    @property
    def nbytes(self) -> int:
        return self.alpha.nbytes + self.mask.nbytes + self.slot.nbytes

    def count(self) -> int:
        """Voxels with evidence inside the window."""
        return int(np.count_nonzero(self.mask)) if self.origin is not None else 0

    def _physical(self, lo: np.ndarray, hi: np.ndarray):
        """Index arrays (for np.ix_) of the torus positions of the global box [lo, hi)."""
        return tuple(np.arange(lo[a], hi[a]) % self.dims[a] for a in range(3))

    def _evict(self, lo: np.ndarray, hi: np.ndarray, keep: bool = True) -> np.ndarray:
        """Move the evidence of global box [lo, hi) to the store (``keep``) or drop it, and reset
        the box to the prior; returns the global indices (n, 3) of the voxels that held evidence."""
        px, py, pz = self._physical(lo, hi)
        mask = self.mask[np.ix_(px, py, pz)]
        local = np.argwhere(mask)
        if local.size and keep:
            rows = self.alpha[:, px[local[:, 0]], py[local[:, 1]], pz[local[:, 2]]].T
            marks = mask[local[:, 0], local[:, 1], local[:, 2]] if self.track_changes else None
            self._write_back(local + lo, rows, marks)
        self.alpha[np.ix_(np.arange(self.num_classes), px, py, pz)] = self.prior
        self.mask[np.ix_(px, py, pz)] = 0
        self._columns_left(px, py, pz)
        return local + lo

    def _write_back(self, indices: np.ndarray, rows: np.ndarray, marks: np.ndarray | None) -> None:
        """Write voxels leaving the window (global ``indices`` (n, 3), ``rows`` (n, C), their mask
        bytes ``marks`` when changes are tracked) to the store. Those a full store drops
        (``budget``) have left the map: with ``track_changes`` they are removals
        (``take_dropped``), and no change of theirs is kept to bring them back."""
        dropped = self.store.write(indices, rows)
        if marks is None:
            return
        changed = (marks & CHANGED) != 0
        if dropped.size:
            changed[dropped] = False
            gone = voxel_keys(indices[dropped])
            self._evicted_changes = [(kept[keep], alpha[keep]) for kept, alpha in self._evicted_changes
                                     for keep in [~np.isin(voxel_keys(kept), gone)]]
            self._dropped.append(indices[dropped])
        if changed.any():
            self._evicted_changes.append((indices[changed], rows[changed]))

    def forget_evicted_changes(self) -> None:
        """Let the changes of voxels that left the window go: the map's next changes are all of
        it anyway (a correction's map mapping again, a loaded map), and they would pile up."""
        self._evicted_changes = []

    def take_dropped(self) -> np.ndarray:
        """Global indices (n, 3) of the voxels a full store dropped since the last call (kept only
        with ``track_changes``): they left the map."""
        dropped = np.concatenate(self._dropped) if self._dropped else np.zeros((0, 3), np.int64)
        self._dropped = []
        return dropped

    def _load(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Bring the stored voxels of global box [lo, hi) into the window."""
        linear, alpha = self.store.take_window(lo, hi - lo)
        if linear.size == 0:
            return
        physical = (unravel_linear(linear, hi - lo) + lo) % self.dims
        self.alpha[:, physical[:, 0], physical[:, 1], physical[:, 2]] = alpha.T
        self.mask[physical[:, 0], physical[:, 1], physical[:, 2]] = EVIDENCE | RECLASSED
        self._columns_loaded(physical, alpha)

    # -- which classes each column holds -----------------------------------------------------
    def classes_by_column(self) -> np.ndarray | None:
        """(X, Y) uint64 by physical column: bit c set where class c may hold more than the prior
        in the column (every run whose bit is clear holds exactly the prior). The first call
        reads the whole window and from then on the window keeps the bits current. None for a
        window of more than ``MAX_CLASS_BITS`` classes or whose arrays are not in host memory."""
        if self.num_classes > MAX_CLASS_BITS or not self._in_host_memory():
            return None
        if self._class_columns is None:
            self._class_columns = classes_held(self._host_alpha(), self.prior)
            self._column_scratch = np.zeros((2, *self._class_columns.shape), np.uint64)
        return self._class_columns

    def _in_host_memory(self) -> bool:
        return True

    def _host_alpha(self) -> np.ndarray:
        return self.alpha

    def note_scan(self, volume, half: int) -> None:
        """A scan's evidence was added: its classes may now be above the prior in the columns
        within ``half`` (the filter's half-width) of its occupied voxels (``SparseVolume``
        ``volume``, placed on this window's origin)."""
        if self._class_columns is None or volume.num_voxels == 0:
            return
        _note_scan_classes(volume.linear, volume.features, np.asarray(self.origin, np.int64), self.dims, int(half),
                           self._class_columns, self._column_scratch)

    def _columns_left(self, px: np.ndarray, py: np.ndarray, pz: np.ndarray) -> None:
        """Columns emptied whole (the window moved along x or y) hold no class any more."""
        if self._class_columns is not None and len(pz) == self.dims[2]:
            self._class_columns[np.ix_(px, py)] = 0

    def _columns_loaded(self, physical: np.ndarray, alpha: np.ndarray) -> None:
        """Voxels came back from the store: their classes above the prior, per column."""
        if self._class_columns is None or not len(physical):
            return
        np.bitwise_or.at(self._class_columns, (physical[:, 0], physical[:, 1]), row_class_bits(alpha != self.prior))

    def _columns_cleared(self) -> None:
        """The window was emptied: no column holds a class."""
        if self._class_columns is not None:
            self._class_columns.fill(0)

    def move_to(self, origin: np.ndarray) -> None:
        """Make the window cover global indices origin .. origin + dims - 1."""
        origin = np.asarray(origin, np.int64)
        if self.origin is not None and np.array_equal(origin, self.origin):
            return
        new_lo, new_hi = origin, origin + self.dims
        if self.origin is None:
            self._load(new_lo, new_hi)
        else:
            old_lo, old_hi = self.origin, self.origin + self.dims
            for lo, hi in box_difference(old_lo, old_hi, new_lo, new_hi):
                self._evict(lo, hi)
            for lo, hi in box_difference(new_lo, new_hi, old_lo, old_hi):
                self._load(lo, hi)
            if origin[2] != self.origin[2]:
                self._mark_z_ends(origin)
        self.origin = origin.copy()

    def _mark_z_ends(self, origin: np.ndarray) -> None:
        """The window moved along z: its new bottom and top layers have new neighbours along z
        (or none), which a voxel's ground bit depends on: their voxels are ``RECLASSED``."""
        size_z = int(self.dims[2])
        for layer in (int(origin[2]) % size_z, (int(origin[2]) + size_z - 1) % size_z):
            plane = self.mask[:, :, layer]
            plane |= (plane & EVIDENCE) * RECLASSED

    def warm_up(self, scratch) -> None:
        """Moves of the scratch window (``parts.Scratch``, a window of this kind) along every
        axis and back, with the scan's evidence in it: its classes by column kept from a scan,
        slabs to its store and back, the changes taken, the voxels listed and looked up, a box
        forgotten, the window flushed."""
        window = scratch.window
        window.classes_by_column()  # from now on kept by the window: its scans and moves below
        window.note_scan(scratch.volume, 2)
        for origin in scratch.origins():
            window.move_to(origin)
            window.take_changes()
        indices, _ = window.items()
        window.lookup(indices[window.inside(indices)])
        window.forget_box(scratch.origin, scratch.origin + 2)
        window.flush()

    def flush(self) -> None:
        """Move everything to the store and forget the window's position."""
        if self.origin is not None:
            self._evict(self.origin, self.origin + self.dims)
        self.origin = None

    def clear(self) -> None:
        """Drop every voxel of the window (the store is cleared by its owner)."""
        self.alpha.fill(self.prior)
        self.mask.fill(0)
        self.origin = None
        self._evicted_changes.clear()
        self._columns_cleared()

    def forget_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Drop the evidence of the window's voxels in the global box [lo, hi) (and the changes
        of voxels in it that left the window untaken); returns the indices (n, 3) dropped."""
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        self._evicted_changes = [(indices[~inside], alpha[~inside]) for indices, alpha in self._evicted_changes
                                 for inside in [((indices >= lo) & (indices < hi)).all(axis=1)]]
        if self.origin is None:
            return np.zeros((0, 3), np.int64)
        lo, hi = np.maximum(lo, self.origin), np.minimum(hi, self.origin + self.dims)
        if (hi <= lo).any():
            return np.zeros((0, 3), np.int64)
        return self._evict(lo, hi, keep=False)

    def take_changes(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxels whose concentrations changed since the last call, in the window or since
        moved to the store: (global indices (n, 3), alpha (n, C)); their marks are cleared.
        Needs ``track_changes``."""
        if not self.track_changes:
            raise RuntimeError("this window does not track changes (track_changes=False)")
        parts = self._evicted_changes
        self._evicted_changes = []
        if self.origin is not None:
            parts.append(gather_window(self.alpha, self.mask, self.origin, self.dims, select=CHANGED,
                                       clear=CHANGED))
        if not parts:
            return np.zeros((0, 3), np.int64), np.zeros((0, self.num_classes), np.float32)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def inside(self, indices: np.ndarray) -> np.ndarray:
        """(N,) bool: global indices inside the current window."""
        if self.origin is None:
            return np.zeros(len(indices), bool)
        local = indices - self.origin
        return (local >= 0).all(axis=1) & (local < self.dims).all(axis=1)

    def lookup(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Concentrations at global ``indices`` that lie inside the window: (alpha (n, C), has_evidence (n,))."""
        physical = np.asarray(indices, np.int64) % self.dims
        has = self.mask[physical[:, 0], physical[:, 1], physical[:, 2]].astype(bool)
        alpha = self.alpha[:, physical[:, 0], physical[:, 1], physical[:, 2]].T
        return alpha, has

    def items(self, indices: np.ndarray | None = None,
              alpha: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Voxels with evidence in the window: (global indices (n, 3), alpha (n, C)), in torus order.

        ``indices``/``alpha`` of ``count()`` rows: fill these instead of new arrays.
        """
        if self.origin is None:
            if indices is not None and alpha is not None:
                return indices, alpha
            return np.zeros((0, 3), np.int64), np.zeros((0, self.num_classes), np.float32)
        return gather_window(self.alpha, self.mask, self.origin, self.dims, indices, alpha)


if HAVE_NUMBA:

    @njit(parallel=True, nogil=True)
    def plane_starts(mask, select):  # pragma: no cover - compiled
        """Where each x plane's voxels with a bit of ``select`` start in a gathered output: the
        running count over the planes (X + 1 entries, the last one the total), so that the
        planes can then be gathered in parallel."""
        size_x, size_y, size_z = mask.shape
        counts = np.zeros(size_x + 1, np.int64)
        for x in prange(size_x):
            found = 0
            for y in range(size_y):
                for z in range(size_z):
                    if mask[x, y, z] & select != 0:
                        found += 1
            counts[x + 1] = found
        return np.cumsum(counts)

    @njit(parallel=True, nogil=True)
    def _gather_window_numba(alpha, mask, origin, dims, indices, values, select, keep):  # pragma: no cover
        size_x, size_y, size_z = mask.shape
        num_classes = alpha.shape[0]
        starts = plane_starts(mask, select)
        if starts[-1] != indices.shape[0]:
            return -1  # the caller's count of the mask was wrong: write nothing
        for x in prange(size_x):
            row = starts[x]
            global_x = origin[0] + (x - origin[0]) % dims[0]
            for y in range(size_y):
                global_y = origin[1] + (y - origin[1]) % dims[1]
                for z in range(size_z):
                    if mask[x, y, z] & select != 0:
                        indices[row, 0] = global_x
                        indices[row, 1] = global_y
                        indices[row, 2] = origin[2] + (z - origin[2]) % dims[2]
                        for c in range(num_classes):
                            values[row, c] = alpha[c, x, y, z]
                        mask[x, y, z] &= keep
                        row += 1
        return starts[-1]


def gather_window(alpha: np.ndarray, mask: np.ndarray, origin: np.ndarray, dims: np.ndarray,
                  indices: np.ndarray | None = None, values: np.ndarray | None = None,
                  select: int = EVIDENCE, clear: int = 0):
    """Voxels of the torus window whose ``mask`` has a bit of ``select``: (global indices (n, 3),
    alpha (n, C)), torus order; the bits ``clear`` are then cleared in them.

    One compiled pass instead of ``alpha[:, argwhere(mask)]``, which gathers each of the C
    class planes separately (an order of magnitude slower); the node does this
    for every map it publishes. ``indices``/``values`` (n rows, n = the voxels selected):
    write into these (e.g. slices of a larger array) instead of new arrays.
    """
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    if indices is None or values is None:
        count = int(np.count_nonzero(mask & select)) if select != EVIDENCE else int(np.count_nonzero(mask))
        indices = np.empty((count, 3), np.int64)
        values = np.empty((count, alpha.shape[0]), np.float32)
    if HAVE_NUMBA:
        with parallel_region():
            gathered = _gather_window_numba(alpha, mask, origin, dims, indices, values, np.uint8(select),
                                            np.uint8(~clear & 0xFF))
        if gathered != indices.shape[0]:
            raise ValueError(f"output has {indices.shape[0]} rows, the window "
                             f"{int(np.count_nonzero(mask & select))} selected voxels")
        return indices, values
    physical = np.argwhere(mask & select)
    if physical.shape[0] != indices.shape[0]:
        raise ValueError(f"output has {indices.shape[0]} rows, the window {physical.shape[0]} selected voxels")
    values[:] = alpha[:, physical[:, 0], physical[:, 1], physical[:, 2]].T
    # Unwrap the torus: the global index is the one in [origin, origin + dims) with this remainder.
    indices[:] = origin + (physical - origin) % dims
    mask[physical[:, 0], physical[:, 1], physical[:, 2]] &= np.uint8(~clear & 0xFF)
    return indices, values

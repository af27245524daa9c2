"""The global map store: every voxel with evidence, addressed by its global index.

The paper keeps the global map as one key/value matrix and scans all of it to fetch the
local window, so the fetch slows down as the map grows. Here voxels live in a hash of
chunks (16 x 16 x 16 voxels each); fetching or writing back a window touches only the
chunks that overlap it, so the cost follows the window, not the map.

A voxel's row starts at the prior in every class and grows only in the few classes that
received evidence (one to three of twenty, typically). So a chunk keeps, per voxel, its
12-bit chunk-local offset (uint16, sorted) and the number of classes whose value is not
the prior (uint8); and per such class its id (uint8) and its float32 value, kept as the
bit pattern (uint32). Classes left out are exactly the prior, so rows come back bit for bit.
Rows go in and out dense, (n, C) float32; ``compact_rows`` does the packing.

Resident bytes are a running total, so a byte budget (``set_budget``) costs O(1) per chunk
written: under it the store is as if it had none, bit for bit; at it the map stops growing (``budget``).
"""

from __future__ import annotations

import sys

import numpy as np

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.geometry.grid import linear_index, unravel_linear, voxel_keys
from convbki_core.memory.budget import MemoryState, StoreBudget
from convbki_core.memory.compact_rows import compress_rows, entry_ranges, entry_starts, expand_rows

if HAVE_NUMBA:
    from convbki_core.compiled import njit

CHUNK_SHIFT = 4
CHUNK_EDGE = 1 << CHUNK_SHIFT
_MASK = CHUNK_EDGE - 1


class _Chunk:
    """The voxels of one chunk; every array owns its memory (no views of shared buffers)."""

    # (__weakref__: a scan log folder notes where it wrote a chunk, for as long as the chunk lives)
    __slots__ = ("__weakref__", "classes", "counts", "offsets", "values")

    def __init__(self, offsets: np.ndarray, counts: np.ndarray, classes: np.ndarray, values: np.ndarray):
        self.offsets = offsets  # (n,) uint16 sorted chunk-local offsets (x << 8 | y << 4 | z)
        self.counts = counts  # (n,) uint8: classes of the voxel stored below
        self.classes = classes  # (m,) uint8 class ids, ascending within a voxel
        self.values = values  # (m,) uint32 float32 bit patterns


def _per_chunk_bytes() -> int:
    """Python memory a chunk adds besides its array data: the chunk object, four array headers
    (plus the allocator's header of each data block, 16 bytes), the key tuple and its ints."""
    array = np.zeros(1, np.uint8)
    header = sys.getsizeof(array) - array.nbytes + 16
    empty = np.zeros(0, np.uint8)
    key = (1 << 20, 1 << 20, 1 << 20)  # ints beyond the small-int cache, as far from the origin
    chunk = _Chunk(empty, empty, empty, empty)
    return sys.getsizeof(chunk) + 4 * header + sys.getsizeof(key) + 3 * sys.getsizeof(key[0])


_PER_CHUNK_BYTES = _per_chunk_bytes()


def _chunk_bytes(chunk: _Chunk) -> int:
    """The bytes of a chunk's arrays (``VoxelStore.nbytes`` counts these)."""
    return chunk.offsets.nbytes + chunk.counts.nbytes + chunk.classes.nbytes + chunk.values.nbytes


def _subset(chunk: _Chunk, keep: np.ndarray) -> _Chunk:
    """A new chunk of the voxels of ``chunk`` where ``keep`` (n,) bool is set."""
    entries = np.repeat(keep, chunk.counts)
    return _Chunk(chunk.offsets[keep], chunk.counts[keep], chunk.classes[entries], chunk.values[entries])


def _chunk_keys(indices: np.ndarray) -> np.ndarray:
    return indices >> CHUNK_SHIFT  # arithmetic shift: floor division, right for negatives


def _local_offsets(indices: np.ndarray) -> np.ndarray:
    local = indices & _MASK
    return ((local[:, 0] << (2 * CHUNK_SHIFT)) | (local[:, 1] << CHUNK_SHIFT) | local[:, 2]).astype(np.uint16)


def _decode_offsets(offsets: np.ndarray) -> np.ndarray:
    offsets = offsets.astype(np.int64)
    return np.stack([offsets >> (2 * CHUNK_SHIFT), (offsets >> CHUNK_SHIFT) & _MASK, offsets & _MASK], axis=1)


if HAVE_NUMBA:

    @njit(nogil=True)
    def _window_linear_numba(offsets, first, shift, dims, linear, inside):  # pragma: no cover - compiled
        for k in range(first.size - 1):
            count = 0
            for i in range(first[k], first[k + 1]):
                offset = np.int64(offsets[i])
                x = (offset >> 8) + shift[k, 0]
                y = ((offset >> 4) & 15) + shift[k, 1]
                z = (offset & 15) + shift[k, 2]
                if 0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]:
                    linear[i] = (x * dims[1] + y) * dims[2] + z
                    count += 1
                else:
                    linear[i] = -1
            inside[k] = count

    @njit(nogil=True)
    def _merge_numba(old_offsets, old_counts, old_classes, old_values, new_offsets, new_counts, new_classes,
                     new_values, offsets, counts, classes, values):  # pragma: no cover - compiled
        i = j = k = old_entry = new_entry = entry = 0
        while i < old_offsets.size or j < new_offsets.size:
            if j < new_offsets.size and (i == old_offsets.size or new_offsets[j] <= old_offsets[i]):
                if i < old_offsets.size and old_offsets[i] == new_offsets[j]:  # overwritten
                    old_entry += old_counts[i]
                    i += 1
                offsets[k], counts[k] = new_offsets[j], new_counts[j]
                for _ in range(new_counts[j]):
                    classes[entry], values[entry] = new_classes[new_entry], new_values[new_entry]
                    entry += 1
                    new_entry += 1
                j += 1
            else:
                offsets[k], counts[k] = old_offsets[i], old_counts[i]
                for _ in range(old_counts[i]):
                    classes[entry], values[entry] = old_classes[old_entry], old_values[old_entry]
                    entry += 1
                    old_entry += 1
                i += 1
            k += 1
        return k, entry


def _window_linear(offsets: np.ndarray, first: np.ndarray, shift: np.ndarray,
                   dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Window-linear index of each voxel (-1 outside) and the count inside per chunk.

    ``first``: (k + 1,) where each chunk's voxels begin; ``shift``: (k, 3) chunk base - origin."""
    if HAVE_NUMBA:
        linear, inside = np.empty(offsets.size, np.int64), np.empty(first.size - 1, np.int64)
        _window_linear_numba(offsets, first, shift, dims, linear, inside)
        return linear, inside
    local = _decode_offsets(offsets) + np.repeat(shift, np.diff(first), axis=0)
    within = (local >= 0).all(axis=1) & (local < dims).all(axis=1)
    linear = np.where(within, linear_index(local, dims), -1)
    return linear, np.add.reduceat(within.astype(np.int64), first[:-1])  # chunks are never empty


def _merge(old: _Chunk, offsets: np.ndarray, counts: np.ndarray, classes: np.ndarray, values: np.ndarray) -> _Chunk:
    """``old`` with the given voxels (sorted offsets) inserted or overwritten, as a new chunk."""
    if HAVE_NUMBA:  # into buffers with room for both, then trimmed: the chunk's arrays must own their memory
        buffers = [np.empty(a.size + b.size, a.dtype) for a, b in ((old.offsets, offsets), (old.counts, counts),
                                                                    (old.classes, classes), (old.values, values))]
        voxels, entries = _merge_numba(old.offsets, old.counts, old.classes, old.values, offsets, counts, classes,
                                       values, *buffers)
        return _Chunk(buffers[0][:voxels].copy(), buffers[1][:voxels].copy(), buffers[2][:entries].copy(),
                      buffers[3][:entries].copy())
    keep = ~np.isin(old.offsets, offsets, assume_unique=True)
    kept_entries = np.repeat(keep, old.counts)
    all_offsets = np.concatenate([old.offsets[keep], offsets])
    all_counts = np.concatenate([old.counts[keep], counts])
    sort = np.argsort(all_offsets, kind="stable")
    entries = entry_ranges(entry_starts(all_counts)[:-1][sort], all_counts[sort])
    return _Chunk(all_offsets[sort], all_counts[sort], np.concatenate([old.classes[kept_entries], classes])[entries],
                  np.concatenate([old.values[kept_entries], values])[entries])


class VoxelStore:
    """Sparse global map: voxel index (3 x int64) -> concentrations (C x float32).

    ``prior``: the concentration of a class without evidence; only other values take memory.
    ``budget_bytes`` / ``ceiling_bytes``: the map's memory budget and hard ceiling, as
    ``set_budget`` takes them (0: no bound, the default).
    """

    def __init__(self, num_classes: int, prior: float, budget_bytes: int = 0, ceiling_bytes: int | None = None):
        self.num_classes = int(num_classes)
        if self.num_classes < 1:
            raise ValueError(f"num_classes must be positive, got {num_classes}")
        self.prior = np.float32(prior)
        self._chunks: dict[tuple[int, int, int], _Chunk] = {}
        self._count = 0
        self._array_bytes = 0  # running sum of every chunk's ``_chunk_bytes``
        self.budget = StoreBudget(budget_bytes, ceiling_bytes)

    # -- size ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._count

    @property
    def nbytes(self) -> int:
        """Bytes held by the voxel arrays (offsets, counts, class ids, values), excluding Python overhead."""
        return self._array_bytes

    @property
    def resident_bytes(self) -> int:
        """``nbytes`` plus the Python bookkeeping: the chunk table and, per chunk, its objects. O(1)."""
        return self._array_bytes + sys.getsizeof(self._chunks) + _PER_CHUNK_BYTES * len(self._chunks)

    def recount_resident_bytes(self) -> int:
        """``resident_bytes`` summed afresh over every chunk (O(chunks)): what the running total must equal."""
        return (sum(_chunk_bytes(c) for c in self._chunks.values()) + sys.getsizeof(self._chunks)
                + _PER_CHUNK_BYTES * len(self._chunks))

    # -- the budget ------------------------------------------------------------------------
    def set_budget(self, budget_bytes: int, ceiling_bytes: int | None = None) -> None:
        """Bound the map's memory (``budget``): at ``budget_bytes`` (resident plus lent) the map
        is full, writes go only into chunks held or lent; at ``ceiling_bytes`` resident (default:
        the budget) none. 0: no bound. A store over a new budget keeps its voxels and is full."""
        self.budget.set(budget_bytes, ceiling_bytes)
        self.budget.note(self.resident_bytes)

    def memory_state(self) -> MemoryState:
        """The budget's state now: bytes, bound, full, voxels dropped, times it became full."""
        budget = self.budget
        resident = self.resident_bytes
        return MemoryState(resident, budget.lent_bytes, budget.budget_bytes, budget.ceiling_bytes,
                           budget.note(resident), budget.voxels_dropped, budget.times_full)

    def copy(self) -> VoxelStore:
        """A copy that shares every chunk with this store: a chunk is never changed in place (a
        write makes a new one), so each store goes on as if the other did not exist. The copy has
        this store's budget and counts; it lent nothing (the window is this store's)."""
        other = VoxelStore(self.num_classes, self.prior)
        other._chunks = dict(self._chunks)
        other._count = self._count
        other._array_bytes = self._array_bytes
        other.budget = self.budget.copy()
        return other

    def bytes_not_shared_with(self, other: VoxelStore) -> int:
        """The memory this store holds that ``other`` (a store it was copied from) does not share:
        its chunk table and the chunks written since the copy."""
        own = [c for key, c in self._chunks.items() if other._chunks.get(key) is not c]
        return sum(_chunk_bytes(c) for c in own) + sys.getsizeof(self._chunks) + _PER_CHUNK_BYTES * len(own)

    def clear(self) -> None:
        """Forget every voxel; the budget stays, and the map is no longer full (nothing lent or dropped)."""
        self._chunks.clear()
        self._count = 0
        self._array_bytes = 0
        self.budget.clear()

    def _replace_chunk(self, key: tuple[int, int, int], old: _Chunk | None, new: _Chunk | None) -> int:
        """Put ``new`` (None: nothing) in the place of ``old`` (None: nothing) at ``key``, keeping
        the running totals; returns the change of resident bytes (per-chunk overhead included)."""
        grown = ((_chunk_bytes(new) + _PER_CHUNK_BYTES if new is not None else 0)
                 - (_chunk_bytes(old) + _PER_CHUNK_BYTES if old is not None else 0))
        if new is None:
            del self._chunks[key]
        else:
            self._chunks[key] = new
        self._array_bytes += grown - _PER_CHUNK_BYTES * ((new is not None) - (old is not None))
        self._count += (new.offsets.size if new is not None else 0) - (old.offsets.size if old is not None else 0)
        return grown

    def _expand_chunks(self, chunks: list[_Chunk], positions: np.ndarray | None = None,
                       out: np.ndarray | None = None) -> np.ndarray:
        """Dense rows of the chunks' voxels (concatenated in order), all or those at ``positions``."""
        return expand_rows(np.concatenate([c.counts for c in chunks]), np.concatenate([c.classes for c in chunks]),
                           np.concatenate([c.values for c in chunks]), self.prior, self.num_classes, positions, out)

    # -- window access ---------------------------------------------------------------------
    def query_window(self, origin: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stored voxels inside the window: (linear (n,) int64 sorted, alpha (n, C) float32 copy)."""
        return self._collect_window(origin, dims, remove=False)

    def take_window(self, origin: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like ``query_window``, and the voxels leave the store (the caller now holds them)."""
        return self._collect_window(origin, dims, remove=True)

    def _collect_window(self, origin: np.ndarray, dims: np.ndarray, remove: bool) -> tuple[np.ndarray, np.ndarray]:
        origin = np.asarray(origin, np.int64)
        dims = np.ascontiguousarray(dims, np.int64)
        first, last = _chunk_keys(origin).tolist(), _chunk_keys(origin + dims - 1).tolist()
        keys, chunks = [], []
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    chunk = self._chunks.get((cx, cy, cz))
                    if chunk is not None:
                        keys.append((cx, cy, cz))
                        chunks.append(chunk)
        if not chunks:
            return np.zeros(0, np.int64), np.zeros((0, self.num_classes), np.float32)
        bounds = np.zeros(len(chunks) + 1, np.int64)
        np.cumsum([c.offsets.size for c in chunks], out=bounds[1:])
        shift = (np.array(keys, np.int64) << CHUNK_SHIFT) - origin
        linear, inside = _window_linear(np.concatenate([c.offsets for c in chunks]), bounds, shift, dims)
        selected = np.flatnonzero(linear >= 0)
        # Each chunk is already a sorted run of window-linear indices; numpy's stable sort of int64
        # (timsort) merges such runs instead of sorting from scratch.
        order = np.argsort(linear[selected], kind="stable")
        positions = selected[order]
        rows = self._expand_chunks(chunks, positions)
        if remove:
            bounded = bool(self.budget.budget_bytes)
            for key, chunk, count, start, end in zip(keys, chunks, inside.tolist(), bounds[:-1].tolist(),
                                                     bounds[1:].tolist()):
                if not count:
                    continue
                grown = self._replace_chunk(key, chunk, None if count == chunk.offsets.size else
                                            _subset(chunk, linear[start:end] < 0))
                if bounded:  # the map's all the same: what the window holds counts against the budget
                    self.budget.lend(key, -grown)
        return linear[positions], rows

    def write_window(self, origin: np.ndarray, dims: np.ndarray, linear: np.ndarray, alpha: np.ndarray) -> None:
        """Insert or overwrite the voxels at window-linear indices ``linear`` with ``alpha`` rows."""
        origin = np.asarray(origin, np.int64)
        self.write(unravel_linear(np.asarray(linear, np.int64), np.asarray(dims, np.int64)) + origin, alpha)

    def write(self, indices: np.ndarray, alpha: np.ndarray, bounded: bool = True) -> np.ndarray:
        """Insert or overwrite voxels at global ``indices`` (n, 3) with ``alpha`` (n, C) float32.

        An index given twice keeps its last row. With a budget (``set_budget``), a full map
        writes only into chunks it holds or lent, and nothing past the ceiling: the other rows
        are dropped (a row the store held at such an index stays) and counted. ``bounded``
        False: every row is written whatever the budget (a map file loaded, a log's base).
        Returns the positions (k,) int64 in ``indices`` of the rows dropped.
        """
        indices = np.asarray(indices, np.int64)
        alpha = np.ascontiguousarray(alpha, np.float32)
        if alpha.shape != (indices.shape[0], self.num_classes):
            raise ValueError(f"alpha must be ({indices.shape[0]}, {self.num_classes}), got {alpha.shape}")
        if indices.shape[0] == 0:
            return np.zeros(0, np.int64)
        keys = _chunk_keys(indices)
        offsets = _local_offsets(indices)
        order = np.lexsort((offsets, keys[:, 2], keys[:, 1], keys[:, 0]))
        keys, offsets = keys[order], offsets[order]
        # The sort is stable: of an index given twice, the last row is last; keep that one.
        last = np.append((keys[1:] != keys[:-1]).any(axis=1) | (offsets[1:] != offsets[:-1]), True)
        order, keys, offsets = order[last], keys[last], offsets[last]
        new_chunk = np.append(True, (keys[1:] != keys[:-1]).any(axis=1))
        counts, classes, values = compress_rows(alpha, self.prior, order)
        starts = entry_starts(counts)
        bounds = np.append(np.flatnonzero(new_chunk), order.size).tolist()
        budget = self.budget if bounded and self.budget.budget_bytes else None
        dropped = []
        for key, start, end in zip(map(tuple, keys[bounds[:-1]].tolist()), bounds[:-1], bounds[1:]):
            first, stop = int(starts[start]), int(starts[end])
            chunk = self._chunks.get(key)
            if budget is not None and not budget.admits(key, chunk is not None, self.resident_bytes):
                dropped.append(order[start:end])
                budget.voxels_dropped += end - start
                continue
            if chunk is None:
                new = _Chunk(offsets[start:end].copy(), counts[start:end].copy(), classes[first:stop].copy(),
                             values[first:stop].copy())
            else:
                new = _merge(chunk, offsets[start:end], counts[start:end], classes[first:stop], values[first:stop])
            grown = self._replace_chunk(key, chunk, new)
            if self.budget.lent:
                self.budget.returned(key, grown)
        if self.budget.budget_bytes:
            self.budget.note(self.resident_bytes)
        return np.concatenate(dropped) if dropped else np.zeros(0, np.int64)

    def forget_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Remove the stored voxels of the global box [lo, hi) (hi exclusive); returns their
        indices (n, 3). Visits only the chunks that overlap the box."""
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        first, last = _chunk_keys(lo).tolist(), _chunk_keys(hi - 1).tolist()
        overlapping = [key for key in self._chunks if all(first[a] <= key[a] <= last[a] for a in range(3))]
        removed = []
        for key in overlapping:
            chunk = self._chunks[key]
            indices = _decode_offsets(chunk.offsets) + (np.asarray(key, np.int64) << CHUNK_SHIFT)
            inside = ((indices >= lo) & (indices < hi)).all(axis=1)
            if not inside.any():
                continue
            removed.append(indices[inside])
            self._replace_chunk(key, chunk, None if inside.all() else _subset(chunk, ~inside))
        if self.budget.lent:  # chunks the box covers whole: what the window held of them is forgotten with it
            self.budget.release_inside(((lo + _MASK) >> CHUNK_SHIFT).tolist(), ((hi >> CHUNK_SHIFT) - 1).tolist())
        if self.budget.budget_bytes:
            self.budget.note(self.resident_bytes)
        return np.concatenate(removed) if removed else np.zeros((0, 3), np.int64)

    # -- point access ----------------------------------------------------------------------
    def lookup(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Concentrations at global voxel ``indices`` (n, 3): (alpha (n, C), found (n,) bool).

        Rows of voxels that are not stored are zero.
        """
        indices = np.asarray(indices, np.int64)
        alpha = np.zeros((indices.shape[0], self.num_classes), np.float32)
        found = np.zeros(indices.shape[0], bool)
        if indices.shape[0] == 0:
            return alpha, found
        keys = _chunk_keys(indices)
        offsets = _local_offsets(indices)
        unique_keys, group = np.unique(keys, axis=0, return_inverse=True)
        group = group.reshape(-1)
        order = np.argsort(group, kind="stable")
        boundaries = np.searchsorted(group[order], np.arange(unique_keys.shape[0] + 1))
        for number, key in enumerate(map(tuple, unique_keys.tolist())):
            chunk = self._chunks.get(key)
            if chunk is None:
                continue
            members = order[boundaries[number]:boundaries[number + 1]]
            position = np.minimum(np.searchsorted(chunk.offsets, offsets[members]), chunk.offsets.size - 1)
            hit = chunk.offsets[position] == offsets[members]
            alpha[members[hit]] = self._expand_chunks([chunk], position[hit])
            found[members[hit]] = True
        return alpha, found

    # -- whole map -------------------------------------------------------------------------
    def voxel_keys(self) -> np.ndarray:
        """Every stored voxel's linear key (``voxel_keys``), chunk order."""
        return np.concatenate([np.zeros(0, np.int64)] + [voxel_keys(_decode_offsets(c.offsets) + (
            np.asarray(k, np.int64) << CHUNK_SHIFT)) for k, c in self._chunks.items()])

    def items(self, indices: np.ndarray | None = None,
              alpha: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every stored voxel: (global indices (N, 3) int64, alpha (N, C) float32), chunk order.

        ``indices``/``alpha`` of ``len(self)`` rows: fill these instead of new arrays (the
        map's ``items()`` fills one array for store and window, with no second copy).
        """
        if indices is None or alpha is None:
            indices = np.empty((len(self), 3), np.int64)
            alpha = np.empty((len(self), self.num_classes), np.float32)
        row = 0
        for key, chunk in self._chunks.items():
            end = row + chunk.offsets.size
            if end > indices.shape[0]:
                break
            indices[row:end] = _decode_offsets(chunk.offsets) + (np.asarray(key, np.int64) << CHUNK_SHIFT)
            self._expand_chunks([chunk], out=alpha[row:end])
            row = end
        if row != indices.shape[0] or row != self._count:
            raise RuntimeError(f"store counted {self._count} voxels, was given {indices.shape[0]} rows")
        return indices, alpha


"""The global map store: every voxel with evidence, addressed by its global index.

The paper keeps the global map as one key/value matrix and scans all of it to fetch the
local window, so the fetch slows down as the map grows. Here voxels live in a hash of
chunks (16 x 16 x 16 voxels each); fetching or writing back a window touches only the
chunks that overlap it, so the cost follows the window, not the map.

Inside a chunk the voxels are kept sorted by their 12-bit chunk-local offset (int16) next
to their concentration rows (float32, C per voxel), about 4 * C + 2 bytes a voxel.

Chunks that have not overlapped a window for ``stale_after`` updates leave the active
table for an archive table; they are still part of the map (saved, exported, listed,
looked up) and come back to the active table when the sensor returns.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from convbki_core.voxelize import linear_index, unravel_linear

CHUNK_SHIFT = 4
CHUNK_EDGE = 1 << CHUNK_SHIFT
_MASK = CHUNK_EDGE - 1


@dataclass
class _Chunk:
    offsets: np.ndarray  # (n,) int16 sorted chunk-local offsets (x << 8 | y << 4 | z)
    alpha: np.ndarray  # (n, C) float32
    last_used: int = 0


def _chunk_keys(indices: np.ndarray) -> np.ndarray:
    return indices >> CHUNK_SHIFT  # arithmetic shift: floor division, right for negatives


def _local_offsets(indices: np.ndarray) -> np.ndarray:
    local = indices & _MASK
    return ((local[:, 0] << (2 * CHUNK_SHIFT)) | (local[:, 1] << CHUNK_SHIFT) | local[:, 2]).astype(np.int16)


def _decode_offsets(offsets: np.ndarray) -> np.ndarray:
    offsets = offsets.astype(np.int64)
    return np.stack([offsets >> (2 * CHUNK_SHIFT), (offsets >> CHUNK_SHIFT) & _MASK, offsets & _MASK], axis=1)


class VoxelStore:
    """Sparse global map: voxel index (3 x int64) -> concentrations (C x float32)."""

    def __init__(self, num_classes: int, stale_after: int = 20):
        self.num_classes = int(num_classes)
        self.stale_after = int(stale_after)
        self._active: dict[tuple[int, int, int], _Chunk] = {}
        self._archive: dict[tuple[int, int, int], _Chunk] = {}
        self._clock = 0
        self._count = 0

    # -- size ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._count

    @property
    def num_active_chunks(self) -> int:
        return len(self._active)

    @property
    def num_archived_chunks(self) -> int:
        return len(self._archive)

    @property
    def nbytes(self) -> int:
        """Bytes held by voxel arrays (keys and concentrations), excluding Python overhead."""
        return sum(c.offsets.nbytes + c.alpha.nbytes for c in self._chunks())

    @property
    def resident_bytes(self) -> int:
        """``nbytes`` plus the Python bookkeeping of the chunk tables (estimated per chunk:
        its key tuple, the chunk object and the two array headers)."""
        per_chunk = 200 + 3 * 28 + 2 * 112
        tables = sys.getsizeof(self._active) + sys.getsizeof(self._archive)
        return self.nbytes + tables + per_chunk * (len(self._active) + len(self._archive))

    def _chunks(self) -> Iterator[_Chunk]:
        yield from self._active.values()
        yield from self._archive.values()

    def clear(self) -> None:
        self._active.clear()
        self._archive.clear()
        self._count = 0

    # -- chunk access ----------------------------------------------------------------------
    def _get(self, key: tuple[int, int, int]) -> _Chunk | None:
        # The active table is kept in order of last use (a used chunk moves to the end), so
        # retiring stale chunks looks only at the front of it, not at every active chunk.
        chunk = self._active.pop(key, None)
        if chunk is None:
            chunk = self._archive.pop(key, None)
        if chunk is not None:
            self._active[key] = chunk
            chunk.last_used = self._clock
        return chunk

    def _window_chunk_keys(self, origin: np.ndarray, dims: np.ndarray):
        first = _chunk_keys(origin)
        last = _chunk_keys(origin + dims - 1)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    yield (cx, cy, cz)

    # -- window access ---------------------------------------------------------------------
    def query_window(self, origin: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stored voxels inside the window: (linear (n,) int64 sorted, alpha (n, C) float32 copy)."""
        return self._collect_window(origin, dims, remove=False)

    def take_window(self, origin: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like ``query_window``, and the voxels leave the store (the caller now holds them)."""
        return self._collect_window(origin, dims, remove=True)

    def _collect_window(self, origin: np.ndarray, dims: np.ndarray, remove: bool) -> tuple[np.ndarray, np.ndarray]:
        origin = np.asarray(origin, np.int64)
        dims = np.asarray(dims, np.int64)
        parts_index, parts_alpha = [], []
        for key in self._window_chunk_keys(origin, dims):
            chunk = self._get(key)
            if chunk is None or chunk.offsets.size == 0:
                continue
            base = np.asarray(key, np.int64) << CHUNK_SHIFT
            local = _decode_offsets(chunk.offsets) + (base - origin)
            inside = (local >= 0).all(axis=1) & (local < dims).all(axis=1)
            parts_index.append(local[inside])
            parts_alpha.append(chunk.alpha[inside])
            if remove and inside.any():
                self._count -= int(inside.sum())
                if inside.all():
                    del self._active[key]
                else:
                    chunk.offsets, chunk.alpha = chunk.offsets[~inside], chunk.alpha[~inside]
        if not parts_index:
            return np.zeros(0, np.int64), np.zeros((0, self.num_classes), np.float32)
        linear = linear_index(np.concatenate(parts_index), dims)
        alpha = np.concatenate(parts_alpha)
        order = np.argsort(linear, kind="stable")
        return linear[order], alpha[order]

    def write_window(self, origin: np.ndarray, dims: np.ndarray, linear: np.ndarray, alpha: np.ndarray) -> None:
        """Insert or overwrite the voxels at window-linear indices ``linear`` with ``alpha`` rows."""
        origin = np.asarray(origin, np.int64)
        self.write(unravel_linear(np.asarray(linear, np.int64), np.asarray(dims, np.int64)) + origin, alpha)

    def write(self, indices: np.ndarray, alpha: np.ndarray) -> None:
        """Insert or overwrite voxels at global ``indices`` (n, 3) with ``alpha`` (n, C)."""
        indices = np.asarray(indices, np.int64)
        alpha = np.asarray(alpha, np.float32)
        if alpha.shape != (indices.shape[0], self.num_classes):
            raise ValueError(f"alpha must be ({indices.shape[0]}, {self.num_classes}), got {alpha.shape}")
        self._clock += 1
        if indices.shape[0] == 0:
            self._retire_stale()
            return
        keys = _chunk_keys(indices)
        offsets = _local_offsets(indices)
        order = np.lexsort((offsets, keys[:, 2], keys[:, 1], keys[:, 0]))
        keys, offsets, alpha = keys[order], offsets[order], alpha[order]
        boundaries = np.flatnonzero((keys[1:] != keys[:-1]).any(axis=1)) + 1
        starts = np.concatenate([[0], boundaries])
        ends = np.concatenate([boundaries, [keys.shape[0]]])
        for start, end in zip(starts.tolist(), ends.tolist()):
            key = tuple(keys[start].tolist())
            new_offsets, new_alpha = offsets[start:end], alpha[start:end]
            chunk = self._get(key)
            if chunk is None:
                self._active[key] = _Chunk(new_offsets.copy(), new_alpha.copy(), self._clock)
                self._count += end - start
                continue
            keep = ~np.isin(chunk.offsets, new_offsets, assume_unique=True)
            merged_offsets = np.concatenate([chunk.offsets[keep], new_offsets])
            merged_alpha = np.concatenate([chunk.alpha[keep], new_alpha])
            sort = np.argsort(merged_offsets, kind="stable")
            self._count += merged_offsets.size - chunk.offsets.size
            chunk.offsets, chunk.alpha = merged_offsets[sort], merged_alpha[sort]
        self._retire_stale()

    def _retire_stale(self) -> None:
        horizon = self._clock - self.stale_after
        stale = []
        for key, chunk in self._active.items():  # oldest use first (see _get)
            if chunk.last_used >= horizon:
                break
            stale.append(key)
        for key in stale:
            self._archive[key] = self._active.pop(key)

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
            chunk = self._active.get(key) or self._archive.get(key)
            if chunk is None or chunk.offsets.size == 0:
                continue
            members = order[boundaries[number]:boundaries[number + 1]]
            position = np.searchsorted(chunk.offsets, offsets[members])
            position = np.minimum(position, chunk.offsets.size - 1)
            hit = chunk.offsets[position] == offsets[members]
            alpha[members[hit]] = chunk.alpha[position[hit]]
            found[members[hit]] = True
        return alpha, found

    # -- whole map -------------------------------------------------------------------------
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
        for table in (self._active, self._archive):
            for key, chunk in table.items():
                end = row + chunk.offsets.size
                indices[row:end] = _decode_offsets(chunk.offsets) + (np.asarray(key, np.int64) << CHUNK_SHIFT)
                alpha[row:end] = chunk.alpha
                row = end
        if row != indices.shape[0]:
            raise RuntimeError(f"store counted {indices.shape[0]} voxels but holds {row}")
        return indices, alpha

"""The shown map as point records, kept chunk by chunk from the map's changes.

Sending a whole map of millions of voxels used to mean copying every voxel's concentrations
under the map's lock, computing every voxel's statistics and packing them, each time.
``ShownMap`` keeps the packed records instead, in chunks of 64^3 voxels: a chunk is redone
only when one of its voxels changed (from the same change records that
``semantic_map/updates`` carries), and the whole map is the concatenation of the chunks, a
copy of bytes. Its records are bit for bit those computed from the map
(``records.records_from_alpha``).
"""

from __future__ import annotations

import numpy as np

from convbki_core.outputs.records import RECORD

CHUNK_SHIFT = 6  # 64 voxels a side: a scan touches tens of chunks, not thousands
OFFSET_BITS = 3 * CHUNK_SHIFT
INDEX_BIAS = 1 << 20  # voxel indices within +-2^20 (+-210 km at 0.2 m) make 21-bit unsigned keys
WORDS = RECORD.itemsize // 4  # a record as 32-bit words: cheap to gather, whatever its fields


def chunk_major_keys(indices: np.ndarray) -> np.ndarray:
    """One int64 per voxel that sorts chunk by chunk, then by position inside the chunk:
    (chunk x, y, z: 15 bits each) then (offset inside the chunk: 18 bits)."""
    biased = np.asarray(indices, np.int64) + INDEX_BIAS
    if biased.size and (biased.min() < 0 or biased.max() >= 2 * INDEX_BIAS):
        raise ValueError(f"voxel indices beyond +-{INDEX_BIAS} cannot be kept in the shown map")
    chunk = biased >> CHUNK_SHIFT
    local = biased & ((1 << CHUNK_SHIFT) - 1)
    return ((chunk[:, 0] << (OFFSET_BITS + 30)) | (chunk[:, 1] << (OFFSET_BITS + 15)) | (chunk[:, 2] << OFFSET_BITS)
            | (local[:, 0] << (2 * CHUNK_SHIFT)) | (local[:, 1] << CHUNK_SHIFT) | local[:, 2])


class ShownMap:
    """Records of the shown voxels per chunk: {chunk key: (offsets (n,) int64 sorted, words (n, 7) uint32)}."""

    def __init__(self):
        self.chunks: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def clear(self) -> None:
        self.chunks.clear()
        self.count = 0

    def apply(self, indices: np.ndarray, records: np.ndarray) -> None:
        """Apply change records in order (``records`` of the voxels at global ``indices`` (n, 3)):
        label 0 removes a voxel, any other label sets it; a voxel listed twice keeps its last."""
        if len(indices) == 0:
            return
        keys = chunk_major_keys(indices)
        order = np.argsort(keys, kind="stable")  # stable: a voxel's records stay in their order
        keys = keys[order]
        last = np.append(keys[1:] != keys[:-1], True)
        keys, order = keys[last], order[last]
        words = np.ascontiguousarray(records).view(np.uint32).reshape(-1, WORDS)[order]
        shown = records["label"][order] != 0
        chunk_of = keys >> OFFSET_BITS
        starts = np.flatnonzero(np.append(True, chunk_of[1:] != chunk_of[:-1]))
        ends = np.append(starts[1:], len(keys))
        offsets = keys & ((1 << OFFSET_BITS) - 1)
        for start, end in zip(starts.tolist(), ends.tolist()):
            part = slice(start, end)
            self._apply_chunk(int(chunk_of[start]), offsets[part], words[part], shown[part])

    def _apply_chunk(self, key: int, offsets: np.ndarray, words: np.ndarray, shown: np.ndarray) -> None:
        kept_offsets, kept_words = self.chunks.pop(key, (np.zeros(0, np.int64), np.zeros((0, WORDS), np.uint32)))
        self.count -= len(kept_offsets)
        # Both offset lists are sorted: a kept voxel stays unless the change lists it.
        position = np.minimum(np.searchsorted(offsets, kept_offsets), len(offsets) - 1)
        stay = offsets[position] != kept_offsets
        merged_offsets = np.concatenate([kept_offsets[stay], offsets[shown]])
        if len(merged_offsets) == 0:
            return
        merged_words = np.concatenate([kept_words[stay], words[shown]])
        order = np.argsort(merged_offsets, kind="stable")
        self.chunks[key] = (merged_offsets[order], merged_words[order])
        self.count += len(merged_offsets)

    def fill(self, out: np.ndarray) -> None:
        """Write every shown record into ``out`` (``len(self)`` records), chunk after chunk."""
        if len(out) != self.count:
            raise ValueError(f"{len(out)} records asked for, {self.count} shown")
        words = out.view(np.uint32).reshape(-1, WORDS)
        row = 0
        for _, chunk in self.chunks.values():
            words[row:row + len(chunk)] = chunk
            row += len(chunk)

    def records(self) -> np.ndarray:
        out = np.empty(self.count, RECORD)
        self.fill(out)
        return out

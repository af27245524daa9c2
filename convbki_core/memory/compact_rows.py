"""Compact rows of concentrations: per voxel only the classes whose value is not the prior.

Most voxels hold evidence for one to three of twenty classes, and every other class holds
exactly the prior. A row of C float32 values becomes its class count, then each such class's
id and its float32 value kept as the bit pattern (uint32), so rows come back bit for bit.
The global store keeps its chunks this way and the map file writes the same arrays.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA

if HAVE_NUMBA:
    from convbki_core.compiled import njit


def entry_starts(counts: np.ndarray) -> np.ndarray:
    """(n + 1,) int64: where each voxel's classes begin, and the total."""
    starts = np.zeros(counts.size + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    return starts


def entry_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated aranges [starts[i], starts[i] + counts[i]) (numpy paths)."""
    counts = counts.astype(np.int64)
    ends = np.cumsum(counts)
    return np.arange(int(ends[-1]) if ends.size else 0) + np.repeat(starts - (ends - counts), counts)


if HAVE_NUMBA:

    @njit(nogil=True)
    def _compress_numba(bits, order, prior_bits, counts, classes, values):  # pragma: no cover - compiled
        m = 0
        for i in range(order.size):
            row = order[i]
            first = m
            for c in range(bits.shape[1]):
                if bits[row, c] != prior_bits:
                    classes[m] = c
                    values[m] = bits[row, c]
                    m += 1
            counts[i] = m - first
        return m

    @njit(nogil=True)
    def _expand_numba(out, positions, starts, counts, classes, values, prior_bits):  # pragma: no cover - compiled
        for k in range(positions.size):
            p = positions[k]
            for c in range(out.shape[1]):
                out[k, c] = prior_bits
            for e in range(starts[p], starts[p] + counts[p]):
                out[k, classes[e]] = values[e]


def _entry_types(num_classes: int) -> tuple[type, type]:
    """dtypes of (class count, class id): one byte each up to 255 classes."""
    return (np.uint8 if num_classes <= 255 else np.uint16), (np.uint8 if num_classes <= 256 else np.uint16)


def compress_rows(alpha: np.ndarray, prior: float,
                  order: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense rows ``alpha[order]`` (N, C) float32 -> (class_count (N,), class_id (M,), value (M,) uint32
    float32 bit patterns) of the values that are not ``prior`` (compared bit for bit), in row order."""
    bits = np.ascontiguousarray(alpha, np.float32).view(np.uint32)
    order = np.arange(bits.shape[0]) if order is None else order
    prior_bits = np.float32(prior).view(np.uint32)
    count_type, class_type = _entry_types(bits.shape[1])
    if HAVE_NUMBA:
        counts = np.empty(order.size, count_type)
        # Room for every class of every row; memory that is never written is never touched.
        classes = np.empty(order.size * bits.shape[1], class_type)
        values = np.empty(order.size * bits.shape[1], np.uint32)
        used = _compress_numba(bits, order, prior_bits, counts, classes, values)
        return counts, classes[:used], values[:used]
    rows = bits[order]
    kept = rows != prior_bits
    row, column = np.nonzero(kept)
    return kept.sum(axis=1).astype(count_type), column.astype(class_type), rows[row, column]


def expand_rows(counts: np.ndarray, classes: np.ndarray, values: np.ndarray, prior: float, num_classes: int,
                positions: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Inverse of ``compress_rows``: dense float32 rows of the voxels at ``positions`` (default: all),
    the prior in every class not listed; into ``out`` if given. Inputs are trusted (ids < C)."""
    count_type, class_type = _entry_types(num_classes)
    counts, classes = counts.astype(count_type, copy=False), classes.astype(class_type, copy=False)
    values = np.ascontiguousarray(values).view(np.uint32)
    positions = np.arange(counts.size) if positions is None else positions
    out = np.empty((positions.size, num_classes), np.float32) if out is None else out
    bits, starts, prior_bits = out.view(np.uint32), entry_starts(counts), np.float32(prior).view(np.uint32)
    if HAVE_NUMBA:
        _expand_numba(bits, positions, starts, counts, classes, values, prior_bits)
        return out
    bits[:positions.size] = prior_bits
    entries = entry_ranges(starts[positions], counts[positions])
    bits[np.repeat(np.arange(positions.size), counts[positions]), classes[entries]] = values[entries]
    return out

"""The ConvBKI update evaluated at chosen voxels only, differentiable in the kernel.

The dense layer computes conv3d(F, K) at every voxel of the window. Training needs it
only at the voxels that hold the current scan's points, and F is sparse (about 1 % of a
window is occupied, and a one-hot voxel has one non-zero class). Written out, Eq. 4 at a
query voxel q is

    increment[q, c] = sum over taps o in [-h, h]^3 of K[c, o + h] * F[q + o, c],

so it is a sum over (query voxel, tap, source voxel, class) quadruples with F[q + o, c] != 0.
``SparsePlan`` finds those quadruples once (they do not depend on K); ``increment`` then
gathers K's taps and sums, with autograd reaching every length. It equals the dense layer
at the query voxels (tested), including zero padding when ``window`` is given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def pack_keys(indices: np.ndarray) -> np.ndarray:
    """Voxel indices (n, 3) with |index| < 2^20 -> one sortable int64 key each."""
    shifted = np.asarray(indices, np.int64) + _KEY_OFFSET
    return (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]


@dataclass
class SparsePlan:
    """Which source entries reach which query voxel through which tap."""

    num_queries: int
    num_classes: int
    filter_size: int
    target: torch.Tensor  # (P,) int64 flat index query * C + class
    tap: torch.Tensor  # (P,) int64 flat index class * f^3 + tap
    value: torch.Tensor  # (P,) float32 F[source, class]

    @classmethod
    def build(cls, query: np.ndarray, source: np.ndarray, features: np.ndarray, filter_size: int,
              window: tuple[np.ndarray, np.ndarray] | None = None) -> SparsePlan:
        """``query`` (Q, 3) voxel indices; ``source`` (M, 3) unique occupied voxels with
        ``features`` (M, C). With ``window`` = (origin, dims), sources outside it are
        ignored, as zero padding would."""
        query = np.asarray(query, np.int64)
        source = np.asarray(source, np.int64)
        features = np.asarray(features, np.float32)
        num_classes = features.shape[1]
        if window is not None:
            origin, dims = (np.asarray(a, np.int64) for a in window)
            inside = ((source >= origin) & (source < origin + dims)).all(axis=1)
            source, features = source[inside], features[inside]
        keys = pack_keys(source)
        order = np.argsort(keys)
        keys, features = keys[order], features[order]
        # Non-zero entries of F in CSR form: row r holds entries row_start[r] .. row_start[r + 1].
        rows, classes = np.nonzero(features)
        values = features[rows, classes]
        row_start = np.searchsorted(rows, np.arange(len(keys) + 1))

        half = filter_size // 2
        steps = np.arange(-half, half + 1)
        offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
        query_keys = pack_keys(query)
        parts_query, parts_source, parts_tap = [], [], []
        if len(keys):
            for tap, offset in enumerate(offsets):
                # Packing is linear in each coordinate, so a voxel offset is a fixed key offset.
                neighbour = query_keys + ((int(offset[0]) << (2 * _KEY_BITS)) + (int(offset[1]) << _KEY_BITS)
                                          + int(offset[2]))
                position = np.minimum(np.searchsorted(keys, neighbour), len(keys) - 1)
                hit = np.flatnonzero(keys[position] == neighbour)
                parts_query.append(hit)
                parts_source.append(position[hit])
                parts_tap.append(np.full(hit.size, tap))
        pair_query = np.concatenate(parts_query) if parts_query else np.zeros(0, np.int64)
        pair_source = np.concatenate(parts_source) if parts_source else np.zeros(0, np.int64)
        pair_tap = np.concatenate(parts_tap) if parts_tap else np.zeros(0, np.int64)
        # Expand every (query, source, tap) pair into the source's non-zero classes.
        counts = row_start[pair_source + 1] - row_start[pair_source]
        total = int(counts.sum())
        first = np.repeat(row_start[pair_source] - np.cumsum(counts) + counts, counts)
        entry = first + np.arange(total)
        query_of_entry = np.repeat(pair_query, counts)
        tap_of_entry = np.repeat(pair_tap, counts)
        class_of_entry = classes[entry]
        taps = filter_size ** 3
        return cls(len(query), num_classes, filter_size,
                   torch.from_numpy(query_of_entry * num_classes + class_of_entry),
                   torch.from_numpy(class_of_entry * taps + tap_of_entry),
                   torch.from_numpy(values[entry].astype(np.float32)))

    def increment(self, filters: torch.Tensor) -> torch.Tensor:
        """conv3d(F, K) at the query voxels, (Q, C); ``filters`` is K[C, 1, f, f, f]."""
        flat_filters = filters.reshape(-1)
        contributions = self.value.to(filters.device, filters.dtype) * flat_filters[self.tap.to(filters.device)]
        result = torch.zeros(self.num_queries * self.num_classes, dtype=filters.dtype, device=filters.device)
        result = result.index_add(0, self.target.to(filters.device), contributions)
        return result.view(self.num_queries, self.num_classes)

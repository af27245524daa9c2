"""``map_tool merge``'s arithmetic: the exact union of maps built in one frame (the ConvBKI
update is a sum of evidence on top of the prior, so the prior is counted once), and the check
that maps can be merged at all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from convbki_core.tools.cli import UserError

# Relative tolerance when comparing resolutions and priors read back from JSON metadata.
SAME_VALUE = 1e-9


def merge_arrays(parts: Sequence[tuple[np.ndarray, np.ndarray]], prior: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The exact merge of maps built in one frame with the same ``prior``.

    ``parts``: (indices (N_i, 3) int64, alpha (N_i, C) float32) per map, each without duplicate
    voxels. Returns (indices (M, 3) int64 sorted x, y, z; alpha (M, C) float32; how many voxels
    were in more than one map). Vectorised: one sort of all voxel keys, one scatter per map.
    """
    indices = np.concatenate([part[0] for part in parts]).astype(np.int64, copy=False)
    order = np.lexsort(indices.T[::-1])
    ordered = indices[order]
    first = np.ones(len(order), bool)
    first[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    group = np.empty(len(order), np.int64)
    group[order] = np.cumsum(first) - 1  # each input row's row in the output
    merged = np.zeros((int(first.sum()), parts[0][1].shape[1]), np.float32)
    count = np.zeros(len(merged), np.int64)
    start = 0
    for part_indices, part_alpha in parts:
        rows = group[start:start + len(part_indices)]
        # A map holds each voxel once, so these rows are distinct and += adds every row exactly once.
        merged[rows] += part_alpha
        count[rows] += 1
        start += len(part_indices)
    shared = count > 1
    # Each map started its voxels at the prior: keep it once. A voxel in one map keeps its row bit for bit.
    merged[shared] -= ((count[shared] - 1) * prior).astype(np.float32)[:, None]
    return ordered[first], merged, int(shared.sum())


def check_same(first: tuple[str, dict], other: tuple[str, dict]) -> None:
    """Refuse to merge maps whose grids, classes, frames or priors differ: their sum would mean nothing."""
    (name_a, meta_a), (name_b, meta_b) = first, other
    for key, what in (("resolution", "resolution (m)"), ("num_classes", "num_classes"), ("frame_id", "frame_id"),
                      ("prior", "prior")):
        a, b = meta_a.get(key), meta_b.get(key)
        same = (math.isclose(float(a), float(b), rel_tol=SAME_VALUE) if key in ("resolution", "prior") else a == b)
        if not same:
            raise UserError(f"cannot merge {name_a} and {name_b}: {what} differs ({a!r} vs {b!r})")


"""The label-noise model's neighbour search: for each point, the nearest point of another class
within a radius, by voxel hashing (numba). It fills unlabelled points and finds the borders the
boundary blur bleeds across.
"""

from __future__ import annotations

import math

import numpy as np

from convbki_core.compiled import njit, parallel_region, prange
from convbki_core.synth import lidar


@njit(parallel=True)
def _nearest_kernel(queries, query_labels, points, labels, cell_keys, cell_start, order, origin, dims, cell,
                    radius):
    n = queries.shape[0]
    out_index = np.full(n, -1, np.int64)
    out_dist = np.full(n, np.inf, np.float32)
    r2 = radius * radius
    for i in prange(n):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        own = query_labels[i]
        ix = math.floor(qx / cell) - origin[0]
        iy = math.floor(qy / cell) - origin[1]
        iz = math.floor(qz / cell) - origin[2]
        best, best_j = r2, -1
        for ax in range(ix - 1, ix + 2):
            if ax < 0 or ax >= dims[0]:
                continue
            for ay in range(iy - 1, iy + 2):
                if ay < 0 or ay >= dims[1]:
                    continue
                for az in range(iz - 1, iz + 2):
                    if az < 0 or az >= dims[2]:
                        continue
                    key = (ax * dims[1] + ay) * dims[2] + az
                    k = np.searchsorted(cell_keys, key)
                    if k >= cell_keys.shape[0] or cell_keys[k] != key:
                        continue
                    for m in range(cell_start[k], cell_start[k + 1]):
                        j = order[m]
                        label = labels[j]
                        if label == own or label == 0:
                            continue
                        dx, dy, dz = points[j, 0] - qx, points[j, 1] - qy, points[j, 2] - qz
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:
                            best, best_j = d2, j
        if best_j >= 0:
            out_index[i] = best_j
            out_dist[i] = math.sqrt(best)
    return out_index, out_dist


def nearest_other(points: np.ndarray, labels: np.ndarray, radius: float, queries: np.ndarray | None = None,
                  query_labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each query point: the nearest of ``points`` whose label is neither the query's nor 0,
    within ``radius`` (m). Returns (index into ``points``, -1 for none; distance float32, inf for
    none). Queries default to ``points`` themselves (then: the nearest point of another class)."""
    lidar.require_numba()
    points = np.ascontiguousarray(points, np.float64)
    labels = np.ascontiguousarray(labels, np.int64)
    queries = points if queries is None else np.ascontiguousarray(queries, np.float64)
    query_labels = labels if query_labels is None else np.ascontiguousarray(query_labels, np.int64)
    if not len(queries):
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    cell = float(radius)
    index = np.floor(points / cell).astype(np.int64)
    origin = np.minimum(index.min(0), np.floor(queries / cell).astype(np.int64).min(0)) - 1 if len(points) \
        else np.zeros(3, np.int64)
    index -= origin
    dims = index.max(0, initial=0) + 3
    keys = (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    first = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]) if len(keys) else np.zeros(0, np.int64)
    cell_keys = np.ascontiguousarray(sorted_keys[first])
    cell_start = np.append(first, len(keys)).astype(np.int64)
    with parallel_region():
        return _nearest_kernel(queries, query_labels, points, labels, cell_keys, cell_start, order,
                               origin.astype(np.int64), dims.astype(np.int64), cell, float(radius))


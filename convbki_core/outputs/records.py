"""Voxel records: what a map output holds per voxel, computed in one pass from the concentrations.

A record is the voxel's centre (x, y, z, float32, metres in the map frame), its class colour
(``rgb``, float32 whose bits are 0x00RRGGBB), its expected class (``label``, uint32), the
variance of that class's probability and the probability itself (float32; Dirichlet
statistics, ``statistics.dirichlet_statistics``). The layout is packed little-endian, so an
array of records is, byte for byte, the data of a point cloud with these fields: the ROS
side publishes it without another copy.

Computing records straight from the window's class planes avoids the intermediate copies
(every voxel's C concentrations, then the statistics arrays, then the packed points) that
dominate the cost of showing a large map.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.grid import voxel_centres
from convbki_core.inference.statistics import dirichlet_statistics

RECORD = np.dtype({"names": ["x", "y", "z", "rgb", "label", "variance", "confidence"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<f4", "<f4"],
                   "offsets": [0, 4, 8, 12, 16, 20, 24], "itemsize": 28})


def packed_palette(class_colors: np.ndarray) -> np.ndarray:
    """(C, 3) uint8 RGB -> (C,) uint32 0x00RRGGBB."""
    rgb = np.asarray(class_colors, np.uint32)
    return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]


def records_from_alpha(indices: np.ndarray, alpha: np.ndarray, resolution: float, palette: np.ndarray,
                       out: np.ndarray | None = None) -> np.ndarray:
    """Records of voxels given as global indices (N, 3) and concentrations (N, C) (the reference)."""
    stats = dirichlet_statistics(alpha)
    records = np.empty(len(indices), RECORD) if out is None else out
    centres = voxel_centres(indices, resolution)
    for axis, name in enumerate("xyz"):
        records[name] = centres[:, axis]
    records["rgb"] = palette[stats.label].view(np.float32)
    records["label"] = stats.label
    records["variance"] = stats.variance
    records["confidence"] = stats.confidence
    return records


def window_records(alpha: np.ndarray, mask: np.ndarray, origin: np.ndarray, dims: np.ndarray, count: int,
                   resolution: float, palette: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Records of the torus window's voxels with evidence (``mask``), ``count`` of them, in torus order.

    ``alpha`` (C, X, Y, Z) class-major, ``origin`` the global index of the window's first
    voxel. ``out``: ``count`` records to fill (e.g. a view on a message buffer).
    """
    out = np.empty(count, RECORD) if out is None else out
    if count == 0:
        return out
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    palette = np.ascontiguousarray(palette, np.uint32)
    if HAVE_NUMBA:
        words = out.view(np.uint32).reshape(count, 7)
        with parallel_region():
            written = _window_records_numba(alpha, mask, origin, dims, float(resolution), palette, words)
        if written != count:
            raise ValueError(f"output has {count} records, the window {int(np.count_nonzero(mask))} voxels")
        return out
    physical = np.argwhere(mask)
    if physical.shape[0] != count:
        raise ValueError(f"output has {count} records, the window {physical.shape[0]} voxels")
    indices = origin + (physical - origin) % dims
    return records_from_alpha(indices, alpha[:, physical[:, 0], physical[:, 1], physical[:, 2]].T, resolution,
                              palette, out)


if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange
    from convbki_core.inference.statistics import voxel_statistics
    from convbki_core.memory.window import plane_starts

    @njit(parallel=True, nogil=True)
    def _window_records_numba(alpha, mask, origin, dims, resolution, palette, words):  # pragma: no cover
        size_x, size_y, size_z = mask.shape
        num_classes = alpha.shape[0]
        starts = plane_starts(mask, np.uint8(0xFF))
        if starts[-1] != words.shape[0]:
            return -1
        floats = words.view(np.float32)
        for x in prange(size_x):
            row = starts[x]
            values = np.empty(num_classes, np.float32)
            centre_x = np.float32((origin[0] + (x - origin[0]) % dims[0] + 0.5) * resolution)
            for y in range(size_y):
                centre_y = np.float32((origin[1] + (y - origin[1]) % dims[1] + 0.5) * resolution)
                for z in range(size_z):
                    if mask[x, y, z] == 0:
                        continue
                    for c in range(num_classes):
                        values[c] = alpha[c, x, y, z]
                    best, expected, variance = voxel_statistics(values)
                    floats[row, 0] = centre_x
                    floats[row, 1] = centre_y
                    floats[row, 2] = np.float32((origin[2] + (z - origin[2]) % dims[2] + 0.5) * resolution)
                    words[row, 3] = palette[best]
                    words[row, 4] = best
                    floats[row, 5] = variance
                    floats[row, 6] = expected
                    row += 1
        return starts[-1]


def removal_records(indices: np.ndarray, resolution: float) -> np.ndarray:
    """Records saying "this voxel left the map": its centre, label 0, every other field 0."""
    records = np.zeros(len(indices), RECORD)
    centres = voxel_centres(indices, resolution)
    for axis, name in enumerate("xyz"):
        records[name] = centres[:, axis]
    return records


def change_records(removed: np.ndarray, indices: np.ndarray, alpha: np.ndarray, resolution: float,
                   palette: np.ndarray, max_variance: float = 0.0) -> np.ndarray:
    """The records of a map's changes, in the order a receiver applies them: the voxels that
    left the map (label 0), then the voxels that changed (a voxel listed twice: its last
    record counts). A changed voxel whose variance exceeds ``max_variance`` (when > 0) is not
    in the shown map, so it is sent as a removal too. A receiver that starts from an empty
    map and applies every message in order holds exactly the shown map (``apply_records``)."""
    return updates_records(removed, records_from_alpha(indices, alpha, resolution, palette), resolution,
                           max_variance)


def updates_records(removed: np.ndarray, changed: np.ndarray, resolution: float,
                    max_variance: float = 0.0) -> np.ndarray:
    """``change_records`` from the changed voxels' records ``changed`` (made where the map
    lives); ``changed`` is written in place."""
    if max_variance > 0:
        hidden = changed["variance"] > max_variance
        for name in ("rgb", "label", "variance", "confidence"):
            changed[name][hidden] = 0
    return np.concatenate([removal_records(removed, resolution), changed])


def apply_records(shown: dict, records: np.ndarray) -> dict:
    """Apply change records to ``shown`` (voxel centre (x, y, z) -> record), as a receiver of
    the map's updates does: label 0 removes the voxel, any other label sets it."""
    for record in records:
        key = (float(record["x"]), float(record["y"]), float(record["z"]))
        if record["label"] == 0:
            shown.pop(key, None)
        else:
            shown[key] = record.copy()
    return shown


def view_records(records: np.ndarray, centre: np.ndarray, radius: float, budget: int) -> np.ndarray:
    """The records within ``radius`` metres (horizontally) of ``centre`` (x, y), at most
    ``budget`` of them, the nearest first when there are more: a view of a large map that a
    viewer can draw at any map size."""
    distance_sq = (records["x"] - np.float32(centre[0])) ** 2 + (records["y"] - np.float32(centre[1])) ** 2
    near = np.flatnonzero(distance_sq <= np.float32(radius) ** 2)
    if len(near) > budget:
        near = near[np.argpartition(distance_sq[near], budget - 1)[:budget]]
        near.sort()
    return records[near]

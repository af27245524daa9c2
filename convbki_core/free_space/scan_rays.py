"""A scan's rays: one per voxel holding returns, and those of the returns beyond the window.

Returns that fall into the same voxel share one ray, from the sensor to that voxel's centre,
weighted by their number (``ray_weights``). Returns beyond the window (far, or above or below
it, ``beyond_window``) still say that the window's part of their ray is empty: they share rays
by the boundary voxel where they leave the window (``window_exits``), which those rays cross
too. The compiled exits (``_exit_linear_numba``) equal the numpy ones.
"""

from __future__ import annotations

import numpy as np

from convbki_core.compiled import HAVE_NUMBA
from convbki_core.geometry.grid import unravel_linear
from convbki_core.geometry.volume import SparseVolume

if HAVE_NUMBA:
    from convbki_core.compiled import njit


def scan_rays(points: np.ndarray, pose: np.ndarray, volume: SparseVolume,
              resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scan's rays as (end voxels (M, 3), weights (M,), through (M,) bool): one per voxel
    holding returns (weighted by their evidence), and one per window voxel where the rays to
    returns beyond the window leave it (``through``: that voxel is crossed too)."""
    weights = ray_weights(volume.features)
    beyond = beyond_window(points, pose, volume, resolution)
    origin = np.ascontiguousarray(volume.origin, np.int64)
    dims = np.ascontiguousarray(volume.dims, np.int64)
    exit_linear, rays = _unique_exits(pose[:3, 3] / resolution, beyond, origin, dims)
    linear = np.concatenate([volume.linear, exit_linear])
    through = np.zeros(len(linear), np.bool_)
    through[len(volume.linear):] = True
    ends = _unravel_numba(linear, origin, dims) if HAVE_NUMBA else unravel_linear(linear, dims) + origin
    return ends, np.concatenate([weights, rays]), through


def beyond_window(points: np.ndarray, pose: np.ndarray, volume: SparseVolume, resolution: float) -> np.ndarray:
    """The scan's returns the volume dropped (beyond the window, or not finite), in voxel units
    of the map frame: ``window_exits`` finds where their rays leave the window."""
    dropped = points[volume.point_linear < 0]
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points are skipped by the exits
        return (dropped @ pose[:3, :3].T + pose[:3, 3]) / resolution


def ray_weights(features: np.ndarray) -> np.ndarray:
    """Rays per occupied voxel: its evidence sum (the number of labelled points in it)."""
    return np.ascontiguousarray(features.sum(axis=1, dtype=np.float32))


def window_exits(sensor: np.ndarray, points: np.ndarray, origin: np.ndarray,
                 dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For returns beyond the window (``points`` (N, 3) in voxel units; those inside and
    those not finite are skipped): the window voxels where their rays leave it, unique, with
    the number of rays each."""
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    linear, rays = _unique_exits(sensor, points, origin, dims)
    local = np.stack(np.unravel_index(linear, tuple(int(d) for d in dims)), axis=1)
    return local + origin, rays


def _unique_exits(sensor, points, origin, dims) -> tuple[np.ndarray, np.ndarray]:
    """``window_exits`` as window-linear indices (sorted) and rays (float32)."""
    sensor = np.ascontiguousarray(sensor, np.float64)
    if HAVE_NUMBA:
        linear = _exit_linear_numba(np.ascontiguousarray(points, np.float64), sensor, origin, dims)
    else:
        linear = _exit_linear_numpy(np.asarray(points, np.float64), sensor, origin, dims)
    linear, rays = np.unique(linear, return_counts=True)
    return linear, rays.astype(np.float32)


def _exit_linear_numpy(points, sensor, origin, dims) -> np.ndarray:
    points = points[np.isfinite(points).all(axis=1)]
    outside = ((points < origin) | (points >= origin + dims)).any(axis=1)
    direction = points[outside] - sensor
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(direction > 0, (origin + dims).astype(np.float64), origin.astype(np.float64))
        leave = np.where(direction != 0, (bound - sensor) / direction, np.inf).min(axis=1)
    exits = np.floor(sensor + direction * (leave[:, None] * (1 - 1e-9)))
    local = np.clip(exits, origin, origin + dims - 1).astype(np.int64) - origin
    return (local[:, 0] * dims[1] + local[:, 1]) * dims[2] + local[:, 2]


if HAVE_NUMBA:

    @njit(nogil=True)
    def _exit_linear_numba(points, sensor, origin, dims):  # pragma: no cover - compiled; tested against numpy
        """Window-local linear index of the voxel where each finite outside point's ray leaves
        the window."""
        out = np.empty(points.shape[0], np.int64)
        count = 0
        for i in range(points.shape[0]):
            if not (np.isfinite(points[i, 0]) and np.isfinite(points[i, 1]) and np.isfinite(points[i, 2])):
                continue
            outside = False
            for axis in range(3):
                if points[i, axis] < origin[axis] or points[i, axis] >= origin[axis] + dims[axis]:
                    outside = True
            if not outside:
                continue
            leave = np.inf
            for axis in range(3):
                direction = points[i, axis] - sensor[axis]
                if direction > 0:
                    leave = min(leave, (origin[axis] + dims[axis] - sensor[axis]) / direction)
                elif direction < 0:
                    leave = min(leave, (origin[axis] - sensor[axis]) / direction)
            linear = 0
            for axis in range(3):
                position = np.floor(sensor[axis] + (points[i, axis] - sensor[axis]) * (leave * (1 - 1e-9)))
                local = min(max(np.int64(position), origin[axis]), origin[axis] + dims[axis] - 1) - origin[axis]
                linear = linear * dims[axis] + local
            out[count] = linear
            count += 1
        return out[:count]

    @njit(nogil=True)
    def _unravel_numba(linear, origin, dims):  # pragma: no cover - compiled; the twin of unravel_linear
        """Global indices (N, 3) of window-linear indices."""
        out = np.empty((linear.shape[0], 3), np.int64)
        for i in range(linear.shape[0]):
            rest = linear[i]
            out[i, 2] = rest % dims[2] + origin[2]
            rest //= dims[2]
            out[i, 1] = rest % dims[1] + origin[1]
            out[i, 0] = rest // dims[1] + origin[0]
        return out

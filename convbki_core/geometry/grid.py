"""The voxel grid and the local window: where a point, a voxel and a window voxel are.

Geometry: the global map is an axis-aligned grid in the map frame with voxel index
``floor(x / resolution)`` on each axis, so voxel (i, j, k) has its centre at
``(i + 0.5, j + 0.5, k + 0.5) * resolution``. The local window is a box of that grid
around the sensor: ``dims`` voxels per axis starting at global index ``origin``. Inside a
window a voxel is addressed by its linear index ``(x * DY + y) * DZ + z``, the memory
order of a C-contiguous (X, Y, Z) volume.

Also the pose check and the point transform every path shares (so that all put a point in
the same voxel), and voxel keys: one int64 per global voxel index.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WindowGeometry:
    """The local window's shape around the sensor, in voxels of ``resolution`` metres.

    ``bounds_min``/``bounds_max`` are metres relative to the sensor position along the
    map axes (the paper: [-40, -40, -2.6] .. [40, 40, 2.6]). They are rounded outwards to
    whole voxels.
    """

    resolution: float
    bounds_min: tuple[float, float, float] = (-40.0, -40.0, -2.6)
    bounds_max: tuple[float, float, float] = (40.0, 40.0, 2.6)

    def __post_init__(self):
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be positive metres, got {self.resolution}")
        if len(self.bounds_min) != 3 or len(self.bounds_max) != 3:
            raise ValueError("local bounds need three values each (x, y, z)")
        if any(not lo < hi for lo, hi in zip(self.bounds_min, self.bounds_max)):
            raise ValueError(f"local bounds must satisfy min < max, got {self.bounds_min} .. {self.bounds_max}")

    @property
    def offset(self) -> np.ndarray:
        """Index of the window's first voxel relative to the sensor's voxel, (3,) int64."""
        return np.floor(np.asarray(self.bounds_min) / self.resolution + 1e-6).astype(np.int64)

    @property
    def dims(self) -> np.ndarray:
        """Voxels per axis, (3,) int64 (the paper's set-up: 400, 400, 26)."""
        end = np.ceil(np.asarray(self.bounds_max) / self.resolution - 1e-6).astype(np.int64)
        return end - self.offset

    @property
    def num_voxels(self) -> int:
        return int(np.prod(self.dims))

    def origin_for(self, sensor_position: np.ndarray) -> np.ndarray:
        """Global index of the window's first voxel when the sensor is at ``sensor_position`` (map frame, m)."""
        sensor_voxel = np.floor(np.asarray(sensor_position, dtype=np.float64) / self.resolution).astype(np.int64)
        return sensor_voxel + self.offset


def check_pose(pose: np.ndarray) -> np.ndarray:
    """Validate a 4x4 homogeneous SE(3) pose (map <- sensor); returns it as float64."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 matrix, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise ValueError("pose contains NaN or inf")
    rotation = pose[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        raise ValueError("pose rotation is not a proper rotation matrix (orthonormal, det +1)")
    if not np.allclose(pose[3], [0, 0, 0, 1]):
        raise ValueError("pose last row must be [0, 0, 0, 1]")
    return pose


def check_poses(poses: np.ndarray) -> np.ndarray:
    """``check_pose`` of each of ``poses`` (n, 4, 4) at once; raises for the first that fails."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be 4x4 matrices, got shape {poses.shape}")
    rotations = poses[:, :3, :3]
    with np.errstate(invalid="ignore"):
        orthonormal = np.isclose(rotations @ np.swapaxes(rotations, 1, 2), np.eye(3), atol=1e-4).all(axis=(1, 2))
        good = (np.isfinite(poses).all(axis=(1, 2)) & orthonormal & (np.linalg.det(rotations) >= 0)
                & np.isclose(poses[:, 3], [0, 0, 0, 1]).all(axis=1))
    if not good.all():
        check_pose(poses[int(np.flatnonzero(~good)[0])])
    return poses


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by a 4x4 pose, in float64: ((x r0 + y r1) + z r2) + t per axis.

    Written out term by term (not a BLAS product) so that every path, the compiled
    voxeliser included, rounds identically and puts a point in the same voxel.
    """
    points = np.asarray(points, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    with np.errstate(invalid="ignore"):  # NaN points stay NaN (dropped later)
        rotated = (points[:, 0:1] * pose[:3, 0] + points[:, 1:2] * pose[:3, 1]) + points[:, 2:3] * pose[:3, 2]
        return rotated + pose[:3, 3]


def voxel_indices(points: np.ndarray, resolution: float) -> np.ndarray:
    """Global voxel index (N, 3) int64 of map-frame points (N, 3) in metres."""
    return np.floor(np.asarray(points, dtype=np.float64) / resolution).astype(np.int64)


_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
# A voxel and its 26 neighbours (faces, edges, corners), as index offsets (27, 3).
TOUCHING_OFFSETS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)], np.int64)


def voxel_keys(indices: np.ndarray) -> np.ndarray:
    """One int64 per global voxel index (N, 3), each axis within +-2^20 voxels: sets of voxels
    are then sorted, searched and intersected as plain integers."""
    shifted = np.asarray(indices, np.int64).reshape(-1, 3) + _KEY_OFFSET
    return (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]


def voxel_centres(indices: np.ndarray, resolution: float) -> np.ndarray:
    """Map-frame centres (N, 3) float64 of global voxel indices (N, 3)."""
    return (np.asarray(indices, dtype=np.float64) + 0.5) * resolution


def linear_index(local: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(N, 3) window-local indices -> (N,) linear indices (x-major, z fastest)."""
    return (local[:, 0] * dims[1] + local[:, 1]) * dims[2] + local[:, 2]


def voxels_of_keys(keys: np.ndarray) -> np.ndarray:
    """The global voxel indices (n, 3) of ``voxel_keys``."""
    mask = (1 << _KEY_BITS) - 1
    keys = np.asarray(keys, np.int64)
    return np.stack([keys >> (2 * _KEY_BITS), (keys >> _KEY_BITS) & mask, keys & mask], axis=1) - _KEY_OFFSET


def unravel_linear(linear: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(N,) linear indices -> (N, 3) window-local indices."""
    z = linear % dims[2]
    rest = linear // dims[2]
    return np.stack([rest // dims[1], rest % dims[1], z], axis=1)

"""Helpers only the tests need: readers of what the package writes, and small wrappers
over its internals that the tests use as probes. The package itself never needs them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from convbki_core.free_space import _walk_ray
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.io.ply import PLY_DTYPE
from convbki_core.kernels import ConvBKIKernel
from convbki_ros.transforms import pose_from_translation_quaternion


def crossed_voxels(start: np.ndarray, end_voxel: np.ndarray, through: bool = False) -> list[tuple[int, int, int]]:
    """The voxels a ray from ``start`` (voxel units) to the centre of ``end_voxel`` passes
    through, in order, the end voxel left out unless ``through`` (the traversal that the
    free-space pass runs)."""
    crossed = []
    _walk_ray(np.asarray(start, np.float64), np.asarray(end_voxel, np.int64), crossed.append, through)
    return crossed


def read_ply(path: str | Path) -> np.ndarray:
    """A PLY written by ``io.ply.write_voxels_ply``, as a structured array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    return np.frombuffer(data, dtype=PLY_DTYPE, count=count, offset=end)


def tap_offsets(filter_size: int, resolution: float, dtype=torch.float64):
    """Metric offsets (dx, dy, dz) of every tap of an f x f x f filter from its centre, each
    (f, f, f), in conv3d's (D, H, W) = (x, y, z) order."""
    half = filter_size // 2
    steps = torch.arange(-half, half + 1, dtype=dtype) * resolution
    return torch.meshgrid(steps, steps, steps, indexing="ij")


def kernel_from_file(path: str | Path) -> ConvBKIKernel:
    return ConvBKIKernel.from_config(load_kernel_file(path))


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of (x, y, z, w) quaternions (rotation b, then a)."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def odometry_to_pose(msg: Any) -> np.ndarray:
    """nav_msgs/Odometry (or a Pose, PoseStamped, PoseWithCovariance) -> 4x4 pose."""
    pose = msg
    while hasattr(pose, "pose"):
        pose = pose.pose
    p, o = pose.position, pose.orientation
    return pose_from_translation_quaternion(np.array([p.x, p.y, p.z], np.float64),
                                            np.array([o.x, o.y, o.z, o.w], np.float64))


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(...) float32 packed 0x00RRGGBB -> (..., 3) uint8 RGB."""
    bits = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=-1).astype(np.uint8)

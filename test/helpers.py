"""Helpers only the core's tests need (no ROS): a simple LiDAR for street scenes, readers of
what the package writes, and small wrappers over its internals that the tests use as probes.
The package itself never needs them. The ROS side's helpers are in ros_helpers.py."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from convbki_core.free_space.ray_walk import _walk_ray
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.io.kernel_file import load_kernel_file
from convbki_core.io.map_file import read_map
from convbki_core.io.ply import PLY_DTYPE

# Real labelled SemanticKITTI scans (the first 10 scans of sequences 00, 01 and 05 in the
# dataset's layout), where this machine has them: CONVBKI_REAL_SCANS, else the project's shared
# data folder beside the repository. Never copied into the repository: tests skip without them.
REAL_SCANS = Path(os.environ.get("CONVBKI_REAL_SCANS") or
                  Path(__file__).resolve().parents[1].parent / "shared" / "data" / "semantic_kitti_real")


def real_sequence(sequence: str) -> Path:
    """The root holding real sequence ``sequence``; skips the test with the reason when absent."""
    import pytest

    if not (REAL_SCANS / "sequences" / sequence / "velodyne").is_dir():
        pytest.skip(f"the real SemanticKITTI scans are not here ({REAL_SCANS}; set CONVBKI_REAL_SCANS)")
    return REAL_SCANS


# A street for the simple LiDAR below: SemanticKITTI learning ids, and a house front across it
# (what the LiDAR sees through the space a car has left).
CAR, ROAD, BUILDING, POLE = 1, 9, 13, 18
BUILDING_ACROSS = (np.array([12.0, -12.0, 0.0]), np.array([12.5, 12.0, 4.0]), BUILDING)


def cast(sensor: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray, int]], max_range: float = 16.0):
    """Returns (points in the world, labels) of a 64-beam, 0.5-degree LiDAR at ``sensor``:
    the nearest hit of each ray on the ground (z = 0, road) or on an axis-aligned box."""
    azimuth = np.radians(np.arange(0, 360, 0.5))
    elevation = np.radians(np.linspace(-25, 3, 64))
    a, e = np.meshgrid(azimuth, elevation)
    directions = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    best = np.full(len(directions), np.inf)
    label = np.zeros(len(directions), np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = np.where(directions[:, 2] < 0, -sensor[2] / directions[:, 2], np.inf)
        best, label = np.where(ground < best, ground, best), np.where(ground < best, ROAD, label)
        for low, high, box_label in boxes:
            t0, t1 = (low - sensor) / directions, (high - sensor) / directions
            enter = np.nanmax(np.minimum(t0, t1), axis=1)
            leave = np.nanmin(np.maximum(t0, t1), axis=1)
            hit = (enter <= leave) & (enter > 0) & (enter < best)
            best, label = np.where(hit, enter, best), np.where(hit, box_label, label)
    keep = best < max_range
    return sensor + directions[keep] * best[keep, None], label[keep]


def sorted_map(path: str | Path) -> tuple[dict, np.ndarray, np.ndarray]:
    """(metadata, indices, alpha) of a map file with the voxels in x, y, z order."""
    metadata, indices, alpha = read_map(path)
    order = np.lexsort(indices.T[::-1])
    return metadata, indices[order], alpha[order]


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


def small_saved_map(folder: Path) -> Path:
    """``folder``/good.npz: a map of three voxels and four classes (concentrations 0..11), saved by the mapper."""
    from convbki_core import ConvBKIMapper
    from convbki_core.config import MapperConfig

    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-1, -1, -1), (1, 1, 1)), device="cpu"),
                           ConvBKIKernel("single", 4, 3, 0.2, ell=0.3))
    mapper.store.write(np.array([[0, 0, 0], [1, 2, 3], [-4, 5, 6]]), np.arange(12, dtype=np.float32).reshape(3, 4))
    path = folder / "good.npz"
    mapper.save(path)
    return path

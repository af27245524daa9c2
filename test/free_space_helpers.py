"""What the free-space tests share (no ROS): an exact oracle of the voxels a ray crosses
(segment/box intersection over every voxel of the segment's bounding box, independent of the
stepping code) and of where a ray leaves the window, rays the walk finds hard, windows for
clamping, and scenes cast by the simple LiDAR of helpers.py."""

from __future__ import annotations

import numpy as np
from helpers import cast

from convbki_core import ConvBKIMapper
from convbki_core.free_space.update import free_taps
from convbki_core.memory.window import EVIDENCE, TOUCHED

BOUNDS = ((-12.0, -12.0, -3.0), (12.0, 12.0, 3.0))


def segment_crosses_box(start: np.ndarray, end: np.ndarray, low: np.ndarray) -> bool:
    """Whether the open segment start -> end passes through the interior of the unit box at
    ``low`` for a positive length (slab method)."""
    direction = end - start
    t_enter, t_exit = 0.0, 1.0
    for axis in range(3):
        if abs(direction[axis]) < 1e-15:
            if not (low[axis] < start[axis] < low[axis] + 1):
                return False
            continue
        t0 = (low[axis] - start[axis]) / direction[axis]
        t1 = (low[axis] + 1 - start[axis]) / direction[axis]
        t_enter, t_exit = max(t_enter, min(t0, t1)), min(t_exit, max(t0, t1))
    return t_exit - t_enter > 1e-9


def brute_force_crossed(start: np.ndarray, end_voxel: np.ndarray, through: bool = False) -> set[tuple[int, int, int]]:
    end = end_voxel + 0.5
    low = np.floor(np.minimum(start, end)).astype(int)
    high = np.floor(np.maximum(start, end)).astype(int)
    crossed = set()
    for x in range(low[0], high[0] + 1):
        for y in range(low[1], high[1] + 1):
            for z in range(low[2], high[2] + 1):
                voxel = np.array([x, y, z])
                if (through or not (voxel == end_voxel).all()) and segment_crosses_box(start, end, voxel):
                    crossed.add((x, y, z))
    if through:
        crossed.add(tuple(int(v) for v in end_voxel))
    return crossed


def exit_voxel(start: np.ndarray, point: np.ndarray, origin: np.ndarray, dims: np.ndarray) -> tuple[int, ...]:
    """The window voxel where the segment start -> point (point outside) leaves the window,
    found by bisection on the segment."""
    inside, outside = 0.0, 1.0
    for _ in range(60):
        middle = (inside + outside) / 2
        position = start + middle * (point - start)
        if ((position >= origin) & (position < origin + dims)).all():
            inside = middle
        else:
            outside = middle
    return tuple(int(v) for v in np.floor(start + inside * (point - start)))


def awkward_scan(rng: np.random.Generator, origin: np.ndarray, dims: np.ndarray, sensor_kind: str):
    """A sensor and rays that the walk finds hard: the sensor on voxel corners, at a voxel's
    centre (rays along an axis, diagonals that meet voxel edges exactly) or outside the window
    in x; rays ending on the sensor's x plane and on either side of it, some leaving the window."""
    if sensor_kind == "corner":
        sensor = rng.integers(origin + 1, origin + dims - 1).astype(np.float64)
    elif sensor_kind == "centre":
        sensor = rng.integers(origin + 1, origin + dims - 1) + 0.5
    elif sensor_kind == "outside":  # below the window in x: every ray ends above it
        sensor = rng.uniform(origin + 1, origin + dims - 1)
        sensor[0] = origin[0] - rng.uniform(0.5, 3.0)
    else:
        sensor = rng.uniform(origin + 1, origin + dims - 1)
    here = np.floor(sensor).astype(np.int64)
    ends = [rng.integers(origin, origin + dims, size=(120, 3))]
    for axis in range(3):  # along each axis, both ways
        line = np.repeat(here[None], dims[axis], axis=0)
        line[:, axis] = origin[axis] + np.arange(dims[axis])
        ends.append(line)
    span = int(dims.min())
    for sign_y, sign_z in ((1, 1), (-1, 1), (1, -1)):  # diagonals
        diagonal = here + np.arange(-span, span)[:, None] * np.array([1, sign_y, sign_z])
        ends.append(diagonal)
    plane = rng.integers(origin, origin + dims, size=(20, 3))
    plane[:, 0] = here[0]  # on the sensor's x plane
    ends.append(plane)
    ends = np.concatenate(ends)
    inside = ((ends >= origin) & (ends < origin + dims)).all(axis=1)
    if sensor_kind == "outside":
        inside &= ends[:, 0] > here[0]
    ends = np.unique(ends[inside], axis=0)
    return sensor, ends, rng.integers(1, 6, len(ends)).astype(np.float32), rng.random(len(ends)) < 0.3


def clamping_case(rng: np.random.Generator, trial: int, wide: bool, classes: int, prior: float | None = None):
    """A window and a scan for clamping: (dims, origin, rays (sensor, ends, weights, through),
    free taps (offsets, weights), alpha, mask): heavy voxels (a mover stood there) and light
    ones, free concentrations small and large, a fifth of the voxels with evidence touched by
    the scan; with ``prior``, half the columns of each class hold only the prior, as most
    columns hold a few classes."""
    dims = np.array([[12, 14, 6], [16, 10, 8]][trial % 2])
    origin = rng.integers(-40, 40, 3)
    rays = awkward_scan(rng, origin, dims, "random")
    free = np.zeros((3, 3, 3), np.float32)
    free[1, 1, 1] = 1
    if wide:
        free[2, 1, 1], free[1, 0, 1] = 0.25, 0.5
    alpha = (rng.uniform(1e-3, 2, (classes, *dims)) * rng.choice([1.0, 30.0], (classes, *dims))).astype(np.float32)
    if prior is not None:
        for c in range(1, classes):
            alpha[c][rng.random(tuple(dims[:2])) < 0.5] = prior
    alpha[0] = rng.uniform(1e-3, 6, tuple(dims)).astype(np.float32)
    mask = (rng.random(tuple(dims)) < 0.6).astype(np.uint8)
    mask[(rng.random(tuple(dims)) < 0.2) & (mask == EVIDENCE)] |= TOUCHED
    return dims, origin, rays, free_taps(free), alpha, mask


def integrate_world(mapper: ConvBKIMapper, sensor: np.ndarray, boxes) -> None:
    points, labels = cast(sensor, boxes)
    pose = np.eye(4)
    pose[:3, 3] = sensor
    mapper.integrate(points - sensor, labels, pose)


def map_labels(mapper: ConvBKIMapper) -> tuple[np.ndarray, np.ndarray]:
    voxels = mapper.voxels()
    return voxels.centres, voxels.label

"""Free space in the mapper: rays empty the voxels they cross, movers leave no trail, thin
structures stay.

The oracle for the ray traversal is an exact segment/box intersection over every voxel of
the segment's bounding box, independent of the stepping code (``free_space_helpers``); the
mapper's free evidence is checked against it scan by scan, with rotated poses, moving windows
and a free-space kernel wider than one voxel. The passes' exactness (compiled, numpy, device)
is tested in test_free_space_passes.py, the ground's surface in test_free_space_ground.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from free_space_helpers import BOUNDS, brute_force_crossed, exit_voxel, integrate_world, map_labels
from helpers import BUILDING, BUILDING_ACROSS, CAR, POLE, ROAD
from reference import sparse_kernel_np

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig


def random_pose(rng: np.random.Generator, position: np.ndarray) -> np.ndarray:
    yaw, pitch, roll = rng.uniform(-math.pi, math.pi), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)
    cz, sz, cy, sy = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    rotation = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) \
        @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    return pose


def brute_force_free_evidence(points, labels, pose, mapper, stored, touched, free_ell):
    """The free evidence one scan adds: rays from the sensor to each used voxel's centre (one
    per point), and through the window to the voxel where the rays to returns beyond it leave
    it, counted exactly per crossed voxel, spread by the free kernel, at the stored voxels
    the scan's class evidence did not reach."""
    resolution = mapper.resolution
    world = points @ pose[:3, :3].T + pose[:3, 3]
    voxels = np.floor(world / resolution).astype(np.int64)
    origin, dims = mapper.window.origin, mapper.geometry.dims
    inside = ((voxels >= origin) & (voxels < origin + dims)).all(axis=1) & (labels != 0)
    ends, rays = np.unique(voxels[inside], axis=0, return_counts=True)
    sensor = pose[:3, 3] / resolution
    beyond = world[~((voxels >= origin) & (voxels < origin + dims)).all(axis=1)] / resolution
    exits: dict[tuple, int] = {}
    for point in beyond:
        key = exit_voxel(sensor, point, origin, dims)
        exits[key] = exits.get(key, 0) + 1
    counts: dict[tuple, float] = {}
    for end, weight, through in [(e, w, False) for e, w in zip(ends, rays)] + [
            (np.array(k), w, True) for k, w in exits.items()]:
        for voxel in brute_force_crossed(sensor, end, through):
            counts[voxel] = counts.get(voxel, 0.0) + float(weight)
    half = mapper.kernel.filter_size // 2
    offsets = [np.array(index) - half for index in np.ndindex(2 * half + 1, 2 * half + 1, 2 * half + 1)]
    taps = [(o, float(sparse_kernel_np(resolution * np.linalg.norm(o), max(free_ell, 1e-4)))) for o in offsets]
    taps = [(o, w) for o, w in taps if w >= 1e-6]
    expected = {}
    for voxel in map(tuple, stored):
        if voxel in touched:
            continue
        evidence = sum(w * counts.get(tuple(np.array(voxel) - o), 0.0) for o, w in taps
                       if ((np.array(voxel) - o >= origin) & (np.array(voxel) - o < origin + dims)).all())
        if evidence > 0:
            expected[voxel] = evidence
    return expected


@pytest.mark.parametrize("free_ell", [None, 0.3])
def test_free_evidence_equals_a_ray_by_ray_reference(tmp_path, free_ell):
    """Scan by scan, free space adds to class 0 exactly the brute-force ray counts (through the
    free kernel) at stored voxels outside the scan's class evidence, and nothing else."""
    rng = np.random.default_rng(7 if free_ell is None else 8)
    kernel = ConvBKIKernel("compound", 20, 3, 0.5, ell_h=0.7, ell_z=0.6, free_ell=free_ell)
    bounds = ((-4.0, -4.0, -2.0), (4.0, 4.0, 2.0))
    # the unclamped model: clamping has its own tests
    with_free = ConvBKIMapper(MapperConfig.paper(local_bounds=bounds, free_space=True, device="cpu",
                                                 max_concentration=0.0), kernel)
    position = np.zeros(3)
    freed = 0
    for scan in range(6):
        position = position + rng.uniform(-1.5, 1.5, 3) * [1, 1, 0.3]  # the window moves between scans
        pose = random_pose(rng, position)
        # A few small clusters, so that later rays cross voxels this scan's evidence does not reach.
        clusters = rng.uniform(-3.5, 3.5, (6, 3)) * [1, 1, 0.5]
        points = clusters[rng.integers(0, 6, 400)] + rng.normal(0, 0.15, (400, 3))
        # and returns beyond the window, whose rays still cross it
        far = rng.normal(0, 1, (60, 3))
        points[-60:] = far / np.linalg.norm(far, axis=1, keepdims=True) * rng.uniform(5, 9, (60, 1))
        labels = rng.integers(0, 20, 400)
        labels[:40] = 0  # ignored points cast no ray
        path = tmp_path / f"before_{scan}.npz"
        with_free.save(path)
        without = ConvBKIMapper(MapperConfig.paper(local_bounds=bounds, device="cpu", track_changes=True), kernel)
        if scan:
            without.load(path)
        without.take_changes(everything=True)
        with_free.integrate(points, labels, pose)
        without.integrate(points, labels, pose)
        touched = {tuple(v) for v in without.take_changes().indices}
        indices, plain_alpha = without.items()
        free_indices, free_alpha = with_free.items()
        order, free_order = np.lexsort(indices.T), np.lexsort(free_indices.T)
        assert (indices[order] == free_indices[free_order]).all()  # free space adds no voxel
        plain_alpha, free_alpha = plain_alpha[order], free_alpha[free_order]
        assert (plain_alpha[:, 1:] == free_alpha[:, 1:]).all()  # the classes are untouched
        expected = brute_force_free_evidence(points, labels, pose, with_free, indices[order], touched,
                                             0.0 if free_ell is None else free_ell)
        added = free_alpha[:, 0] - plain_alpha[:, 0]
        want = np.array([expected.get(tuple(v), 0.0) for v in indices[order]])
        freed += np.count_nonzero(want)
        np.testing.assert_allclose(added, want, rtol=1e-5, atol=1e-5 * (1 + np.abs(plain_alpha[:, 0])).max())
    assert freed > 50


def test_free_space_off_leaves_class_zero_at_the_prior_and_on_needs_class_zero_ignored():
    rng = np.random.default_rng(2)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS), "config/kernels/semantic_kitti_compound.yaml")
    for _ in range(3):
        mapper.integrate(rng.uniform(-8, 8, (2000, 3)), rng.integers(0, 20, 2000), np.eye(4))
    assert (mapper.items()[1][:, 0] == np.float32(mapper.prior)).all()
    with pytest.raises(ValueError, match="class 0"):
        ConvBKIMapper(MapperConfig.paper(ignore_classes=(), free_space=True),
                      "config/kernels/semantic_kitti_compound.yaml")


# -- scenes: a tiny ray caster over a ground plane and boxes ---------------------------------------

@pytest.mark.parametrize("free_space", [False, True])
def test_a_car_crossing_the_street_leaves_no_trail_once_the_street_is_seen_again(free_space):
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=free_space, device="cpu"),
                           "config/kernels/semantic_kitti_compound.yaml")
    car_low, car_high = np.array([-2.0, -0.9, 0.35]), np.array([2.0, 0.9, 1.85])  # 0.35 m above the road
    for scan in range(30):
        sensor = np.array([0.1 * scan, 0.05, 1.73])  # the ego vehicle creeps along x
        boxes = [BUILDING_ACROSS]
        if scan < 12:  # the car crosses in front (along y at x = 7), then has gone
            centre = np.array([7.0, -6.0 + 1.0 * scan, 0.0])
            boxes.append((centre + car_low, centre + car_high, CAR))
        integrate_world(mapper, sensor, boxes)
    centres, labels = map_labels(mapper)
    # The space the car swept in front of the sensor, which the later scans see through to the house.
    swept = ((np.abs(centres[:, 0] - 7.0) < 2.0) & (np.abs(centres[:, 1]) < 3.5)
             & (centres[:, 2] > car_low[2]) & (centres[:, 2] < car_high[2]))
    car_voxels = int(np.count_nonzero((labels == CAR) & swept))
    if free_space:
        assert car_voxels == 0
        under = (np.abs(centres[:, 0] - 7.0) < 2.0) & (np.abs(centres[:, 1]) < 3.5) & (centres[:, 2] < 0.2)
        assert np.count_nonzero((labels == ROAD) & under) >= 0.95 * np.count_nonzero(under)  # the street stays
        assert np.count_nonzero(labels == BUILDING) > 500
    else:
        assert car_voxels > 1000  # plain ConvBKI keeps the trail


@pytest.mark.parametrize("limit", [0.0, 300.0])
def test_a_car_that_stood_long_is_emptied_soon_after_it_leaves_only_with_clamping(limit):
    """A car parked beside the ego vehicle for 60 scans holds thousands of units of "car";
    clamped, the rays of 15 scans after it left empty its voxels; unclamped they cannot."""
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=True, device="cpu",
                                              max_concentration=limit), "config/kernels/semantic_kitti_compound.yaml")
    car_low, car_high = np.array([4.5, -2.0, 0.35]), np.array([6.3, 2.0, 1.85])
    sensor = np.array([0.05, 0.05, 1.73])
    for scan in range(75):
        boxes = [BUILDING_ACROSS] + ([(car_low, car_high, CAR)] if scan < 60 else [])
        integrate_world(mapper, sensor + [0.01 * scan, 0, 0], boxes)
    centres, labels = map_labels(mapper)
    # The face the sensor saw (where the evidence piled up), below the sensor's height, which
    # the later rays to the house cross.
    face = ((centres[:, 0] > car_low[0] - 0.2) & (centres[:, 0] < car_low[0] + 0.3)
            & (np.abs(centres[:, 1]) < 1.6) & (centres[:, 2] > 0.5) & (centres[:, 2] < 1.6))
    seen_through = face
    car_left = int(np.count_nonzero((labels == CAR) & seen_through))
    if limit:
        assert car_left == 0
        assert np.count_nonzero(labels == BUILDING) > 500
    else:
        assert car_left > 20


def test_a_pole_seen_from_all_sides_stays_a_pole():
    pole = (np.array([-0.1, -0.1, 0.0]), np.array([0.1, 0.1, 3.0]), POLE)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, free_space=True, device="cpu"),
                           "config/kernels/semantic_kitti_compound.yaml")
    plain = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu"),
                          "config/kernels/semantic_kitti_compound.yaml")
    for scan in range(36):  # a circle of 6 m around the pole
        angle = math.radians(10 * scan)
        sensor = np.array([6 * math.cos(angle), 6 * math.sin(angle), 1.73])
        integrate_world(mapper, sensor, [pole])
        integrate_world(plain, sensor, [pole])
    layers = {}
    for name, each in (("free", mapper), ("plain", plain)):
        centres, labels = map_labels(each)
        near = (np.abs(centres[:, 0]) < 0.2) & (np.abs(centres[:, 1]) < 0.2) & (centres[:, 2] > 0.2)
        layers[name] = {round(float(z), 1) for z in centres[near & (labels == POLE), 2]}
    # Every 0.2 m layer of the pole from 0.2 m (below, the road wins) to the highest beam's reach.
    assert layers["free"] == layers["plain"] == {round(0.3 + 0.2 * i, 1) for i in range(12)}
    _, free_labels = map_labels(mapper)
    _, plain_labels = map_labels(plain)
    assert np.count_nonzero(free_labels == POLE) >= 0.9 * np.count_nonzero(plain_labels == POLE)

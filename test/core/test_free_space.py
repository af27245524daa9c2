"""Free space: rays empty the voxels they cross, movers leave no trail, thin structures stay.

The oracle for the ray traversal is an exact segment/box intersection over every voxel of
the segment's bounding box, independent of the stepping code; the mapper's free evidence is
checked against it scan by scan, with rotated poses, moving windows and a free-space
kernel wider than one voxel.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import BUILDING, BUILDING_ACROSS, CAR, POLE, ROAD, cast, crossed_voxels
from reference import sparse_kernel_np

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.free_space.device_rays import count_rays_on_device
from convbki_core.free_space.rays import (
    _free_space_numpy,
    count_rays,
    free_space_update,
    free_taps,
    ground_marks,
    scratch_counts,
)
from convbki_core.memory.window import CHANGED, EVIDENCE, GROUND, RECLASSED, TOUCHED, class_bits, classes_held

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


def test_the_traversal_visits_exactly_the_voxels_a_ray_passes_through():
    rng = np.random.default_rng(11)
    for _ in range(300):
        start = rng.uniform(-8, 8, 3)
        end_voxel = rng.integers(-12, 12, 3)
        through = bool(rng.random() < 0.5)
        walked = crossed_voxels(start, end_voxel, through)
        assert len(walked) == len(set(walked))  # each voxel once
        assert set(walked) == brute_force_crossed(start, end_voxel, through)
        if walked:  # a connected path from the sensor's voxel
            assert walked[0] == tuple(np.floor(start).astype(int))
            steps = np.abs(np.diff(np.array(walked + ([] if through else [tuple(end_voxel)])), axis=0)).sum(axis=1)
            assert (steps == 1).all()


def test_the_compiled_pass_equals_the_numpy_pass():
    rng = np.random.default_rng(5)
    for trial in range(8):
        dims = np.array([18, 20, 10])
        origin = rng.integers(-30, 30, 3)
        sensor = rng.uniform(origin + 2, origin + dims - 2)
        occupied = np.unique(rng.integers(origin, origin + dims, size=(250, 3)), axis=0)
        weights = rng.integers(1, 5, len(occupied)).astype(np.float32)
        through = rng.random(len(occupied)) < 0.3
        alpha = rng.uniform(1e-3, 2, (3, *dims)).astype(np.float32)
        mask = (rng.random(tuple(dims)) < 0.4).astype(np.uint8)
        mask[(rng.random(tuple(dims)) < 0.2) & (mask == 1)] |= 4
        free = np.zeros((3, 3, 3), np.float32)
        free[1, 1, 1] = 1
        if trial % 2:
            free[1, 1, 0], free[0, 1, 1] = 0.3, 0.2
        offsets, tap_weights = free_taps(free)
        compiled_alpha, compiled_mask = alpha.copy(), mask.copy()
        counts = scratch_counts(dims)
        grew = free_space_update(sensor, occupied, weights, offsets, tap_weights, origin, dims, compiled_alpha,
                                 compiled_mask, counts, through)
        assert grew == _free_space_numpy(sensor, occupied, weights, through, offsets, tap_weights, origin, dims, alpha,
                                         mask)
        assert grew > 0
        np.testing.assert_allclose(compiled_alpha, alpha, rtol=1e-6)
        assert (compiled_mask == mask).all() and not (mask & 4).any()
        assert not counts[0].any() and not counts[1].any()  # the scratch is left zeroed


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


@pytest.mark.parametrize("sensor_kind", ["random", "corner", "centre", "outside"])
def test_the_compiled_pass_is_exactly_the_numpy_pass_on_awkward_rays(sensor_kind):
    """Bit for bit: the compiled walk, counting in its own layout on two threads, and the
    numpy walk give the same counts, and the same free evidence through a centre-only and a
    wider free kernel, on windows that wrap the torus anywhere."""
    rng = np.random.default_rng(["random", "corner", "centre", "outside"].index(sensor_kind))
    for trial in range(6):
        dims = np.array([[12, 14, 6], [16, 10, 8], [9, 11, 7]][trial % 3])
        origin = rng.integers(-40, 40, 3)
        sensor, ends, weights, through = awkward_scan(rng, origin, dims, sensor_kind)
        expected = np.zeros(tuple(dims), np.float32)
        for end, weight, passes in zip(ends, weights, through):
            for voxel in crossed_voxels(sensor, end, bool(passes)):
                expected[tuple(np.mod(voxel, dims))] += weight
        counts = scratch_counts(dims)
        assert np.array_equal(count_rays(sensor, ends, weights, through, dims, counts), expected)
        counts[0].fill(0.0)
        # The device's walk, every crossing on its own (torch on the CPU here): the same counts.
        on_device = count_rays_on_device(sensor, torch.as_tensor(ends), torch.as_tensor(weights),
                                         torch.as_tensor(through), torch.zeros(tuple(dims), dtype=torch.float32))
        assert np.array_equal(on_device.numpy(), expected)
        free = np.zeros((3, 3, 3), np.float32)
        free[1, 1, 1] = 1
        if trial % 2:
            free[2, 1, 1], free[1, 0, 1], free[1, 1, 2] = 0.25, 0.5, 0.125
        offsets, tap_weights = free_taps(free)
        alpha = rng.uniform(1e-3, 2, (2, *dims)).astype(np.float32)
        mask = (rng.random(tuple(dims)) < 0.5).astype(np.uint8)
        mask[(rng.random(tuple(dims)) < 0.3) & (mask == 1)] |= TOUCHED
        mask[rng.random(tuple(dims)) < 0.1] |= CHANGED
        compiled_alpha, compiled_mask = alpha.copy(), mask.copy()
        grew = free_space_update(sensor, ends, weights, offsets, tap_weights, origin, dims, compiled_alpha,
                                 compiled_mask, counts, through)
        assert grew == _free_space_numpy(sensor, ends, weights, through, offsets, tap_weights, origin, dims, alpha,
                                         mask) > 0
        assert np.array_equal(compiled_alpha, alpha) and np.array_equal(compiled_mask, mask)
        assert not counts[0].any() and not counts[1].any()


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


@pytest.mark.parametrize("wide", [False, True])
def test_the_compiled_pass_clamps_exactly_as_the_numpy_pass(wide):
    """With a clamping limit, the compiled pass (the centre kernel's vectorised runs and the
    wider kernel's loop) and the numpy pass scale the same voxels by the same factors."""
    rng = np.random.default_rng(11 + wide)
    limit = 40.0
    clamped_somewhere = False
    for trial in range(4):
        dims, origin, (sensor, ends, weights, through), (offsets, tap_weights), alpha, mask = clamping_case(
            rng, trial, wide, 4)
        compiled_alpha, compiled_mask = alpha.copy(), mask.copy()
        unclamped, unclamped_mask = alpha.copy(), mask.copy()
        counts = scratch_counts(dims)
        grew = free_space_update(sensor, ends, weights, offsets, tap_weights, origin, dims, compiled_alpha,
                                 compiled_mask, counts, through, limit, 1e-3)
        assert grew == _free_space_numpy(sensor, ends, weights, through, offsets, tap_weights, origin, dims, alpha,
                                         mask, limit, 1e-3) > 0
        assert np.array_equal(compiled_alpha, alpha) and np.array_equal(compiled_mask, mask)
        assert not counts[0].any() and not counts[1].any()
        assert not (compiled_mask & 8).any()  # the pass's own bit does not outlive it
        _free_space_numpy(sensor, ends, weights, through, offsets, tap_weights, origin, dims, unclamped,
                          unclamped_mask, 0.0)
        scaled = (alpha[1:] != unclamped[1:]).any(axis=0)
        if scaled.any():
            clamped_somewhere = True
            np.testing.assert_allclose(alpha[:, scaled].sum(axis=0), limit, rtol=1e-5)
            assert alpha[:, scaled].min() >= np.float32(1e-3)  # the prior is kept
    assert clamped_somewhere


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



@pytest.mark.parametrize("wide", [False, True])
@pytest.mark.parametrize("read_all", [False, True])
def test_the_compiled_pass_keeps_the_ground_bits_as_the_numpy_pass_derives_them(wide, read_all):
    """Voxels that hold the ground's surface take no free evidence. The compiled pass derives
    their bits only in the columns where ``RECLASSED`` says classes changed (reading the held
    class runs alone, or every run), the numpy pass for every voxel: the same masks and
    concentrations, on windows whose z origin wraps the torus anywhere; no surface voxel takes
    free evidence, where without the ground classes some would, and ground voxels above or
    under the surface still do."""
    rng = np.random.default_rng(21 + 2 * wide + read_all)
    prior = np.float32(1e-3)
    ground = (2, 4)
    bits = class_bits(ground)
    for trial in range(4):
        dims, origin, (sensor, ends, weights, through), (offsets, tap_weights), alpha, mask = clamping_case(
            rng, trial, wide, 5, prior)
        evident = (mask & EVIDENCE) != 0
        reclassed = (rng.random(tuple(dims[:2])) < 0.4)[:, :, None] & (rng.random(tuple(dims)) < 0.2) & evident
        mask[reclassed] |= RECLASSED
        stale_columns = np.broadcast_to(reclassed.any(axis=2)[:, :, None], reclassed.shape)
        is_surface = ground_marks(alpha, bits, origin[2], prior) & evident
        mask[is_surface & ~stale_columns] |= GROUND  # as derived before; the others hold anything
        mask[stale_columns & evident & (rng.random(tuple(dims)) < 0.5)] |= GROUND
        before, unguarded, unguarded_mask = alpha.copy(), alpha.copy(), mask & np.uint8(0xFF & ~GROUND)
        compiled_alpha, compiled_mask = alpha.copy(), mask.copy()
        counts = scratch_counts(dims)
        grew = free_space_update(sensor, ends, weights, offsets, tap_weights, origin, dims, compiled_alpha,
                                 compiled_mask, counts, through, 40.0, prior, ground,
                                 None if read_all else classes_held(alpha, prior))
        assert grew == _free_space_numpy(sensor, ends, weights, through, offsets, tap_weights, origin, dims, alpha,
                                         mask, 40.0, prior, bits) > 0
        assert np.array_equal(compiled_alpha, alpha) and np.array_equal(compiled_mask, mask)
        took = alpha[0] != before[0]
        assert not took[is_surface].any()
        ground_class = np.isin(before[1:].argmax(axis=0) + 1, ground) & evident
        assert (took & ground_class & ~is_surface).any()  # the air over (or under) the surface
        # Only the voxels clamped just now are left to derive; elsewhere the bits are current.
        clamped = (alpha[1:] != before[1:]).any(axis=0)
        pending = (mask & RECLASSED) != 0
        assert pending[clamped].all() and clamped.any() and not pending[~took].any()
        current = ~np.broadcast_to(pending.any(axis=2)[:, :, None], pending.shape)
        now = ground_marks(alpha, bits, origin[2], prior) & evident
        assert np.array_equal(((mask & GROUND) != 0)[current], now[current])
        _free_space_numpy(sensor, ends, weights, through, offsets, tap_weights, origin, dims, unguarded,
                          unguarded_mask, 40.0, prior)
        assert (unguarded[0] != before[0])[is_surface].sum() > 10


@pytest.mark.parametrize("origin_z", [0, 4, -3])
@pytest.mark.parametrize("kind", ["numpy", "torch"])
def test_ground_marks_of_hand_built_columns(origin_z, kind):
    """The surface rule on columns whose answer is worked out by hand (the reference of the two
    tests above, which take ``ground_marks`` as their expectation): a voxel holds the surface
    when its most likely occupied class is a ground class and its ground evidence is not below
    its neighbours' under and over it (nothing beyond the window); on a torus window whose z
    origin puts the column's bottom anywhere."""
    prior = np.float32(1e-3)
    ground = class_bits((2, 4))
    # Per column, bottom to top: {class: concentration above the prior}, and the surface by hand.
    columns = [
        ([{2: 3.0}, {2: 5.0, 1: 1.0}, {4: 2.0, 3: 2.5}, {2: 1.0}, {1: 4.0}, {4: 0.5}],
         # z0 under z1's 5; z1 the surface; z2 a class-3 voxel; z3 (1.0) under z2's ground
         # evidence 2.0; z4 no ground; z5 over z4's 0 and the window's end.
         [False, True, False, False, False, True]),
        ([{2: 2.0}, {2: 2.0}, {}, {1: 1.0, 4: 0.9}, {4: 3.0}, {3: 7.0, 2: 6.9}],
         # equal neighbours both hold it; z3's class 1 leads; z4 (3.0) is under z5's ground
         # evidence 6.9, though z5's leading class is 3.
         [True, True, False, False, False, False]),
        ([{}] * 6, [False] * 6),  # nothing but the prior: no class leads, no surface
    ]
    size_z = 6
    alpha = np.full((5, len(columns), 1, size_z), prior, np.float32)
    expected = np.zeros((len(columns), 1, size_z), bool)
    for x, (voxels, surface) in enumerate(columns):
        for step, held in enumerate(voxels):
            physical = (origin_z + step) % size_z  # the torus: the column's bottom at its origin
            for c, above in held.items():
                alpha[c, x, 0, physical] = prior + np.float32(above)
            expected[x, 0, physical] = surface[step]
    got = ground_marks(torch.as_tensor(alpha) if kind == "torch" else alpha, ground, origin_z, prior)
    got = got.numpy() if kind == "torch" else got
    assert np.array_equal(got, expected), (got[:, 0], expected[:, 0])


def crossing_car_map(**config) -> ConvBKIMapper:
    """The street of ``test_a_car_crossing_the_street...``, mapped with ``config``, its road
    0.1 m higher in the map frame: the middle of a voxel layer, as a surface usually lies."""
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", **config),
                           "config/kernels/semantic_kitti_compound.yaml")
    car_low, car_high = np.array([-2.0, -0.9, 0.35]), np.array([2.0, 0.9, 1.85])
    for scan in range(30):
        boxes = [BUILDING_ACROSS]
        if scan < 12:
            centre = np.array([7.0, -6.0 + 1.0 * scan, 0.0])
            boxes.append((centre + car_low, centre + car_high, CAR))
        sensor = np.array([0.1 * scan, 0.05, 1.73])
        points, labels = cast(sensor, boxes)
        pose = np.eye(4)
        pose[:3, 3] = sensor + [0.0, 0.0, 0.1]
        mapper.integrate(points - sensor, labels, pose)
    return mapper


def test_rays_leave_the_grounds_surface_and_still_empty_a_movers_trail():
    """Rays that end on the road some way off run just above it for their last metres. With
    the ground classes, the voxels of the road's surface (the layer of its returns) stay road,
    as many as plain ConvBKI shows, while the road's evidence that the kernel spread into the
    layer above is emptied as without them, and the car that crossed leaves no trail; without
    the ground classes, the rays erode the surface (so this can fail)."""
    surface, above = {}, {}
    for name, config in (("plain", {}), ("unguarded", {"free_space": True}),
                         ("ground", {"free_space": True, "ground_classes": (ROAD,)})):
        centres, labels = map_labels(crossing_car_map(**config))
        road = labels == ROAD
        surface[name] = int(np.count_nonzero(road & (centres[:, 2] > 0.0) & (centres[:, 2] < 0.2)))
        above[name] = int(np.count_nonzero(road & (centres[:, 2] > 0.2) & (centres[:, 2] < 0.4)))
        if name == "ground":
            swept = ((np.abs(centres[:, 0] - 7.0) < 2.0) & (np.abs(centres[:, 1]) < 3.5)
                     & (centres[:, 2] > 0.45) & (centres[:, 2] < 1.95))
            assert not np.count_nonzero((labels == CAR) & swept)
    assert surface["ground"] == surface["plain"] > surface["unguarded"], surface
    assert above["ground"] == above["unguarded"] < above["plain"] - 100, above


def test_the_ground_bits_follow_every_change_of_the_classes():
    """After every scan (a car crossing, the movers' rules on, the window moving along z, leaving
    the street and coming back from the store), each voxel's ground bit is what the classes of
    its column say, except in the columns of voxels clamped in that scan, which are marked to
    be derived in the next."""
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=BOUNDS, device="cpu", free_space=True,
                                              ground_classes=(ROAD,), movable_classes=(CAR,)),
                           "config/kernels/semantic_kitti_compound.yaml")
    car_low, car_high = np.array([-2.0, -0.9, 0.35]), np.array([2.0, 0.9, 1.85])
    positions = [np.array([0.1 * scan, 0.05, 1.73]) for scan in range(14)]
    positions += [np.array([1.4, 0.05, 2.6]), np.array([1.5, 0.05, 1.73]), np.array([40.0, 0.05, 1.73]),
                  np.array([1.5, 0.05, 1.73]), np.array([1.6, 0.05, 1.73])]
    surfaces, origins_z = [], set()
    for scan, sensor in enumerate(positions):
        boxes = [BUILDING_ACROSS]
        if scan < 8:
            centre = np.array([7.0, -4.0 + 1.0 * scan, 0.0])
            boxes.append((centre + car_low, centre + car_high, CAR))
        integrate_world(mapper, sensor, boxes)
        window = mapper.window
        evident = (window.mask & EVIDENCE) != 0
        expected = ground_marks(window.alpha, class_bits((ROAD,)), window.origin[2], mapper.prior) & evident
        pending = np.broadcast_to(((window.mask & RECLASSED) != 0).any(axis=2)[:, :, None], evident.shape)
        assert np.array_equal(((window.mask & GROUND) != 0)[~pending], expected[~pending]), scan
        assert pending.mean() < 0.05
        surfaces.append(int(expected.sum()))
        origins_z.add(int(window.origin[2]))
    assert min(surfaces) > 500 and len(origins_z) > 1
    assert mapper.forgetting.reset_voxels + mapper.forgetting.emptied_voxels > 0


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

def integrate_world(mapper: ConvBKIMapper, sensor: np.ndarray, boxes) -> None:
    points, labels = cast(sensor, boxes)
    pose = np.eye(4)
    pose[:3, 3] = sensor
    mapper.integrate(points - sensor, labels, pose)


def map_labels(mapper: ConvBKIMapper) -> tuple[np.ndarray, np.ndarray]:
    voxels = mapper.voxels()
    return voxels.centres, voxels.label


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


def test_window_exits_compiled_equals_numpy_and_lie_on_the_boundary():
    from convbki_core.free_space.rays import _exit_linear_numba, _exit_linear_numpy, window_exits

    rng = np.random.default_rng(4)
    origin, dims, sensor = np.array([-10, -12, -5]), np.array([20, 24, 10]), np.array([0.3, -0.2, 0.1])
    points = rng.uniform(-40, 40, (3000, 3))
    points[:30] = [[np.nan, 50, 0], [np.inf, 0, 0], [-np.inf, np.nan, 0]] * 10  # skipped, never an exit
    compiled = _exit_linear_numba(points, sensor, origin, dims)
    assert (compiled == _exit_linear_numpy(points, sensor, origin, dims)).all()
    exits, rays = window_exits(sensor, points, origin, dims)
    points = points[30:]
    outside = ((points < origin) | (points >= origin + dims)).any(axis=1)
    assert rays.sum() == outside.sum() == len(compiled)
    on_boundary = ((exits == origin) | (exits == origin + dims - 1)).any(axis=1)
    assert on_boundary.all()
    for point in points[outside][:200]:  # each ray leaves through the voxel the bisection finds
        assert exit_voxel(sensor, point, origin, dims) in {tuple(e) for e in exits}

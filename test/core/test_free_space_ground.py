"""The ground's surface and free space: the voxels that hold it take no free evidence (the
compiled pass keeps their bits as the numpy pass derives them, and both follow every change of
the classes), so rays that end on the road some way off leave the surface while they still
empty the air over it and a mover's trail.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from free_space_helpers import BOUNDS, clamping_case, integrate_world, map_labels
from helpers import BUILDING_ACROSS, CAR, ROAD, cast

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.free_space.ground import ground_marks
from convbki_core.free_space.ray_walk import scratch_counts
from convbki_core.free_space.update import _free_space_numpy, free_space_update
from convbki_core.memory.column_classes import class_bits, classes_held
from convbki_core.memory.window import EVIDENCE, GROUND, RECLASSED


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

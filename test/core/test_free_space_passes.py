"""Free space's passes, bit for bit: the ray walk visits exactly the voxels a ray passes
through (against an exact segment/box oracle); the compiled walk, the numpy walk and the
device's walk count the same rays; the compiled free-space update (with clamping) leaves the
same window as the numpy one; the rays beyond the window leave it where the oracle says.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from free_space_helpers import awkward_scan, brute_force_crossed, clamping_case, exit_voxel
from helpers import crossed_voxels

from convbki_core.free_space.device_rays import count_rays_on_device
from convbki_core.free_space.ray_walk import count_rays, scratch_counts
from convbki_core.free_space.update import _free_space_numpy, free_space_update, free_taps
from convbki_core.memory.window import CHANGED, TOUCHED


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


def test_window_exits_compiled_equals_numpy_and_lie_on_the_boundary():
    from convbki_core.free_space.scan_rays import _exit_linear_numba, _exit_linear_numpy, window_exits

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

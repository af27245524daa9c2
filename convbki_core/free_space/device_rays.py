"""Free space's rays walked on a torch device: every crossing of every ray at once.

The compiled pass walks each ray voxel by voxel (``ray_walk._walk_ray``, Amanatides-Woo),
which a GPU would do one small step at a time. The same walk, written so that each of its
steps is computed on its own:

A ray from the sensor s (voxel units) to the centre of its end voxel e crosses
n_a = |e_a - floor(s_a)| voxel boundaries along each axis a, the k-th (k = 0 .. n_a - 1) at
time t_a(k) = t0_a + k * delta_a, computed in float64 by the same operations as the compiled
walk. The walk visits the sensor's voxel, then the voxel after each crossing, in the order of
(time, axis) (on equal times x before y before z); it makes n_x + n_y + n_z - 1 steps (one
more, reaching the end voxel too, for a ray that goes on beyond the window). The voxel after
the crossing (a, k) is the sensor's voxel moved by k + 1 along a and, along each other axis b,
by the number of b's crossings that come before it: the k' < n_b with (t_b(k'), b) before
(t_a(k), a), found from the formula by one division and checked against the times themselves
(a rounding may put the division one off). Its rank in the walk is the sum of those numbers
minus one, which says whether the walk makes that step.

So the visits are a scatter of (voxel, weight) pairs: no sort, no loop over the rays' steps,
the same voxels as the compiled walk bit for bit, and counts equal wherever the weights are
whole numbers (returns counted one by one), as float32 sums of them are in any order.
"""

from __future__ import annotations

import numpy as np
import torch


def count_rays_on_device(sensor: np.ndarray, ends: torch.Tensor, weights: torch.Tensor, through: torch.Tensor,
                         counts: torch.Tensor) -> torch.Tensor:
    """Add each ray's weight to ``counts`` (X, Y, Z) float32 on the device, torus order (voxel v at
    v mod dims), at every voxel the ray crosses before its end voxel (and the end voxel too where
    ``through``): what ``ray_walk.count_rays`` counts on the host. ``sensor`` (3,) the sensor in
    voxel units; ``ends`` (M, 3) int64, ``weights`` (M,) float32, ``through`` (M,) bool, on the
    device. Returns ``counts``."""
    device = counts.device
    dims = counts.shape
    start = torch.as_tensor(np.asarray(sensor, np.float64), device=device)
    voxel = torch.floor(start).to(torch.int64)
    ends = ends.to(device=device, dtype=torch.int64)
    direction = (ends.to(torch.float64) + 0.5) - start
    crossings = (ends - voxel).abs()  # n_a per ray and axis
    moving = direction != 0
    safe = torch.where(moving, direction, torch.ones((), dtype=torch.float64, device=device))
    boundary = torch.where(direction > 0, voxel.to(torch.float64) + 1.0, voxel.to(torch.float64) * 1.0)
    first = torch.where(moving, (boundary - start) / safe, torch.inf)  # t0 per ray and axis
    delta = (1.0 / safe).abs()  # finite everywhere; read only where an axis has crossings
    step = torch.where(direction > 0, 1, -1)
    total = crossings.sum(dim=1)
    steps = total + through.to(torch.int64)  # the walk's visits
    flat = counts.view(-1)

    # The sensor's voxel: every ray that makes a step visits it first.
    walked = steps > 0
    _scatter(flat, dims, voxel.expand(int(walked.sum()), 3), weights[walked])

    for axis in range(3):
        ray = torch.repeat_interleave(torch.arange(len(ends), device=device), crossings[:, axis])
        if not len(ray):
            continue
        offsets = torch.cumsum(crossings[:, axis], 0) - crossings[:, axis]
        k = torch.arange(len(ray), device=device) - offsets[ray]
        time = first[ray, axis] + k.to(torch.float64) * delta[ray, axis]
        moved = torch.empty((len(ray), 3), dtype=torch.int64, device=device)
        moved[:, axis] = k + 1
        for other in range(3):
            if other != axis:
                moved[:, other] = _crossed_before(time, axis, other, first[ray, other], delta[ray, other],
                                                  crossings[ray, other])
        rank = moved.sum(dim=1) - 1
        kept = rank < steps[ray] - 1  # the last crossing of a ray that ends inside leads to its end voxel
        ray = ray[kept]
        _scatter(flat, dims, voxel + step[ray] * moved[kept], weights[ray])
    return counts


def _crossed_before(time: torch.Tensor, axis: int, other: int, first: torch.Tensor, delta: torch.Tensor,
                    crossings: torch.Tensor) -> torch.Tensor:
    """How many of the crossings k' < ``crossings`` along ``other`` (at first + k' * delta) come
    before a crossing along ``axis`` at ``time`` (on equal times, the lower axis first)."""
    def before(k: torch.Tensor) -> torch.Tensor:
        at = first + k.to(torch.float64) * delta
        return (at < time) | ((at == time) & (other < axis))

    has = crossings > 0
    with torch.no_grad():
        guess = torch.floor((time - first) / delta) + 1  # inf or nan where the axis has no crossing
    count = torch.where(has, guess.clamp(0, None).nan_to_num(0.0), 0.0).to(torch.int64)
    count = torch.minimum(count, crossings)
    # The division's rounding puts the guess at most one off (a difference of times far below a
    # crossing's spacing): the times themselves decide, one crossing down, then one up.
    count = count - ((count > 0) & ~before(count - 1)).to(torch.int64)
    return count + ((count < crossings) & before(count)).to(torch.int64)


def _scatter(flat: torch.Tensor, dims, voxels: torch.Tensor, weights: torch.Tensor) -> None:
    """``weights`` added at ``voxels`` (global indices) of a torus-ordered count volume."""
    if not len(voxels):
        return
    size_x, size_y, size_z = (int(d) for d in dims)
    linear = (torch.remainder(voxels[:, 0], size_x) * size_y + torch.remainder(voxels[:, 1], size_y)) * size_z \
        + torch.remainder(voxels[:, 2], size_z)
    flat.index_add_(0, linear, weights.to(flat.dtype))

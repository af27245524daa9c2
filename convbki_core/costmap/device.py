"""The planner's costmap computed where a torch window lives (a GPU): only the grid comes back.

The rules are ``columns``' (its module docstring), written as whole-window torch operations
over the columns the grid needs (its cells and the ``NEIGHBOUR_PASSES`` around them that a
hidden ground's estimate reads), in the compiled column pass's arithmetic, so that the cells
are the same: each voxel's moments summed class by class in float64 from the prior's, its
cost and kind by ``_voxel_cost``'s operations; per column the ground voxel (the highest ground
voxel under the lowest obstacle, else the highest), the lowest voxel, whether an obstacle
stands there; hidden grounds from the neighbours' in ``NEIGHBOUR_PASSES`` passes over the grid
(each cell the mean of its known 8 neighbours, summed in the compiled order); then each
column's cell from its ground voxel and its band.
"""

from __future__ import annotations

import numpy as np
import torch

from convbki_core.costmap.columns import (
    _COSTLY,
    _COSTLY_COST,
    _EMPTY_SUM,
    _FREE,
    _GROUND_SUM,
    _TOTAL,
    EMPTY_SHARE,
    GROUND_SHARE,
    MOMENTS,
    NEIGHBOUR_PASSES,
    UNKNOWN,
    _lethal_prior,
    _moment_weights,
    _prior_moments,
)
from convbki_core.costmap.grid import CostGrid, _cropped, columns_to_read
from convbki_core.costmap.profile import LETHAL, TraversabilityProfile
from convbki_core.memory.window import EVIDENCE

_TINY = float(np.finfo(np.float64).tiny)


def device_window_grid(alpha: torch.Tensor, mask: torch.Tensor, origin: np.ndarray, resolution: float,
                       profile: TraversabilityProfile, prior: float, region: tuple | None = None) -> CostGrid:
    """``costmap.window_grid`` of a torch window (``alpha`` (C, X, Y, Z), ``mask``, torus
    ``origin``) computed on its device: over the footprint, or ``region`` (origin cell (2,),
    (width, height) cells) only; one copy of the grid to the host."""
    size_x, size_y = mask.shape[:2]
    origin = np.asarray(origin, np.int64)
    inner_low, inner_high, low, high = columns_to_read(origin, (size_x, size_y), region)
    values = np.full((size_y, size_x), UNKNOWN, np.int8)
    if (high > low).all():
        read = _column_cells(alpha, mask, origin, low, high, resolution, profile, prior)
        inner = read[inner_low[0] - low[0]:inner_high[0] - low[0], inner_low[1] - low[1]:inner_high[1] - low[1]]
        values[inner_low[1]:inner_high[1], inner_low[0]:inner_high[0]] = inner.T.cpu().numpy()
    return _cropped(CostGrid(origin[:2].copy(), values, float(resolution)), region)


def _column_cells(alpha, mask, origin, low, high, resolution, profile, prior) -> torch.Tensor:
    """The cells (nx, ny) int8 of the columns from ``low`` to ``high`` (global order, x then y)."""
    device = alpha.device
    size_x, size_y, size_z = mask.shape
    px = torch.as_tensor((np.arange(low[0], high[0]) + origin[0]) % size_x, device=device)
    py = torch.as_tensor((np.arange(low[1], high[1]) + origin[1]) % size_y, device=device)
    pz = torch.as_tensor((np.arange(size_z) + origin[2]) % size_z, device=device)  # up the column
    columns = alpha[:, px][:, :, py][:, :, :, pz]
    marks = mask[px][:, py][:, :, pz]

    # Per voxel: the moments, as the compiled pass sums them (class by class, from the prior's).
    weights = _moment_weights(profile)
    base = _prior_moments(weights, prior)
    prior64 = float(np.float64(np.float32(prior)))
    sums = [torch.full(marks.shape, float(base[k]), dtype=torch.float64, device=device) for k in range(MOMENTS)]
    for c in range(columns.shape[0]):
        if not weights[:, c].any():
            continue
        above = columns[c].to(torch.float64) - prior64
        for k in range(MOMENTS):
            if weights[k, c] != 0:
                sums[k] += above if weights[k, c] == 1.0 else above * float(weights[k, c])
    total, empty_sum = sums[_TOTAL], sums[_EMPTY_SUM]
    evident = ((marks & EVIDENCE) != 0) & (total - float(prior) * columns.shape[0] >= profile.min_evidence)
    is_empty = evident & (empty_sum / total > EMPTY_SHARE)
    occupied = torch.clamp_min(total - empty_sum, _TINY)
    risk = torch.where(is_empty, 0.0, _voxel_cost(sums[_FREE], sums[_COSTLY], sums[_COSTLY_COST], occupied,
                                                  profile.risk_sigma, _lethal_prior(profile, prior)))
    is_ground = evident & ~is_empty & (sums[_GROUND_SUM] / occupied > GROUND_SHARE)
    obstacle = evident & ~is_empty & ~is_ground

    # Per column: its ground voxel's step up the window, its lowest voxel's, an obstacle.
    step = torch.arange(size_z, device=device)
    first_obstacle = torch.where(obstacle, step, size_z).amin(dim=2)
    ground_below = torch.where(is_ground & (step < first_obstacle[..., None]), step, -1).amax(dim=2)
    ground_any = torch.where(is_ground, step, -1).amax(dim=2)
    ground = torch.where(ground_below >= 0, ground_below, ground_any)  # -1: none seen
    lowest = torch.where(evident, step, size_z).amin(dim=2)
    has_obstacle = obstacle.any(dim=2)
    hidden = (ground < 0) & has_obstacle
    # The neighbours' mean in global z, as the compiled pass takes it (its rounding depends on it).
    bottom = int(origin[2])
    estimate = _ground_from_neighbours(torch.where(ground >= 0, (ground + bottom).to(torch.float64), torch.nan))
    # The ground of a hidden column from the neighbours' (rounded), or under its lowest voxel; in steps.
    ground = torch.where(ground >= 0, ground, torch.where(
        torch.isnan(estimate), lowest - 1, torch.round(torch.nan_to_num(estimate)).to(torch.int64) - bottom))

    # Each column's cell: the most costly of its ground voxel and its band's voxels.
    above = (step - ground[..., None]).to(torch.float64) * float(resolution)
    in_band = (above >= profile.min_obstacle_height - 1e-9) & (above <= profile.robot_height + 1e-9)
    surface = is_ground & (step == ground[..., None])
    counted = evident & (in_band | surface)
    cost = torch.where(counted, risk, -torch.inf).amax(dim=2)
    observed = (counted & (surface | ~is_empty)).any(dim=2) & ((ground_below >= 0) | (ground_any >= 0) | hidden)
    cells = torch.round(torch.clamp(cost, 0.0, float(LETHAL))).to(torch.int8)
    return torch.where(observed, cells, torch.tensor(UNKNOWN, dtype=torch.int8, device=device))


def _voxel_cost(free, costly, costly_cost, occupied, risk_sigma: float, lethal_prior: float) -> torch.Tensor:
    """``costmap``'s cost of occupied voxels from their moments (rule 4), in the compiled order of operations."""
    lethal = torch.clamp_min(occupied - free - costly, 0.0)
    lethal_share = torch.clamp_max(lethal / occupied, 1.0)
    kind_cost = torch.where(free / occupied > 0.5, 0.0, torch.where(
        lethal_share < 0.5, costly_cost / torch.clamp_min(costly, _TINY), float(LETHAL)))
    evidence = torch.clamp_max(torch.clamp_min((lethal - lethal_prior) / occupied, 0.0), 1.0)
    margin = LETHAL * (evidence + risk_sigma * torch.sqrt(evidence * (1.0 - evidence) / (occupied + 1.0)))
    return torch.clamp_max(torch.clamp_min(torch.maximum(kind_cost, margin), 0.0), 100.0)


def _ground_from_neighbours(grid: torch.Tensor) -> torch.Tensor:
    """``grid`` (NaN: no ground) with each NaN cell given the mean of its known 8 neighbours,
    ``NEIGHBOUR_PASSES`` times, cells beyond the grid unknown: ``costmap._ground_near`` for
    every cell at once (its sums in the same order)."""
    for _ in range(NEIGHBOUR_PASSES):
        padded = torch.nn.functional.pad(grid[None], (1, 1, 1, 1), value=torch.nan)[0]
        total = torch.zeros_like(grid)
        count = torch.zeros_like(grid)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx or dy:
                    near = padded[1 + dx:padded.shape[0] - 1 + dx, 1 + dy:padded.shape[1] - 1 + dy]
                    known = ~torch.isnan(near)
                    total = torch.where(known, total + near, total)
                    count += known
        grid = torch.where(torch.isnan(grid) & (count > 0), total / count, grid)
    return grid

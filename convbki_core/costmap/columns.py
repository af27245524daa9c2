"""A planner's view of the semantic map: a traversability cost per ground cell.

The map is a set of voxels with Dirichlet concentrations. A planner wants, per cell of a 2D
grid (a column of voxels), how costly it is to drive there, as Nav2 reads an occupancy
grid: 0 free .. 100 lethal, -1 unknown. Per column:

1. **Empty or occupied.** Class 0 is space that rays found empty. A voxel whose class 0
   holds more than three quarters of its concentration is empty space and costs nothing (a
   mover that left, emptied by free space, no longer blocks); the others are occupied. Not
   half: rays that graze an object's edge, or a sparse surface seen from afar, leave
   empty-space evidence in voxels that are still there, and a planner should find an
   obstacle empty only when the rays say so clearly.
2. **Ground.** An occupied voxel is ground when the ground classes (a profile's
   ``ground_classes``: road, parking, sidewalk, ...) hold more than half of its occupied
   evidence. The column's ground is its highest ground voxel under its lowest obstacle
   voxel (so leaves read as terrain on top of a tree do not lift the ground into the
   canopy), or its highest ground voxel where no obstacle is under one. A column whose
   ground is hidden (under a car) takes its neighbours' ground height, and failing that the
   height just under its lowest voxel.
3. **The band.** Voxels from ``min_obstacle_height`` above the ground up to
   ``robot_height`` can be in the robot's way; a kerb lower than the first, or a canopy
   above the second, is not.
4. **The voxel's cost.** An occupied voxel's classes are read as kinds, as a planner reads
   costs: free (a class cost of at most ``FREE_MAX``: road and parking for a car), costly
   (between: a kerb-side surface) and lethal (at least ``LETHAL_MIN``: what stands in the way).
   Given that the voxel is occupied, its Dirichlet posterior gives each kind an expected share
   (the aggregation property: the occupied classes' share is again Dirichlet, with the
   concentrations ``alpha_1 .. alpha_C`` summing to ``A = alpha0 - alpha_empty``), ``p_free``,
   ``p_costly`` and ``p_lethal``. The voxel costs its most likely kind, read from the cheapest:
   0 when ``p_free`` is over one half (a road whose evidence the input also called sidewalk
   or terrain now and then is free, whatever that noise), else the mean cost of its costly
   classes while ``p_lethal`` is under one half, else ``LETHAL`` (100). The
   uncertainty goes where a planner needs it, near what stands in the way: ``p_lethal`` (from
   the lethal classes' evidence, the prior left out) has the Beta posterior standard deviation
   ``sqrt(p_lethal (1 - p_lethal) / (A + 1))``, and the voxel costs at least ``LETHAL *
   (p_lethal + risk_sigma * sd)``: a road voxel with a little of a car's evidence costs a
   little, one the map is unsure between road and car costs more the less it has seen.
   (Conditioning on occupancy matters: the rays that graze a fence leave empty-space evidence
   in its voxels, which must not make the fence a part-obstacle.)
5. **The cell** costs the most of its ground voxel and its band voxels. A column with
   neither ground evidence nor anything occupied in its band (only empty space, or nothing
   seen) is unknown.

Here these rules over voxels given as a list (``column_costs``: what a saved map or the
voxels gathered from a window hold), in numpy, with the compiled estimate of a hidden ground
that must equal it. The profile is in ``profile``, the grids in ``grid``; ``window_pass``
computes the same cells in place from the window's arrays, ``device`` on a torch device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.costmap.profile import FREE_MAX, LETHAL, LETHAL_MIN, TraversabilityProfile

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

UNKNOWN = -1
GROUND_SHARE = 0.5  # an occupied voxel is ground when the ground classes hold more than this share
EMPTY_SHARE = 0.75  # a voxel is empty space when class 0 (seen empty by rays) holds more than this share
NEIGHBOUR_PASSES = 3  # how many cells away a hidden column looks for its ground height


@dataclass(frozen=True)
class ColumnCosts:
    """The cost of every observed column: ``cells`` (M, 2) global x, y voxel indices, ``cost``
    (M,) int8 in -1 (unknown), 0..100, and the ground height of each (voxel index z, or the
    estimate for a hidden one)."""

    cells: np.ndarray
    cost: np.ndarray
    ground: np.ndarray


# The sums each voxel's cost is read from (its "moments"), rows of ``_moment_weights``: every
# class (alpha0); the free and the costly kinds' classes (class 0, empty space, in neither; the
# lethal classes' sum is what the occupied concentration leaves); the costly classes weighted
# by their costs; the ground classes; class 0.
(_TOTAL, _FREE, _COSTLY, _COSTLY_COST, _GROUND_SUM, _EMPTY_SUM) = range(6)
MOMENTS = 6
# What a class adds its run to, in the compiled column pass (``_class_codes``): each common
# set of moments has a loop of its own, so a lethal class's run is added once, not six times.
_ONLY_TOTAL, _FREE_GROUND, _COSTLY_GROUND, _EMPTY_ONLY, _ANY_ROWS = range(5)


def _kinds(profile: TraversabilityProfile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(C,) bool each: the free, costly and lethal classes of a profile (class 0 in none)."""
    costs = profile.class_costs.astype(np.float64)
    free, lethal = costs <= FREE_MAX, costs >= LETHAL_MIN
    costly = ~free & ~lethal
    for kind in (free, costly, lethal):
        kind[0] = False
    return free, costly, lethal


def _moment_weights(profile: TraversabilityProfile) -> np.ndarray:
    """(MOMENTS, C) float64: per row, each class's weight in that sum."""
    costs = profile.class_costs.astype(np.float64)
    free, costly, _ = _kinds(profile)
    ground = np.zeros(len(costs))
    ground[list(profile.ground_classes)] = 1.0
    empty = np.zeros(len(costs))
    empty[0] = 1.0
    return np.ascontiguousarray(np.stack([np.ones(len(costs)), free, costly, costly * costs, ground, empty])
                                .astype(np.float64))


def _class_codes(weights: np.ndarray) -> np.ndarray:
    """(C,) int64: per class, which of the column pass's loops adds its run (the moments it
    has a weight in): the total alone (a lethal class), the total, free and ground sums (road),
    the total, costly, costly-cost and ground sums (sidewalk), the total and empty sums (class
    0), or every moment with its weight (any other class)."""
    codes = np.full(weights.shape[1], _ANY_ROWS, np.int64)
    for c in range(weights.shape[1]):
        used = tuple(np.flatnonzero(weights[:, c]).tolist())
        exact = all(weights[k, c] == 1.0 for k in used if k != _COSTLY_COST)  # indicators, as they are
        if used == (_TOTAL,) and exact:
            codes[c] = _ONLY_TOTAL
        elif used == (_TOTAL, _FREE, _GROUND_SUM) and exact:
            codes[c] = _FREE_GROUND
        elif used == (_TOTAL, _COSTLY, _COSTLY_COST, _GROUND_SUM) and exact:
            codes[c] = _COSTLY_GROUND
        elif used == (_TOTAL, _EMPTY_SUM) and exact:
            codes[c] = _EMPTY_ONLY
    return codes


def _prior_moments(weights: np.ndarray, prior: float) -> np.ndarray:
    """(MOMENTS,) float64: the moments of a voxel whose every class holds the prior, summed in class order."""
    base = np.zeros(weights.shape[0])
    prior = float(np.float32(prior))  # the window's float32 prior
    for c in range(weights.shape[1]):
        base += prior * weights[:, c]
    return base


def _moments(alpha: np.ndarray, profile: TraversabilityProfile, prior: float) -> np.ndarray:
    """Per voxel, the sums of ``_moment_weights``, float64 (N, MOMENTS). Written as the
    prior's moments plus those of the evidence above it, class by class in float64: a class
    at the prior adds exactly nothing, so the window's kernel below skips it and computes the
    same sums, and a grid from the window equals the grid of the same voxels saved."""
    weights = _moment_weights(profile)
    base = _prior_moments(weights, prior)
    if HAVE_NUMBA:
        return _row_moments(np.ascontiguousarray(alpha), weights, np.float64(np.float32(prior)), base)
    return base + (np.asarray(alpha, np.float64) - np.float64(np.float32(prior))) @ weights.T


if HAVE_NUMBA:

    @njit(nogil=True)
    def _row_moments(alpha, weights, prior, base):  # pragma: no cover - compiled
        rows, classes = alpha.shape
        out = np.zeros((rows, MOMENTS))
        for row in range(rows):
            for k in range(MOMENTS):
                total = base[k]
                for c in range(classes):
                    above = np.float64(alpha[row, c]) - prior
                    if above != 0.0:
                        total += above * weights[k, c]
                out[row, k] = total
        return out


def _lethal_prior(profile: TraversabilityProfile, prior: float) -> float:
    """What the prior alone puts in the lethal classes' sum (left out of the lethal share)."""
    return float(np.float32(prior)) * float(_kinds(profile)[2].sum())


def _voxel_risks(moments: np.ndarray, risk_sigma: float, lethal_prior: float) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """Per voxel: its cost (the module docstring's rule 4; 0 where it is empty space), whether
    it is ground (the ground classes hold most of its occupied evidence) and whether it is empty."""
    total = moments[:, _TOTAL]
    occupied = np.maximum(total - moments[:, _EMPTY_SUM], np.finfo(np.float64).tiny)
    is_empty = moments[:, _EMPTY_SUM] / total > EMPTY_SHARE
    lethal = np.maximum(occupied - moments[:, _FREE] - moments[:, _COSTLY], 0.0)
    free, lethal_share = moments[:, _FREE] / occupied, np.minimum(lethal / occupied, 1.0)
    kind_cost = np.where(free > 0.5, 0.0, np.where(
        lethal_share < 0.5, moments[:, _COSTLY_COST] / np.maximum(moments[:, _COSTLY], np.finfo(np.float64).tiny),
        LETHAL))
    evidence = np.clip((lethal - lethal_prior) / occupied, 0.0, 1.0)
    margin = LETHAL * (evidence + risk_sigma * np.sqrt(evidence * (1.0 - evidence) / (occupied + 1.0)))
    risk = np.where(is_empty, 0.0, np.clip(np.maximum(kind_cost, margin), 0.0, LETHAL))
    is_ground = ~is_empty & (moments[:, _GROUND_SUM] / occupied > GROUND_SHARE)
    return risk, is_ground, is_empty


def column_costs(indices: np.ndarray, alpha: np.ndarray, resolution: float,
                 profile: TraversabilityProfile, prior: float = 0.0) -> ColumnCosts:
    """The cost of each column holding voxels with evidence (see the module's docstring);
    ``prior``: the map's prior concentration per class, which is not evidence."""
    indices = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    alpha = np.asarray(alpha)
    if not np.issubdtype(alpha.dtype, np.floating):
        alpha = alpha.astype(np.float64)
    moments = _moments(alpha, profile, prior)
    evident = moments[:, _TOTAL] - prior * alpha.shape[1] >= profile.min_evidence
    indices, moments = indices[evident], moments[evident]
    if not len(indices):
        empty = np.zeros((0, 2), np.int64)
        return ColumnCosts(empty, np.zeros(0, np.int8), np.zeros(0, np.int64))
    risk, is_ground, is_empty = _voxel_risks(moments, profile.risk_sigma, _lethal_prior(profile, prior))
    # Columns by a linear key (unique over one int64 is far faster than over rows).
    low = indices[:, :2].min(axis=0)
    span = indices[:, 1].max() - low[1] + 1
    keys, column = np.unique((indices[:, 0] - low[0]) * span + (indices[:, 1] - low[1]), return_inverse=True)
    column = column.reshape(-1)
    cells = np.stack([keys // span + low[0], keys % span + low[1]], axis=1)
    count = len(cells)
    z = indices[:, 2]

    # 1. ground: the highest ground voxel of each column; hidden columns from their neighbours
    ground = np.full(count, np.iinfo(np.int64).min)
    # The ground under the lowest obstacle voxel where one is under the column's ground
    # evidence (leaves or a sign read as terrain on top of a tree), else the highest.
    obstacle = ~is_ground & ~is_empty
    first_obstacle = np.full(count, np.iinfo(np.int64).max)
    np.minimum.at(first_obstacle, column[obstacle], z[obstacle])
    below = is_ground & (z < first_obstacle[column])
    np.maximum.at(ground, column[below], z[below])
    above_only = is_ground & (ground[column] == np.iinfo(np.int64).min)
    np.maximum.at(ground, column[above_only], z[above_only])
    has_ground = ground > np.iinfo(np.int64).min
    estimate = _ground_from_neighbours(cells, ground.astype(np.float64), has_ground)
    lowest = np.full(count, np.iinfo(np.int64).max)
    np.minimum.at(lowest, column, z)
    ground_z = np.where(has_ground, ground, np.where(np.isnan(estimate), lowest - 1,
                                                     np.round(np.nan_to_num(estimate)).astype(np.int64)))

    # 2.-4. the ground voxel's cost, and the band's
    above = (z - ground_z[column]) * resolution
    low_step = profile.min_obstacle_height
    in_band = (above >= low_step - 1e-9) & (above <= profile.robot_height + 1e-9)
    surface = is_ground & (z == ground_z[column])
    counted = in_band | surface
    cost = np.full(count, -np.inf)
    np.maximum.at(cost, column[counted], risk[counted])
    # Something in the band that is not empty space, or ground seen: the column is observed.
    occupied = counted & ~is_empty
    observed = np.zeros(count, bool)
    observed[column[occupied | surface]] = True
    values = np.where(observed & np.isfinite(cost), np.rint(np.clip(cost, 0, LETHAL)), UNKNOWN).astype(np.int8)
    return ColumnCosts(cells, values, ground_z)


def _ground_from_neighbours(cells: np.ndarray, ground: np.ndarray, known: np.ndarray) -> np.ndarray:
    """For columns without ground evidence: the mean ground height of the nearest columns that
    have it, up to NEIGHBOUR_PASSES cells away; NaN where none is that close."""
    estimate = np.where(known, ground, np.nan)
    if known.all() or not known.any():
        return estimate
    low = cells.min(axis=0) - NEIGHBOUR_PASSES
    shape = cells.max(axis=0) - low + 1 + NEIGHBOUR_PASSES
    local = cells - low
    if HAVE_NUMBA:  # each unknown column from the patch of neighbours its estimate depends on
        top = np.full(tuple(shape), _NO_GROUND, np.int64)
        top[tuple(local[known].T)] = ground[known].astype(np.int64)
        with parallel_region():
            estimate[~known] = _ground_near_cells(top, np.ascontiguousarray(local[~known]))
        return estimate
    grid = np.full(tuple(shape), np.nan)
    grid[tuple(local.T)] = estimate
    return _spread_ground(grid)[tuple(local.T)]


def _spread_ground(grid: np.ndarray) -> np.ndarray:
    """``grid`` (NaN: no ground height) with each NaN cell given the mean of its known 8
    neighbours, NEIGHBOUR_PASSES times (a pass sees the cells the previous one filled). The
    grid needs NEIGHBOUR_PASSES cells of margin beyond the columns it serves. The numpy rule;
    compiled, ``_ground_near`` gives the same value for one cell from its patch alone."""
    for _ in range(NEIGHBOUR_PASSES):
        missing = np.isnan(grid)
        if not missing.any():
            break
        padded = np.pad(grid, 1, constant_values=np.nan)
        neighbours = np.stack([padded[1 + dx:padded.shape[0] - 1 + dx, 1 + dy:padded.shape[1] - 1 + dy]
                               for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy])
        sums = np.nansum(neighbours, axis=0)
        counts = np.sum(~np.isnan(neighbours), axis=0)
        fill = missing & (counts > 0)
        grid[fill] = sums[fill] / counts[fill]
    return grid


# A column without ground, in the int64 grids of ground heights the compiled passes read.
_NO_GROUND = np.iinfo(np.int64).min

if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def _ground_near(top, cx, cy, patch, fresh):  # pragma: no cover - compiled
        """``_spread_ground``'s estimate for the hidden column at global-order (cx, cy) of ``top``
        (ground z or _NO_GROUND), NaN where none is near: the passes run over the patch of
        NEIGHBOUR_PASSES cells around it only, pass p over the cells within NEIGHBOUR_PASSES - p
        of it (those its value depends on after pass p). Cells beyond the window count as cells
        without ground, as in the grid with a margin."""
        reach = NEIGHBOUR_PASSES
        size_x, size_y = top.shape
        for i in range(2 * reach + 1):
            for j in range(2 * reach + 1):
                gx, gy = cx + i - reach, cy + j - reach
                inside = 0 <= gx < size_x and 0 <= gy < size_y
                patch[i, j] = np.float64(top[gx, gy]) if inside and top[gx, gy] != _NO_GROUND else np.nan
        for step in range(1, reach + 1):
            near = reach - step
            for i in range(reach - near, reach + near + 1):
                for j in range(reach - near, reach + near + 1):
                    fresh[i, j] = patch[i, j]
                    if not np.isnan(patch[i, j]):
                        continue
                    total = 0.0
                    count = 0
                    for dx in (-1, 0, 1):
                        for dy in (-1, 0, 1):
                            if (dx or dy) and not np.isnan(patch[i + dx, j + dy]):
                                total += patch[i + dx, j + dy]
                                count += 1
                    if count:
                        fresh[i, j] = total / count
            for i in range(reach - near, reach + near + 1):
                for j in range(reach - near, reach + near + 1):
                    patch[i, j] = fresh[i, j]
        return patch[reach, reach]

    @njit(parallel=True, nogil=True)
    def _ground_near_cells(top, cells):  # pragma: no cover - compiled
        """``_ground_near`` of each of ``cells`` (n, 2) of ``top``."""
        side = 2 * NEIGHBOUR_PASSES + 1
        estimates = np.empty(cells.shape[0])
        chunk = 256
        for first in prange((cells.shape[0] + chunk - 1) // chunk):
            patch = np.empty((side, side))
            fresh = np.empty((side, side))
            for i in range(first * chunk, min(cells.shape[0], (first + 1) * chunk)):
                estimates[i] = _ground_near(top, cells[i, 0], cells[i, 1], patch, fresh)
        return estimates

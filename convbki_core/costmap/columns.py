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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.memory.window import EVIDENCE, gather_window

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange

UNKNOWN = -1
LETHAL = 100
# Cost kinds, as a planner reads them (Nav2's map_server: free at most 25 of 100): a class cost of
# at most FREE_MAX is free, of at least LETHAL_MIN lethal, and costly between.
FREE_MAX = 25
LETHAL_MIN = 90
GROUND_SHARE = 0.5  # an occupied voxel is ground when the ground classes hold more than this share
EMPTY_SHARE = 0.75  # a voxel is empty space when class 0 (seen empty by rays) holds more than this share
NEIGHBOUR_PASSES = 3  # how many cells away a hidden column looks for its ground height


class ProfileError(ValueError):
    """A traversability profile that cannot be used: one line."""


@dataclass(frozen=True)
class TraversabilityProfile:
    """What a class costs a given robot (0 free .. 100 lethal), which classes are ground, and
    the robot's height band."""

    name: str
    class_costs: np.ndarray  # (C,) float64 in [0, 100]; class 0 (empty space) is 0
    ground_classes: tuple[int, ...]
    robot_height: float = 2.0  # metres above the ground in which evidence is in the way
    min_obstacle_height: float = 0.25  # metres: lower steps (a kerb) are not obstacles
    risk_sigma: float = 1.0  # standard deviations of the lethal share added as a margin
    # Voxels with less evidence than this (summed kernel weights of the points, past the prior)
    # are left out as unobserved: the kernel spreads a surface's evidence thinly over the
    # voxels around it, and such a voxel would pass for ground or obstacle on a whiff.
    min_evidence: float = 0.5


def load_profile(path: str | Path, class_names: tuple[str, ...]) -> TraversabilityProfile:
    """A profile from YAML: ``name``, ``costs`` {class name: 0..100} for every class but
    ``class_names[0]``, ``ground`` [class names], ``robot_height``, ``min_obstacle_height``,
    ``risk_sigma``. Raises ProfileError with one line naming the file and the problem."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise ProfileError(f"{path}: cannot read the traversability profile ({error.strerror or error})") from None
    except yaml.YAMLError as error:
        raise ProfileError(f"{path}: not YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("costs"), dict):
        raise ProfileError(f"{path}: a traversability profile needs a `costs` mapping of class names to 0..100")
    index = {name: number for number, name in enumerate(class_names)}
    costs = np.zeros(len(class_names))
    for name, cost in data["costs"].items():
        if name not in index or index[name] == 0:
            raise ProfileError(f"{path}: unknown class '{name}' in costs (classes: {', '.join(class_names[1:])})")
        if isinstance(cost, bool) or not isinstance(cost, (int, float)) or not 0 <= cost <= LETHAL:
            raise ProfileError(f"{path}: cost of '{name}' must be a number from 0 to {LETHAL}, got {cost!r}")
        costs[index[name]] = float(cost)
    missing = [name for name in class_names[1:] if name not in data["costs"]]
    if missing:
        raise ProfileError(f"{path}: no cost for {', '.join(missing)} (every class needs one)")
    ground = data.get("ground") or []
    unknown = [name for name in ground if name not in index or index[name] == 0]
    if unknown or not ground:
        raise ProfileError(f"{path}: `ground` must list ground classes, " +
                           (f"unknown: {', '.join(map(str, unknown))}" if unknown else "got none"))
    settings = {}
    for key, default, low in (("robot_height", 2.0, 0.0), ("min_obstacle_height", 0.25, 0.0), ("risk_sigma", 1.0, 0.0),
                              ("min_evidence", 0.5, 0.0)):
        value = data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < low:
            raise ProfileError(f"{path}: {key} must be a number >= {low:g}, got {value!r}")
        settings[key] = float(value)
    if settings["min_obstacle_height"] >= settings["robot_height"]:
        raise ProfileError(f"{path}: min_obstacle_height must be below robot_height")
    return TraversabilityProfile(str(data.get("name", path.stem)), costs, tuple(index[name] for name in ground),
                                 **settings)


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


@dataclass(frozen=True)
class CostGrid:
    """A 2D grid of costs as nav_msgs/OccupancyGrid holds it: ``values`` (rows = y, columns =
    x) int8, cell (0, 0) at global voxel x, y index ``origin``."""

    origin: np.ndarray  # (2,) int64
    values: np.ndarray  # (height, width) int8
    resolution: float

    @property
    def origin_metres(self) -> np.ndarray:
        return self.origin.astype(np.float64) * self.resolution


def rasterise(columns: ColumnCosts, resolution: float, origin: np.ndarray | None = None,
              size: tuple[int, int] | None = None) -> CostGrid:
    """The columns as a grid; unobserved cells -1. Default extent: the observed columns'."""
    if origin is None:
        origin = columns.cells.min(axis=0) if len(columns.cells) else np.zeros(2, np.int64)
    origin = np.asarray(origin, np.int64)
    if size is None:
        size = tuple((columns.cells.max(axis=0) - origin + 1).tolist()) if len(columns.cells) else (0, 0)
    width, height = int(size[0]), int(size[1])
    values = np.full((height, width), UNKNOWN, np.int8)
    local = columns.cells - origin
    inside = (local[:, 0] >= 0) & (local[:, 0] < width) & (local[:, 1] >= 0) & (local[:, 1] < height)
    values[local[inside, 1], local[inside, 0]] = columns.cost[inside]
    return CostGrid(origin, values, float(resolution))


def _gathered_grid(indices: np.ndarray, alpha: np.ndarray, origin: np.ndarray, dims: np.ndarray, resolution: float,
                   profile: TraversabilityProfile, prior: float) -> CostGrid:
    """The grid of a window's gathered voxels over its footprint (``window_grid``'s rules the slow way)."""
    return rasterise(column_costs(indices, alpha, resolution, profile, prior), resolution,
                     np.asarray(origin[:2], np.int64), (int(dims[0]), int(dims[1])))


def grid_of_window(window, resolution: float, profile: TraversabilityProfile, prior: float,
                   region: tuple | None = None) -> CostGrid:
    """``window_grid`` of a mapper's window (``RollingWindow`` or ``TorchWindow``) over its
    footprint, or over ``region`` (origin cell (2,), (width, height) cells) only: read in place
    where its arrays are in host memory (numpy, or torch on the CPU), skipping the class runs
    its ``classes_by_column`` says hold the prior; computed on the device where they are on a
    GPU (``device_costmap``: the same cells, only the grid comes back)."""
    alpha, mask = window.alpha, window.mask
    if not isinstance(alpha, np.ndarray):
        if alpha.device.type != "cpu":
            from convbki_core.costmap.device import device_window_grid  # it builds on this module

            return device_window_grid(alpha, mask, window.origin, resolution, profile, prior, region)
        alpha, mask = alpha.numpy(), mask.numpy()
    return window_grid(alpha, mask, window.origin, window.dims, resolution, profile, prior,
                       window.classes_by_column(), region)


def rolling_geometry(position: np.ndarray, resolution: float, size: float, window_extent: float) -> tuple:
    """(origin cell (2,) int64, cells per edge) of the square grid of edge ``size`` metres (at
    most ``window_extent``; 0: that) centred on ``position``: the node's rolling costmap."""
    edge = min(size, window_extent) if size > 0 else window_extent
    cells = max(1, round(edge / resolution))
    centre = np.floor(np.asarray(position[:2], np.float64) / resolution).astype(np.int64)
    return centre - cells // 2, cells


def _cropped(grid: CostGrid, region: tuple | None) -> CostGrid:
    return grid if region is None else crop(grid, *region)


def crop(grid: CostGrid, origin: np.ndarray, size: tuple[int, int]) -> CostGrid:
    """The part of ``grid`` at ``origin`` (global cell) of ``size`` (width, height) cells,
    unknown where ``grid`` does not reach."""
    origin = np.asarray(origin, np.int64)
    width, height = int(size[0]), int(size[1])
    values = np.full((height, width), UNKNOWN, np.int8)
    shift = origin - grid.origin  # where the crop starts in grid's cells (x, y)
    x0, y0 = max(0, -shift[0]), max(0, -shift[1])
    x1 = min(width, grid.values.shape[1] - shift[0])
    y1 = min(height, grid.values.shape[0] - shift[1])
    if x1 > x0 and y1 > y0:
        values[y0:y1, x0:x1] = grid.values[y0 + shift[1]:y1 + shift[1], x0 + shift[0]:x1 + shift[0]]
    return CostGrid(origin, values, grid.resolution)


def columns_to_read(origin: np.ndarray, footprint: tuple[int, int], region: tuple | None) -> tuple:
    """(inner low, inner high, low, high): in the grid's global order (x, y from the window's
    origin, ``footprint`` columns), the columns whose cells ``region`` asks for (all: None) and
    those to read, with the margin a hidden ground's estimate depends on."""
    footprint = np.asarray(footprint, np.int64)
    if region is None:
        zero = np.zeros(2, np.int64)
        return zero, footprint, zero, footprint
    start = np.asarray(region[0], np.int64) - np.asarray(origin, np.int64)[:2]
    end = start + np.asarray(region[1], np.int64)
    return (np.clip(start, 0, footprint), np.clip(end, 0, footprint),
            np.clip(start - NEIGHBOUR_PASSES, 0, footprint), np.clip(end + NEIGHBOUR_PASSES, 0, footprint))


def window_grid(alpha: np.ndarray, mask: np.ndarray, origin: np.ndarray, dims: np.ndarray, resolution: float,
                profile: TraversabilityProfile, prior: float, classes: np.ndarray | None = None,
                region: tuple | None = None) -> CostGrid:
    """The costs of the dense torus window's columns (``RollingWindow``'s ``alpha`` (C, X, Y, Z),
    ``mask``, ``origin``, ``dims``) over its footprint: equal to ``rasterise(column_costs(
    *window.items(), ...))`` on that footprint, without gathering the voxels. ``classes``
    (X, Y) uint64, the window's ``classes_by_column``: the class runs of a column whose bit is
    clear hold the prior and are not read; None: every run is read. ``region`` (origin cell
    (2,), (width, height) cells): only that part, equal to ``crop`` of the footprint's grid,
    reading only its columns and the NEIGHBOUR_PASSES around them that a hidden ground's
    estimate depends on (a rolling costmap smaller than the window costs its share of it).

    One compiled pass over the columns computes each column's voxel costs and ground, and the
    cell of every column whose ground it saw, and keeps the voxel costs of the columns whose
    ground is hidden (a few of them); a second pass gives those their neighbours' ground and
    their cells, without reading the window again."""
    origin = np.asarray(origin, np.int64)
    if not HAVE_NUMBA:  # the same rules, through the voxels gathered
        return _cropped(_gathered_grid(*gather_window(alpha, mask.copy(), origin, dims), origin, dims, resolution,
                                       profile, prior), region)
    size_x, size_y = mask.shape[:2]
    partial = region is not None
    inner_low, inner_high, low, high = columns_to_read(origin, (size_x, size_y), region)
    dims = np.asarray(dims, np.int64)
    read_all = classes is None
    if read_all:
        classes = np.zeros((size_x, size_y), np.uint64)
    weights = _moment_weights(profile)
    codes = _class_codes(weights)
    rules = np.array([float(resolution), profile.min_obstacle_height, profile.robot_height, profile.min_evidence,
                      profile.risk_sigma, float(prior) * alpha.shape[0], _lethal_prior(profile, prior)])
    base = _prior_moments(weights, prior)
    # In global order: row y of the grid is the column at origin + y (the torus unrolled).
    # Every cell is written when every column is read; a region leaves the rest unknown.
    values = np.full((size_y, size_x), UNKNOWN, np.int8) if partial else np.empty((size_y, size_x), np.int8)
    top = np.empty((size_x, size_y), np.int64)
    # Where the voxel costs of a hidden column are kept, or -1.
    hidden = np.full((size_x, size_y), -1, np.int64) if partial else np.empty((size_x, size_y), np.int64)
    ground_z = np.empty((size_x, size_y), np.int64)  # filled where ``hidden``
    # Room for every column of a row, but a row fills only as many slots as it has hidden
    # columns, and only the pages written are ever mapped.
    kept_risk = np.empty((size_x * size_y, mask.shape[2]))
    kept_kind = np.empty((size_x * size_y, mask.shape[2]), np.uint8)
    with parallel_region():
        _grounded_columns(alpha, mask, origin, dims, codes, weights, np.float32(prior), base, rules, classes,
                          read_all, low, high, values, top, hidden, ground_z, kept_risk, kept_kind)
    # The inner columns' hidden grounds only: the margin's would need neighbours not read.
    inner = hidden[inner_low[0]:inner_high[0], inner_low[1]:inner_high[1]]
    # C order whatever the count (argwhere's is F for two cells or more): one compiled signature.
    cells = np.ascontiguousarray(np.argwhere(inner >= 0) + inner_low, np.int64)
    if len(cells):
        with parallel_region():
            _hidden_columns(origin, rules, cells, top, ground_z, hidden, kept_risk, kept_kind, values)
    return _cropped(CostGrid(origin[:2].copy(), values, float(resolution)), region)


_NO_GROUND = np.iinfo(np.int64).min
_NO_VOXEL = np.iinfo(np.int64).max
_EVIDENT, _GROUND, _EMPTY = 1, 2, 4
_TINY = np.finfo(np.float64).tiny
# The profile's numbers as the compiled passes take them (one float64 array).
_RESOLUTION, _MIN_HEIGHT, _ROBOT_HEIGHT, _MIN_EVIDENCE, _RISK_SIGMA, _PRIOR_TOTAL, _LETHAL_PRIOR = range(7)

if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def _column_evident(mask, x, y, kind):  # pragma: no cover - compiled
        """Whether the column holds a voxel with evidence; clears ``kind``."""
        evident = False
        for z in range(mask.shape[2]):
            kind[z] = 0
            evident |= (mask[x, y, z] & EVIDENCE) != 0
        return evident

    @njit(nogil=True, inline="always")
    def _add_run(alpha, c, x, y, read_all, codes, weights, prior, sums):  # pragma: no cover - compiled
        """Class c's run of the column into its moment ``sums`` (MOMENTS, Z), as ``_row_moments``
        adds it (nothing where it holds the prior), to the moments it has a weight in only
        (``_class_codes``: one loop per common set of them, each vectorised)."""
        size_z = alpha.shape[3]
        if read_all:
            held = False
            for z in range(size_z):
                held |= alpha[c, x, y, z] != prior
            if not held:
                return
        prior64 = np.float64(prior)
        code = codes[c]
        if code == _ONLY_TOTAL:
            for z in range(size_z):
                sums[_TOTAL, z] += np.float64(alpha[c, x, y, z]) - prior64
        elif code == _FREE_GROUND:
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_FREE, z] += value
                sums[_GROUND_SUM, z] += value
        elif code == _COSTLY_GROUND:
            cost = weights[_COSTLY_COST, c]
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_COSTLY, z] += value
                sums[_COSTLY_COST, z] += value * cost
                sums[_GROUND_SUM, z] += value
        elif code == _EMPTY_ONLY:
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[_TOTAL, z] += value
                sums[_EMPTY_SUM, z] += value
        else:
            w0, w1, w2 = weights[0, c], weights[1, c], weights[2, c]
            w3, w4, w5 = weights[3, c], weights[4, c], weights[5, c]
            for z in range(size_z):
                value = np.float64(alpha[c, x, y, z]) - prior64
                sums[0, z] += value * w0
                sums[1, z] += value * w1
                sums[2, z] += value * w2
                sums[3, z] += value * w3
                sums[4, z] += value * w4
                sums[5, z] += value * w5

    @njit(nogil=True, inline="always")
    def _reads_class(c, runs, read_all):  # pragma: no cover - compiled
        """Whether class c's run of a column with the class bits ``runs`` is read: class 0
        (empty space) always, as free space adds it without a bit."""
        return read_all or c == 0 or ((runs >> np.uint64(c)) & np.uint64(1)) != 0

    @njit(nogil=True, inline="always")
    def _voxel_cost(free, costly, costly_cost, occupied, rules):  # pragma: no cover - compiled
        """``_voxel_risks``' cost of one occupied voxel from its moments."""
        lethal = max(occupied - free - costly, 0.0)
        lethal_share = min(lethal / occupied, 1.0)
        if free / occupied > 0.5:
            kind_cost = 0.0
        elif lethal_share < 0.5:
            kind_cost = costly_cost / max(costly, _TINY)
        else:
            kind_cost = np.float64(LETHAL)
        evidence = min(max((lethal - rules[_LETHAL_PRIOR]) / occupied, 0.0), 1.0)
        margin = LETHAL * (evidence + rules[_RISK_SIGMA] * np.sqrt(evidence * (1.0 - evidence) / (occupied + 1.0)))
        return min(max(max(kind_cost, margin), 0.0), 100.0)

    @njit(nogil=True, inline="always")
    def _column_kinds(sums, mask, x, y, origin, dims, rules, risk, kind):  # pragma: no cover - compiled
        """One column's voxels (physical x, y) from their moment ``sums`` (MOMENTS, Z by physical z):
        per step up the window (global z = origin z + step) its risk and kind bits
        (``_voxel_risks``' rules) into ``risk``, ``kind``; returns (its ground voxel's global z
        by ``column_costs``' rule, its lowest voxel's, whether it holds an occupied voxel that
        is not ground)."""
        size_z = mask.shape[2]
        ground_below = _NO_GROUND  # the highest ground voxel under the first obstacle
        ground_any = _NO_GROUND
        obstacle_seen = False
        low = _NO_VOXEL
        z = origin[2] % dims[2] - 1  # the physical z of each step, without a division per voxel
        for step in range(size_z):
            global_z = origin[2] + step
            z = z + 1 if z + 1 < size_z else 0
            if (mask[x, y, z] & EVIDENCE) == 0:
                continue
            total, empty = sums[_TOTAL, z], sums[_EMPTY_SUM, z]
            if not total - rules[_PRIOR_TOTAL] >= rules[_MIN_EVIDENCE]:
                continue
            low = min(low, global_z)
            if empty / total > EMPTY_SHARE:
                risk[step] = 0.0
                kind[step] = _EVIDENT | _EMPTY
                continue
            occupied = max(total - empty, _TINY)
            risk[step] = _voxel_cost(sums[_FREE, z], sums[_COSTLY, z], sums[_COSTLY_COST, z], occupied, rules)
            if sums[_GROUND_SUM, z] / occupied > GROUND_SHARE:
                kind[step] = _EVIDENT | _GROUND
                ground_any = global_z
                if not obstacle_seen:
                    ground_below = global_z
            else:
                kind[step] = _EVIDENT
                obstacle_seen = True
        return (ground_below if ground_below != _NO_GROUND else ground_any), low, obstacle_seen

    @njit(nogil=True, inline="always")
    def _column_voxels(alpha, mask, x, y, origin, dims, codes, weights, prior, base, rules, runs, read_all, sums,
                       risk,
                       kind):  # pragma: no cover - compiled
        """``_column_kinds`` of one column read on its own (``runs``: its class bits)."""
        if not _column_evident(mask, x, y, kind):
            return _NO_GROUND, _NO_VOXEL, False
        # Class by class along z: a class's run of the column is contiguous in memory, where the
        # classes of one voxel lie a whole class plane apart. A run at the prior adds nothing and
        # is skipped: most classes of a column hold no evidence.
        for k in range(MOMENTS):
            sums[k, :] = base[k]
        for c in range(alpha.shape[0]):
            if _reads_class(c, runs, read_all):
                _add_run(alpha, c, x, y, read_all, codes, weights, prior, sums)
        return _column_kinds(sums, mask, x, y, origin, dims, rules, risk, kind)

    @njit(nogil=True, inline="always")
    def _column_value(risk, kind, origin_z, ground, rules):  # pragma: no cover - compiled
        """The cell of a column whose ground is at global z ``ground``: the most costly of its
        ground voxel and its band voxels, -1 unless something non-empty is in the band or its
        ground was seen."""
        cost = -np.inf
        observed = False
        for step in range(kind.shape[0]):
            bits = kind[step]
            if bits == 0:
                continue
            global_z = origin_z + step
            above = (global_z - ground) * rules[_RESOLUTION]
            in_band = above >= rules[_MIN_HEIGHT] - 1e-9 and above <= rules[_ROBOT_HEIGHT] + 1e-9
            surface = (bits & _GROUND) != 0 and global_z == ground
            if in_band or surface:
                cost = max(cost, risk[step])
                if surface or (bits & _EMPTY) == 0:
                    observed = True
        return np.int8(np.rint(min(max(cost, 0.0), 100.0))) if observed else np.int8(-1)

    @njit(parallel=True, nogil=True)
    def _grounded_columns(alpha, mask, origin, dims, codes, weights, prior, base, rules, classes, read_all, low,
                          high, values, top, hidden, ground_z, kept_risk,
                          kept_kind):  # pragma: no cover - compiled
        """Every column from ``low`` to ``high`` (x, y in global order, ``high`` excluded): its
        ground voxel into ``top``, its cell into ``values`` where it saw its own ground or holds
        no obstacle (then its ground does not matter); a hidden-ground column with an obstacle
        keeps its voxel costs (``_column_kinds``' ``risk`` and ``kind``) in a row of
        ``kept_risk``, ``kept_kind`` (the first free one of its x's ``size_y`` rows), whose
        number goes into ``hidden`` (-1 for the others), and the height under its lowest voxel
        into ``ground_z`` (for when no neighbour has ground); all in global order."""
        size_x, size_y, size_z = mask.shape
        for column_x in prange(low[0], high[0]):
            sums = np.empty((MOMENTS, size_z))  # the column's moments per physical z
            risk = np.empty(size_z)
            kind = np.empty(size_z, np.uint8)
            kept = column_x * size_y  # the next free row of this x's share of the kept costs
            x = (column_x + origin[0]) % size_x
            y = (low[1] + origin[1]) % size_y - 1
            for column_y in range(low[1], high[1]):
                y = y + 1 if y + 1 < size_y else 0
                ground, lowest, obstacle = _column_voxels(alpha, mask, x, y, origin, dims, codes, weights, prior,
                                                          base, rules, classes[x, y], read_all, sums, risk, kind)
                top[column_x, column_y] = ground
                hidden[column_x, column_y] = -1
                if ground != _NO_GROUND:
                    values[column_y, column_x] = _column_value(risk, kind, origin[2], ground, rules)
                else:  # nothing seen or only empty space, or hidden: its cell comes in the second pass
                    values[column_y, column_x] = -1
                    ground_z[column_x, column_y] = lowest - 1
                    if obstacle:
                        kept_risk[kept, :] = risk
                        kept_kind[kept, :] = kind
                        hidden[column_x, column_y] = kept
                        kept += 1

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

    @njit(parallel=True, nogil=True)
    def _hidden_columns(origin, rules, cells, top, ground_z, hidden, kept_risk, kept_kind,
                        values):  # pragma: no cover - compiled
        """The columns at global-order ``cells`` (n, 2), whose ground is hidden: the ground from
        their neighbours' (``top``, global order), or ``ground_z`` (under their lowest voxel)
        where none is near; their cells, from the voxel costs the first pass kept (row
        ``hidden`` of ``kept_risk``, ``kept_kind``), into ``values``."""
        count = cells.shape[0]
        chunk = 256
        side = 2 * NEIGHBOUR_PASSES + 1
        for first in prange((count + chunk - 1) // chunk):
            patch = np.empty((side, side))
            fresh = np.empty((side, side))
            for i in range(first * chunk, min(count, (first + 1) * chunk)):
                column_x, column_y = cells[i, 0], cells[i, 1]
                estimate = _ground_near(top, column_x, column_y, patch, fresh)
                ground = ground_z[column_x, column_y] if np.isnan(estimate) else np.int64(np.rint(estimate))
                kept = hidden[column_x, column_y]
                values[column_y, column_x] = _column_value(kept_risk[kept], kept_kind[kept], origin[2], ground, rules)

"""A planner's view of the semantic map: a traversability cost per ground cell.

The map is a set of voxels with Dirichlet concentrations. A planner wants, per cell of a 2D
grid (a column of voxels), how costly it is to drive there, as Nav2 reads an occupancy
grid: 0 free .. 100 lethal, -1 unknown. Per column:

1. **Ground.** The ground surface is the highest voxel whose expected probability of the
   ground classes (a profile's ``ground_classes``: road, parking, sidewalk, ...) is over
   one half. A column whose ground is hidden (under a car) takes its neighbours' ground
   height, and failing that the height just under its lowest voxel.
2. **The band.** Voxels from ``min_obstacle_height`` above the ground up to
   ``robot_height`` can be in the robot's way; a kerb lower than the first, or a canopy
   above the second, is not.
3. **Expected cost.** Each voxel's cost is the expectation of the class cost under its
   Dirichlet posterior, not the cost of its most likely class: with expected probabilities
   ``p = alpha / alpha0``, ``E[cost] = p . c`` and ``Var[cost] = (p . c^2 - (p . c)^2) /
   (alpha0 + 1)``. A risk margin adds ``risk_sigma`` standard deviations, so a voxel the map
   is unsure about costs more than one it is sure about. Class 0 (space that rays found
   empty) costs nothing, so a mover that left, emptied by free space, no longer blocks.
4. **The cell** costs the most of its ground voxel and its band voxels. A column with
   neither ground evidence nor anything in its band (only empty space, or nothing seen) is
   unknown.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

UNKNOWN = -1
LETHAL = 100
GROUND_SHARE = 0.5  # a voxel is ground when the ground classes hold more than this share
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
    risk_sigma: float = 1.0  # standard deviations of the cost added as a margin
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


def _moments(alpha: np.ndarray, profile: TraversabilityProfile) -> np.ndarray:
    """Per voxel, in one product with the concentrations (no (N, C) temporaries): alpha0,
    sum alpha c, sum alpha c^2, the ground classes' alpha, class 0's alpha; float64 (N, 5)."""
    costs = profile.class_costs
    ground = np.zeros(len(costs))
    ground[list(profile.ground_classes)] = 1.0
    empty = np.zeros(len(costs))
    empty[0] = 1.0
    weights = np.stack([np.ones(len(costs)), costs, costs ** 2, ground, empty], axis=1)
    return (alpha @ weights.astype(alpha.dtype)).astype(np.float64)


def voxel_costs(alpha: np.ndarray, profile: TraversabilityProfile) -> tuple[np.ndarray, np.ndarray]:
    """(expected cost, its standard deviation) of each voxel under its Dirichlet posterior."""
    return _cost_moments(_moments(np.asarray(alpha), profile))


def _cost_moments(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    total = moments[:, 0]
    mean = moments[:, 1] / total
    variance = np.maximum(moments[:, 2] / total - mean ** 2, 0.0) / (total + 1.0)
    return mean, np.sqrt(variance)


def column_costs(indices: np.ndarray, alpha: np.ndarray, resolution: float,
                 profile: TraversabilityProfile, prior: float = 0.0) -> ColumnCosts:
    """The cost of each column holding voxels with evidence (see the module's docstring);
    ``prior``: the map's prior concentration per class, which is not evidence."""
    indices = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    alpha = np.asarray(alpha)
    if not np.issubdtype(alpha.dtype, np.floating):
        alpha = alpha.astype(np.float64)
    moments = _moments(alpha, profile)
    evident = moments[:, 0] - prior * alpha.shape[1] >= profile.min_evidence
    indices, moments = indices[evident], moments[evident]
    if not len(indices):
        empty = np.zeros((0, 2), np.int64)
        return ColumnCosts(empty, np.zeros(0, np.int8), np.zeros(0, np.int64))
    mean, sigma = _cost_moments(moments)
    risk = np.clip(mean + profile.risk_sigma * sigma, 0.0, LETHAL)
    is_ground = moments[:, 3] / moments[:, 0] > GROUND_SHARE
    is_empty = moments[:, 4] / moments[:, 0] > 0.5
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
    np.maximum.at(ground, column[is_ground], z[is_ground])
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
    grid = np.full(tuple(shape), np.nan)
    grid[tuple((cells - low).T)] = estimate
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
    return grid[tuple((cells - low).T)]


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

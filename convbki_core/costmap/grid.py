"""The cost grid a planner reads (as nav_msgs/OccupancyGrid holds it) and its extent.

The column costs (``columns``) laid out as a 2D grid in global cells, the part of a grid a
rolling costmap asks for (``crop``, ``rolling_geometry``), and which of a window's columns
such a region needs read (``columns_to_read``: its own and the margin a hidden ground's
estimate depends on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.costmap.columns import NEIGHBOUR_PASSES, UNKNOWN, ColumnCosts


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

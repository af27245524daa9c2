"""The planner's costmap: ``semantic_map/costmap`` and ``~/get_costmap`` (nav_msgs).

The cost of each cell comes from ``convbki_core.costmap.columns`` (the expected class cost under each
voxel's posterior plus a risk margin, in the robot's height band). The rolling grid is a
square around the sensor, at most the local window's footprint, computed from the window's
dense arrays in place; the whole-map grid of ``~/get_costmap`` from a copy of every voxel.
"""

from __future__ import annotations

import numpy as np

from convbki_core.costmap.columns import UNKNOWN, column_costs
from convbki_core.costmap.grid import CostGrid, rasterise, rolling_geometry
from convbki_core.costmap.profile import ProfileError, load_profile
from convbki_core.costmap.window_pass import grid_of_window
from convbki_core.paths import traversability_profile
from convbki_ros.inputs.transforms import make_header, message_types
from convbki_ros.params import StartupError


def profile_of(node, class_names):
    """The ``costmap_profile`` parameter's profile; a bad one is a StartupError (exit 2)."""
    try:
        return load_profile(traversability_profile(node.param("costmap_profile")), tuple(class_names))
    except ProfileError as error:
        raise StartupError(f"parameter costmap_profile: {error}") from None


def rolling_grid(window, resolution: float, prior: float, profile, position: np.ndarray, size: float,
                 window_extent: float) -> CostGrid:
    """The rolling grid from the mapper's dense window (``RollingWindow``), read in place: call
    it under the map's lock. Equal to the grid of the same voxels saved (``column_costs``)."""
    origin, cells = rolling_geometry(position, resolution, size, window_extent)
    if window.origin is None:  # nothing mapped yet
        return CostGrid(origin, np.full((cells, cells), UNKNOWN, np.int8), float(resolution))
    return grid_of_window(window, resolution, profile, prior, (origin, (cells, cells)))


def whole_grid(indices: np.ndarray, alpha: np.ndarray, resolution: float, prior: float, profile) -> CostGrid:
    return rasterise(column_costs(indices, alpha, resolution, profile, prior), resolution)


def occupancy_grid(grid: CostGrid, stamp, frame_id: str):
    """nav_msgs/OccupancyGrid of ``grid``: row-major from the cell at the origin, +x along a row."""
    types = message_types()
    msg = types("nav_msgs/msg/OccupancyGrid")()
    msg.header = make_header(types, stamp, frame_id)
    height, width = grid.values.shape
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(grid.resolution)
    msg.info.width, msg.info.height = int(width), int(height)
    msg.info.origin.position.x, msg.info.origin.position.y = (float(v) for v in grid.origin_metres)
    msg.info.origin.orientation.w = 1.0
    msg.data = _int8_data(grid.values)
    return msg


def _int8_data(values: np.ndarray):
    """OccupancyGrid.data from int8 values without a Python list (rclpy takes an array.array)."""
    import array

    data = array.array("b")
    data.frombytes(np.ascontiguousarray(values, dtype=np.int8).tobytes())
    return data

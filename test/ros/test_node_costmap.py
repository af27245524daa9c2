"""The planner's costmap over DDS: semantic_map/costmap (rolling, latched) and ~/get_costmap
(the whole map) equal the grids computed offline from the map file the node saved."""

import numpy as np
from mapper_rig import BOUNDS, POSE, Rig

from convbki_core.costmap.columns import column_costs
from convbki_core.costmap.grid import rasterise
from convbki_core.io.labels import load_label_map
from convbki_core.io.map_file import read_map
from convbki_ros.outputs.costmap import profile_of, rolling_geometry, whole_grid


class Params:
    """What profile_of reads from a node."""

    def __init__(self, **values):
        self.values = values

    def param(self, name):
        return self.values[name]


def grid_values(msg) -> np.ndarray:
    return np.asarray(msg.data, np.int8).reshape(msg.info.height, msg.info.width)


def test_the_costmap_topic_and_service_equal_the_offline_grids(tmp_path):
    from nav_msgs.msg import OccupancyGrid
    from nav_msgs.srv import GetMap

    rig = Rig(tmp_path, "-p", "costmap_size:=20.0", diagnostics_period=0.05)
    grids = rig.probe.subscribe(OccupancyGrid, "/semantic_map/costmap", latched=True)
    profile = profile_of(Params(costmap_profile="car"), load_label_map("semantic_kitti").class_names)
    try:
        rig.integrate_good_cloud()
        rig.integrate_good_cloud()
        assert rig.call("save_map").success
        metadata, indices, alpha = read_map(rig.map_file)
        origin, cells = rolling_geometry(POSE[:3, 3], metadata["resolution"], 20.0, BOUNDS[3] - BOUNDS[0])
        rolling = rasterise(column_costs(indices, alpha, metadata["resolution"], profile, metadata["prior"]),
                            metadata["resolution"], origin, (cells, cells))

        def current(msg) -> bool:
            """The grid of the map as saved (an earlier one, e.g. of the empty map at start, is not)."""
            origin = [msg.info.origin.position.x, msg.info.origin.position.y]
            return np.allclose(origin, rolling.origin_metres) and np.array_equal(grid_values(msg), rolling.values)

        # The node publishes the costmap of each map version with its cycle: the last one sent
        # is the saved map's (nothing changed it after the save).
        assert rig.probe.spin_until(lambda: grids and current(grids[-1]), 30), \
            [(g.info.origin.position.x, g.info.origin.position.y) for g in grids]
        answer = rig.probe.call(GetMap, "/convbki_mapper/get_costmap")
    finally:
        output = rig.close()
    assert "Traceback" not in output, output

    msg = grids[-1]
    assert msg.header.frame_id == "map" and abs(msg.info.resolution - 0.2) < 1e-6 and msg.info.width == 100
    # The scene: a road, a wall 8 m ahead, a car. Two scans leave the road a little uncertain
    # (a few points of evidence a voxel: cost 3-6 with the margin), in the free group all the same
    # (<= 25, map_server's free threshold); the wall and the car lethal; the rest unknown.
    values = rolling.values
    assert ((values >= 0) & (values <= 25)).sum() > 1000 and (values == 100).sum() > 100
    assert (values == -1).sum() > 1000

    whole = whole_grid(indices, alpha, metadata["resolution"], metadata["prior"], profile)
    np.testing.assert_array_equal(grid_values(answer.map), whole.values)
    np.testing.assert_allclose([answer.map.info.origin.position.x, answer.map.info.origin.position.y],
                               whole.origin_metres)

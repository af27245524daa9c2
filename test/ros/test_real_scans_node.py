"""Real SemanticKITTI scans through the node, as a user runs it: ``label_noise`` makes the input
segmentation, ``kitti_to_bag`` the bag, the node (shipped parameters) maps it while
``play_bag`` replays it over DDS, and an outside client reads the map and the costmap
(skipped, with the reason, where the real scans are absent)."""

import numpy as np
import pytest
from helpers import real_sequence
from ros_helpers import Probe, domain_id, start, stop

from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.poses import pose_from_translation_quaternion, pose_to_translation_quaternion
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import config_dir
from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.tools.kitti_to_bag import main as kitti_to_bag

SEQUENCE = "05"


def input_grid(dataset, grid) -> np.ndarray:
    """The input segmentation's own car costmap on the cells of ``grid`` (an OccupancyGrid): its
    labels of every scan's points counted per voxel and costed without a margin, as
    ``evaluate --costmap-report`` scores it."""
    from convbki_core.costmap.columns import column_costs
    from convbki_core.costmap.grid import rasterise
    from convbki_core.costmap.profile import load_profile
    from convbki_core.geometry.grid import transform_points
    from convbki_core.measures.costmap_eval import GroundTruthVoxels, truth_profile
    from convbki_core.paths import traversability_profile

    counted = GroundTruthVoxels(dataset.label_map.num_classes, grid.info.resolution)
    for frame in dataset:
        counted.add(transform_points(frame.points, frame.pose), frame.input_labels)
    profile = truth_profile(load_profile(traversability_profile("car"), dataset.label_map.class_names))
    origin = np.array([grid.info.origin.position.x, grid.info.origin.position.y]) / grid.info.resolution
    columns = column_costs(*counted.items(), grid.info.resolution, profile)
    return rasterise(columns, grid.info.resolution, np.round(origin).astype(np.int64),
                     (grid.info.width, grid.info.height)).values


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    """The mapper node (shipped parameters), started before ``real_bag`` is made so that the two
    overlap: its domain and process (stopped by the test, which reads its output)."""
    real_sequence(SEQUENCE)  # skips here, before any process starts, where the real scans are absent
    domain = domain_id()
    process = start("convbki_ros.main", domain, "--ros-args", "--params-file", config_dir() / "mapper.yaml",
                    "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom", "-p", "device:=cpu",
                    "-p", "publish_period:=0.3", "-p", "map_period:=0.3",
                    "-p", f"map_file:={tmp_path_factory.mktemp('node') / 'map.npz'}")
    yield domain, process
    stop(process)


@pytest.fixture(scope="module")
def real_bag(real_noisy, tmp_path_factory):
    """Real sequence 05 with ``label_noise``'s input (seed 0, mIoU 0.55; the run's shared copy),
    and its bag."""
    data = real_noisy(SEQUENCE)
    out = tmp_path_factory.mktemp("real")
    assert kitti_to_bag(["--dataset", str(data), "--sequence", SEQUENCE, "--out", str(out / "bag")]) == 0
    return data, out / "bag"


def test_a_real_drive_through_the_node_gives_the_offline_map_and_a_free_road_under_the_ego_path(node, real_bag):
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2

    domain, process = node
    probe = Probe(domain)
    player = None
    try:
        maps = probe.subscribe(PointCloud2, "/semantic_map", latched=True)
        costmaps = probe.subscribe(OccupancyGrid, "/semantic_map/costmap", latched=True)
        player = start("convbki_ros.tools.play_bag", domain, real_bag[1], "--wait-for-node")
        # The offline map, made while the node maps the replay (the probe's latched readers keep
        # the node's latest map and costmap meanwhile).
        dataset = SemanticKittiSequence(real_bag[0], SEQUENCE)
        offline = ConvBKIMapper(MapperConfig.from_params_file(config_dir() / "mapper.yaml").replace(device="cpu"))
        for frame in dataset:  # at the pose the bag's odometry carries (a translation and a quaternion)
            offline.integrate(frame.points, frame.input_labels,
                              pose_from_translation_quaternion(*pose_to_translation_quaternion(frame.pose)))
        voxels = offline.voxels()
        shown = voxels.label != 0  # the published map leaves out voxels seen empty (class 0)
        assert shown.sum() > 100_000
        assert player.wait(timeout=120) == 0, stop(player)
        assert probe.spin_until(lambda: maps and maps[-1].width == shown.sum(), timeout=60), \
            f"map has {maps[-1].width if maps else 0} voxels, the offline map {shown.sum()}"
        # What an outside client receives is the offline map: every voxel, every label.
        decoded = decode_cloud(maps[-1], 20)
        got, want = decoded.points.astype(np.float32), voxels.centres[shown].astype(np.float32)
        got_order, want_order = np.lexsort(got.T), np.lexsort(want.T)
        np.testing.assert_array_equal(got[got_order], want[want_order])
        np.testing.assert_array_equal(decoded.labels[got_order], voxels.label[shown][want_order])

        # The car's costmap around the last scan: the road along the car's way is free. The ground
        # within about 3 m of the LiDAR is never seen (its lowest beam meets the road farther
        # out, the car hides the rest), so the cells read are those on the line of the drive,
        # 4 to 15 m ahead of the last scan and behind the first.
        assert probe.spin_until(lambda: costmaps and costmaps[-1].header.stamp.sec > 0, timeout=30)
        grid = costmaps[-1]
        values = np.asarray(grid.data, np.int8).reshape(grid.info.height, grid.info.width)
        first, last = dataset.poses[0][:3, 3], dataset.poses[-1][:3, 3]
        heading = (last - first) / np.linalg.norm(last - first)
        along = [last + heading * d for d in np.arange(4.0, 15.0, 0.2)] + \
                [first - heading * d for d in np.arange(4.0, 15.0, 0.2)]
        cells = {(int(np.floor((x - grid.info.origin.position.x) / grid.info.resolution)),
                  int(np.floor((y - grid.info.origin.position.y) / grid.info.resolution))) for x, y, _ in along}
        costs = np.array([values[row, column] for column, row in cells])
        # Where the input segmentation itself calls the road something else (a persistent
        # confusion of road with sidewalk), the map follows its input: the input's own grid (its
        # labels of every scan's points, counted per voxel) says how much of the way it leaves free.
        said = input_grid(dataset, grid)
        input_costs = np.array([said[row, column] for column, row in cells])
        # (The ground truth calls every one of these cells road.) No cell on the way is an
        # obstacle, and the map leaves as many free as its input does, less the kernel's spread
        # of the input's confusions by a cell.
        assert len(costs) >= 100 and (costs < 90).all(), (costs, input_costs)
        assert (costs == 0).mean() >= max(0.85, (input_costs == 0).mean() - 0.05), (costs, input_costs)
    finally:
        if player is not None:
            stop(player)  # a player still running when a check failed
        probe.close()
        output = stop(process)
    assert "Traceback" not in output and "[ERROR]" not in output, output

"""A robot's TF over DDS: a SLAM's map -> odom, odometry of base_link in odom, the LiDAR's mount
on /tf_static, and no base_to_sensor.

Two nodes map the same drive side by side: one takes its poses from the odometry and puts
them into ``map`` through TF, the other (pose_source tf) reads no odometry at all. Both maps
must equal the map built offline from the composed poses, across a jump of map -> odom (a
loop closure) half-way through the drive.
"""

import numpy as np
import pytest
from mapper_rig import (
    LABELS,
    POINTS,
    WAIT,
    Rig,
    close_together,
    cloud,
    expect_file_holds,
    node_default_mapper,
)
from test_node_frames import BOUNDS, MOUNT, assert_same_voxels, shown_voxels

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_ros.inputs.transforms import pose_to_odometry, pose_to_transform_stamped


def yawed(x: float, y: float, yaw: float) -> np.ndarray:
    return pose_from_translation_quaternion([x, y, 0.0], [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])


# base_link in odom: a drive with a turn.
BASE_IN_ODOM = [yawed(1.5 * i, 0.3 * i, 0.08 * i) for i in range(4)]
# The SLAM's correction: small, then after its loop closure a jump of 1.2 m and 0.1 rad.
MAP_FROM_ODOM = [yawed(0.2, -0.1, 0.02), yawed(0.2, -0.1, 0.02), yawed(1.4, 0.5, 0.12), yawed(1.4, 0.5, 0.12)]


def expected_map() -> ConvBKIMapper:
    """The clouds integrated offline at map <- odom x odom <- base_link x base_link <- lidar_top."""
    label_map = load_label_map("semantic_kitti")
    mapper = node_default_mapper(local_bounds=(BOUNDS[:3], BOUNDS[3:]))
    for correction, base in zip(MAP_FROM_ODOM, BASE_IN_ODOM, strict=True):
        mapper.integrate(POINTS, label_map.to_learning(LABELS), correction @ base @ MOUNT)
    return mapper


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The module's nodes, started side by side (each test takes its own): "by odometry" and
    "by tf" map the drive; "no transform" waits for a map -> odom that no one publishes."""
    folder = tmp_path_factory.mktemp("tf")
    params = ("-p", "map_frame:=map")
    nodes = {"by odometry": Rig(folder / "odometry", *params, diagnostics_period=0.05, wait=False),
             "by tf": Rig(folder / "tf", *params, "-p", "pose_source:=tf", odometry=False, diagnostics_period=0.05,
                          wait=False),
             "no transform": Rig(folder / "no_transform", *params, "-p", "transform_timeout:=0.3",
                                 diagnostics_period=0.05, wait=False)}
    yield nodes
    close_together(*nodes.values())


def test_a_robot_maps_in_map_through_tf_with_and_without_odometry(nodes):
    expected = expected_map()  # while the nodes start
    rigs = by_odometry, by_tf = nodes["by odometry"].wait_ready(), nodes["by tf"].wait_ready()
    try:
        for rig in rigs:
            rig.publish_tf(pose_to_transform_stamped(MOUNT, 0, "base_link", "lidar_top"), static=True)
        for correction, base in zip(MAP_FROM_ODOM, BASE_IN_ODOM, strict=True):
            stamp = by_odometry.next_stamp()
            # As a robot sends them: the SLAM's correction on /tf, the odometry both as a message
            # and on /tf (odom -> base_link), then the cloud in the LiDAR's frame.
            slam = pose_to_transform_stamped(correction, stamp, "map", "odom")
            by_odometry.publish_tf(slam)
            by_odometry.publish(pose_to_odometry(base, stamp, "odom", "base_link"))
            by_tf.publish_tf(slam, pose_to_transform_stamped(base, stamp, "odom", "base_link"))
            for rig in rigs:
                rig.publish(cloud(stamp, frame="lidar_top"))
        for rig in rigs:
            stats = rig.wait_stats(lambda s: s.integrated + s.dropped == len(BASE_IN_ODOM))
            assert stats.integrated == len(BASE_IN_ODOM), stats
            msg = rig.map_message(len(shown_voxels(expected)[0]))
            assert msg.header.frame_id == "map"
            assert_same_voxels(msg, expected)
            assert rig.call("save_map").success
            expect_file_holds(rig.map_file, expected)
        assert by_odometry.log.find(r"mapper ready.*poses from odometry, sensor mount from TF, map in 'map'")
        assert by_odometry.log.find(r"the odometry is in 'odom', the map in map_frame 'map'")
        assert by_tf.log.find(r"mapper ready.*poses from TF \('map' -> each cloud's frame\).* \+ TF")
    finally:
        outputs = close_together(*rigs)
    assert not any("Traceback" in output for output in outputs), outputs


def test_a_cloud_whose_transform_never_comes_is_dropped_and_said(nodes):
    """map_frame 'map', odometry in 'odom', no map -> odom on TF: each cloud waits
    transform_timeout (0.3 s), then is dropped with a warning naming the transform; the map stays empty."""
    rig = nodes["no transform"].wait_ready()
    try:
        stamp = rig.next_stamp()
        rig.publish(pose_to_odometry(BASE_IN_ODOM[0], stamp, "odom", "velo_link"), cloud(stamp))
        stats = rig.wait_stats(lambda s: s.dropped == 1)
        assert stats.integrated == 0 and stats.reasons == {"no transform": 1}, stats
        rig.wait_log(r"\[WARN\].*dropping cloud stamped 1001\.000 s in frame 'velo_link' after waiting "
                     r"transform_timeout = 0\.3 s \(no transform\): no transform from map_frame 'map' to the "
                     r"odometry's 'odom' \(frames 'map' and 'odom' are unknown\)", since=0)

        # transform_timeout 0 at run time: the next cloud waits (16 reports, 0.8 s, outlast the
        # 0.3 s before) until map -> odom comes, and is then mapped.
        assert rig.set_parameters(transform_timeout=0.0)[0].successful
        stamp = rig.next_stamp()
        rig.publish(pose_to_odometry(BASE_IN_ODOM[0], stamp, "odom", "velo_link"), cloud(stamp))
        rig.wait_stats(lambda s: s.scans_in == 2)
        seen = len(rig.diagnostics)
        assert rig.probe.spin_until(lambda: len(rig.diagnostics) >= seen + 16, WAIT)
        stats = rig.stats()
        assert (stats.integrated, stats.dropped) == (0, 1), stats
        rig.publish_tf(pose_to_transform_stamped(np.eye(4), 0, "map", "odom"), static=True)
        assert rig.wait_stats(lambda s: s.integrated == 1).dropped == 1
    finally:
        output = rig.close()
    assert "Traceback" not in output, output

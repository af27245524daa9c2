"""A robot's frames over DDS: odometry of base_link, a LiDAR on a mount, a namespaced node.

On a robot the odometry is the pose of ``base_link`` in ``odom``/``map`` and the LiDAR
publishes in its own frame. The node must map such clouds exactly as it maps clouds whose
odometry is the LiDAR's own pose, with the mount from ``base_to_sensor`` or from ``/tf_static``.
"""

import numpy as np
import pytest
from mapper_rig import (
    BOUNDS,
    LABELS,
    POINTS,
    Rig,
    close_together,
    cloud,
    expect_file_holds,
    node_default_mapper,
    odometry,
)

from convbki_core.geometry.poses import pose_from_translation_quaternion, pose_to_translation_quaternion
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_ros.inputs.cloud_decoding import decode_cloud

# The LiDAR 1.8 m above base_link, 0.4 m ahead, yawed by 0.2 rad and pitched a little.
MOUNT_TRANSLATION = [0.4, 0.0, 1.8]
MOUNT_QUATERNION = [0.0, 0.05, 0.1, 1.0] / np.linalg.norm([0.0, 0.05, 0.1, 1.0])
MOUNT = pose_from_translation_quaternion(MOUNT_TRANSLATION, MOUNT_QUATERNION)
BASE_POSES = [pose_from_translation_quaternion([1.0 + 2.0 * i, 0.5 * i, 0.0], [0.0, 0.0, np.sin(0.1 * i),
                                                                                  np.cos(0.1 * i)])
              for i in range(3)]


def expected_map() -> ConvBKIMapper:
    """The clouds integrated offline at the LiDAR's poses (base pose x mount), with free space
    as the node has it by default: its rays start at the LiDAR, so the mount must be right."""
    label_map = load_label_map("semantic_kitti")
    mapper = node_default_mapper(local_bounds=(BOUNDS[:3], BOUNDS[3:]))
    for base in BASE_POSES:
        mapper.integrate(POINTS, label_map.to_learning(LABELS), base @ MOUNT)
    return mapper


def drive(rig: Rig, child: str, poses: list[np.ndarray]) -> None:
    """Odometry of ``child`` at ``poses`` and the same cloud in frame lidar_top at each stamp."""
    before = rig.stats().integrated
    for pose in poses:
        stamp = rig.next_stamp()
        translation, quaternion = pose_to_translation_quaternion(pose)
        rig.publish(odometry(stamp, translation, quaternion, child=child), cloud(stamp, frame="lidar_top"))
    rig.wait_stats(lambda s: s.integrated == before + len(poses))


def shown_voxels(expected: ConvBKIMapper):
    """The voxels a map message holds: those not seen empty (class 0)."""
    voxels = expected.voxels()
    keep = voxels.label != 0
    return voxels.centres[keep], voxels.label[keep]


def assert_same_voxels(msg, expected: ConvBKIMapper) -> None:
    centres, labels = shown_voxels(expected)
    got = decode_cloud(msg, 20)
    order_got, order_want = np.lexsort(got.points.T), np.lexsort(centres.T)
    np.testing.assert_array_equal(got.points[order_got], centres[order_want])
    np.testing.assert_array_equal(got.labels[order_got], labels[order_want])


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The module's nodes, started side by side (each test takes its own): "on base" (namespaced
    /robot1, the mount from base_to_sensor), "on lidar" (map_frame the odometry's own) and "no
    mount" (the default parameters: no base_to_sensor)."""
    folder = tmp_path_factory.mktemp("frames")
    mount = [*MOUNT_TRANSLATION, *MOUNT_QUATERNION]
    nodes = {"on base": Rig(folder / "base", "-p", f"base_to_sensor:={[float(v) for v in mount]}",
                            namespace="/robot1", diagnostics_period=0.05, wait=False),
             "on lidar": Rig(folder / "lidar", "-p", "map_frame:=map", diagnostics_period=0.05, wait=False),
             "no mount": Rig(folder / "no_mount", diagnostics_period=0.05, wait=False)}
    yield nodes
    close_together(*nodes.values())


def test_a_lidar_on_a_mount_maps_like_odometry_of_the_lidar_itself(nodes):
    """Node A (namespaced /robot1): odometry of base_link, the mount from base_to_sensor.
    Node B: odometry of the LiDAR itself, map_frame the odometry's own (no TF needed). Both
    maps equal the offline map."""
    expected = expected_map()  # while the nodes start
    on_base, on_lidar = nodes["on base"].wait_ready(), nodes["on lidar"].wait_ready()
    try:
        drive(on_base, "base_link", BASE_POSES)
        drive(on_lidar, "lidar_top", [base @ MOUNT for base in BASE_POSES])
        for rig in (on_base, on_lidar):
            msg = rig.map_message(len(shown_voxels(expected)[0]))
            assert msg.header.frame_id == "map"  # the odometry's frame
            assert_same_voxels(msg, expected)
            assert rig.call("save_map").success
            expect_file_holds(rig.map_file, expected)
        assert on_base.log.find(r"mapper ready.*sensor mount from base_to_sensor")
        assert not on_lidar.log.find(r"\[WARN\]"), on_lidar.log.text()
        report = on_base.diagnostics[-1].status[0]
        assert report.name == "/robot1/convbki_mapper: mapping" and report.level == b"\x00", report
    finally:
        outputs = close_together(on_base, on_lidar)
    assert not any("Traceback" in output for output in outputs), outputs


def test_the_mount_from_tf_static_gives_the_same_map(nodes):
    """No base_to_sensor: the mount published once on /tf_static (transient local, before the
    first cloud) places the clouds as the parameter does."""
    from convbki_ros.inputs.transforms import pose_to_transform_stamped

    rig = nodes["no mount"].wait_ready()
    try:
        rig.publish_tf(pose_to_transform_stamped(MOUNT, 0, "base_link", "lidar_top"), static=True)
        assert rig.log.find("sensor mount from TF")
        drive(rig, "base_link", BASE_POSES)
        expected = expected_map()
        assert_same_voxels(rig.map_message(len(shown_voxels(expected)[0])), expected)
        assert rig.stats().dropped == 0
    finally:
        output = rig.close()
    assert "Traceback" not in output, output

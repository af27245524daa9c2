"""The mapper node's parameters as a user meets them: bad start-up input is one line and exit
code 2; unknown names and overrides of the kernel are said once; run-time changes take effect
and read-only parameters refuse to change. Real processes over DDS."""

import re

import numpy as np
import pytest
import torch
from mapper_rig import (
    BOUNDS,
    LABELS,
    POINTS,
    QUATERNION,
    SECOND,
    TRANSLATION,
    WAIT,
    Rig,
    close_together,
    node_default_mapper,
)
from ros_helpers import IMPORT_LOG, domain_id, split_import_log, start

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_core.io.labels import load_label_map
from convbki_ros.inputs.cloud_decoding import FLOAT32, UINT32, decode_cloud

MIXED_LIST = "/**:\n  ros__parameters:\n    local_bounds: [1.0, 2, 3.0, 4.0, 5.0, 6.0]\n"
BROKEN_YAML = "/**:\n  ros__parameters:\n    resolution: [0.2\n"

# (arguments after --ros-args, or a params file's text; the one line the user must get)
BAD_STARTS = {
    "type": (["-p", "resolution:=abc"], r"parameter resolution: 'abc' is a string, expected a number"),
    "range": (["-p", "resolution:=50.0"], r"parameter resolution: 50.0 is out of range 0.01 .. 10"),
    "even filter": (["-p", "filter_size:=4"], r"parameter filter_size: 4 is out of range 1 .. 31 \(odd values only\)"),
    "choice": (["-p", "label_space:=ids"], r"parameter label_space: 'ids' is not one of raw, learning"),
    "bounds": (["-p", "local_bounds:=[1.0, 2.0]"], r"local_bounds needs 6 numbers \(min xyz, max xyz\), got 2"),
    "mount": (["-p", "base_to_sensor:=[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0]"],
              r"parameter base_to_sensor: orientation quaternion \(0, 0, 0, 2\) has norm 2, not 1"),
    "kernel": (["-p", "kernel_file:=/nowhere/kernel.yaml"], r"/nowhere/kernel.yaml"),
    "classes": (["-p", "num_classes:=7"], r"kernel has 20 classes, num_classes is 7"),
    "missing params file": (["--params-file", "/nowhere/params.yaml"],
                            r"params file /nowhere/params.yaml: No such file or directory"),
    "broken params file": (BROKEN_YAML, r"params file .*broken_params_file.yaml is not valid YAML"),
    "mixed list": (MIXED_LIST, r"ROS 2 could not start: .*Couldn't parse params file"),
    "costmap profile": (["-p", "costmap_profile:=/nowhere/robot.yaml"],
                        r"parameter costmap_profile: /nowhere/robot.yaml: cannot read the traversability profile"),
    "tf without map_frame": (["-p", "pose_source:=tf"], r"pose_source tf needs map_frame"),
    "pose source": (["-p", "pose_source:=gps"], r"parameter pose_source: 'gps' is not one of odometry, tf"),
    "log folder": (["-p", "scan_log_folder:=/proc/no_log_here"], r"scan_log_folder /proc/no_log_here cannot be used"),
    "min move": (["-p", "correction_min_move:=-0.5"],
                 r"parameter correction_min_move: -0.5 m: -1.0 \(half a voxel\) or a distance of at least 0"),
}
if not torch.cuda.is_available():
    BAD_STARTS["no cuda"] = (["-p", "device:=cuda"], r"device 'cuda' requested, but .* no CUDA")


def test_every_bad_start_is_one_line_and_exit_2(tmp_path):
    processes = {}
    for case, (arguments, _) in BAD_STARTS.items():  # all at once: each is a process of its own
        if isinstance(arguments, str):
            params = tmp_path / f"{case.replace(' ', '_')}.yaml"
            params.write_text(arguments)
            arguments = ["--params-file", str(params)]
        # Python's import log (on stderr, before the error line): which modules the process loaded.
        processes[case] = start("convbki_ros.main", domain_id(), "--ros-args", "-p", "device:=cpu", *arguments,
                                env=IMPORT_LOG)
    for case, process in processes.items():
        output, imported = split_import_log(process.communicate(timeout=120)[0])
        lines = output.strip().splitlines()
        assert process.returncode == 2, (case, lines)
        assert len(lines) == 1 and re.fullmatch(r"mapper: error: .*" + BAD_STARTS[case][1] + ".*", lines[0]), \
            (case, lines)
        # Every parameter is checked before the mapper (torch, compiled kernels) is loaded, so the
        # error comes at once; only the CUDA check needs torch itself.
        assert "convbki_core.mapper" in imported if case == "no cuda" else "torch" not in imported, (case, imported)


NAMESPACES = ["", "/robot1"]


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The nodes of the tests below, started side by side (each test takes its own): "overrides"
    (a params file with a misspelt name, an override of the kernel's filter size) and one in each
    of NAMESPACES."""
    folder = tmp_path_factory.mktemp("overrides")
    params = folder / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    resolutoin: 0.3\n    map_period: 1000.0\n"
                      "    publish_period: 1000.0\n")
    # map_period, publish_period and stats_period so long that, unless the change re-creates their
    # timers, the map and its updates would not be published nor the counters logged while the test runs.
    nodes = {"overrides": Rig(folder, "--params-file", str(params), "-p", "filter_size:=3",
                              "-p", "stats_period:=1000.0", diagnostics_period=0.05, wait=False),
             **{namespace: Rig(tmp_path_factory.mktemp("namespaced"), namespace=namespace, diagnostics_period=0.05,
                               wait=False) for namespace in NAMESPACES}}
    yield nodes
    close_together(*nodes.values())


def test_unknown_names_and_kernel_overrides_are_said_and_run_time_changes_take_effect(nodes):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    rig = nodes["overrides"].wait_ready()
    try:
        from sensor_msgs.msg import PointCloud2

        updates = rig.probe.subscribe(PointCloud2, "/semantic_map/updates")
        assert rig.log.find(r"\[WARN\].*unknown parameters ignored \(misspelt\?\): resolutoin;")
        assert rig.log.find(r"\[WARN\].*set explicitly, overriding the kernel file .*: filter_size 3 \(kernel: 5\)")
        assert rig.log.find(r"mapper ready: compound kernel, 0.2 m voxels, f = 3,")
        rig.integrate_good_cloud()
        assert not rig.maps and not updates and not rig.log.find(r"scans in \d+, integrated")

        client = rig.probe.node.create_client(SetParameters, "/convbki_mapper/set_parameters")

        def set_parameter(name: str, value: float):
            request = SetParameters.Request(parameters=[Parameter(name=name, value=ParameterValue(
                type=ParameterType.PARAMETER_DOUBLE, double_value=value))])
            assert rig.probe.spin_until(client.service_is_ready, WAIT)
            future = client.call_async(request)
            assert rig.probe.spin_until(future.done, WAIT)
            return future.result().results[0]

        refused = set_parameter("resolution", 0.4)
        assert not refused.successful and "read-only" in refused.reason
        refused = set_parameter("publish_period", 0.001)
        assert not refused.successful and "out of range" in refused.reason
        # An integer for a number parameter, as `ros2 param set ... publish_period 2` sends it.
        assert rig.set_parameters(publish_period=2)[0].successful
        assert rig.parameter("publish_period") == 2.0 and isinstance(rig.parameter("publish_period"), float)
        assert rig.set_parameters(publish_period=0.2)[0].successful
        assert rig.probe.spin_until(lambda: bool(updates), WAIT), "no updates after publish_period became 0.2 s"
        assert set_parameter("map_period", 0.2).successful
        assert rig.probe.spin_until(lambda: bool(rig.maps), WAIT), "no map after map_period became 0.2 s"
        assert set_parameter("stats_period", 0.2).successful
        assert rig.probe.spin_until(lambda: rig.log.find(r"scans in 1, integrated 1"), WAIT)
    finally:
        output = rig.close()
    assert "Traceback" not in output, output


@pytest.mark.parametrize("namespace", NAMESPACES)
def test_output_topics_are_relative_to_the_namespace(namespace, nodes):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    rig = nodes[namespace].wait_ready()
    try:
        # semantic_map/local is volatile: subscribed before the scans, so the node sends it after them.
        local = []
        subscription = rig.probe.node.create_subscription(
            PointCloud2, f"{namespace}/semantic_map/local", local.append,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        assert rig.probe.spin_until(lambda: subscription.get_publisher_count() > 0, WAIT)
        # A second scan 15 m on moves the window: part of the first scan's voxels leave it.
        moved = TRANSLATION + [15.0, 0.0, 0.0]
        rig.integrate_good_cloud()
        rig.integrate_good_cloud(translation=moved)
        wanted = {f"{namespace}/{topic}" for topic in ("semantic_map", "semantic_map/variance", "semantic_map/local")}
        wanted.add("/diagnostics")

        def names() -> set[str]:
            return {name for name, _ in rig.probe.node.get_topic_names_and_types()}

        assert rig.probe.spin_until(lambda: wanted <= names(), WAIT), sorted(names())
        assert rig.map_message(rig.shown_voxels()).width > 0

        # The local window after the second scan (stamped with it) holds what the offline mapper's
        # window holds after the same scans: the voxels around the sensor, with their labels.
        def stamp(msg) -> int:
            return msg.header.stamp.sec * SECOND + msg.header.stamp.nanosec

        assert rig.probe.spin_until(lambda: local and stamp(local[-1]) == rig.stamp, WAIT), \
            [stamp(msg) for msg in local]
        window = local[-1]
        assert window.header.frame_id == "map" and window.height == 1
        assert {f.name: f.datatype for f in window.fields} == {
            "x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "rgb": FLOAT32, "label": UINT32, "variance": FLOAT32,
            "confidence": FLOAT32}
        decoded = decode_cloud(window, 20)
        expected = node_default_mapper()
        label_map = load_label_map("semantic_kitti")
        for translation in (TRANSLATION, moved):
            expected.integrate(POINTS, label_map.to_learning(LABELS),
                               pose_from_translation_quaternion(translation, QUATERNION))
        voxels, everything = expected.local_voxels(), expected.voxels()
        shown = voxels.label != 0
        assert 0 < shown.sum() < (everything.label != 0).sum()  # the window is not the whole map
        got = np.lexsort(decoded.points.T)
        want = np.lexsort(voxels.centres[shown].T)
        np.testing.assert_array_equal(decoded.points[got], voxels.centres[shown][want])
        np.testing.assert_array_equal(decoded.labels[got], voxels.label[shown][want])
        low, high = moved + BOUNDS[:3], moved + BOUNDS[3:]
        assert (decoded.points >= low - 0.2).all() and (decoded.points <= high + 0.2).all()
    finally:
        output = rig.close()
    assert "Traceback" not in output, output

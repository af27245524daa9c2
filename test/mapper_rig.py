"""A mapper node under test: a small scene, its inputs, and a rig that runs the node in its own
process and talks to it over DDS (publishes clouds and odometry, reads /semantic_map and
/diagnostics, calls its services)."""

import os
import re
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ros_helpers import NodeLog, Probe, domain_id, start

from convbki_core.config import MapperConfig
from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import config_dir
from convbki_ros.inputs.transforms import pose_to_odometry
from convbki_ros.outputs.cloud_encoding import encode_cloud

BOUNDS = [-20.0, -12.0, -3.0, 20.0, 12.0, 4.0]
FRAME = "velo_link"
SECOND = 1_000_000_000
START = 1_000 * SECOND  # stamp of the first input (ns); not 0, so that time can go back
TRANSLATION = np.array([1.0, 2.0, 0.5])
QUATERNION = np.array([0.0, 0.0, np.sin(0.15), np.cos(0.15)])  # yaw 0.3 rad: not the identity
POSE = pose_from_translation_quaternion(TRANSLATION, QUATERNION)
WAIT = 30.0  # seconds any one thing may take on a loaded CI machine before the test gives up
def good_points() -> tuple[np.ndarray, np.ndarray]:
    """A small scene in the sensor frame: road (raw 40) on the ground, a building wall (50),
    a car (10); float32 points (m) and uint32 raw labels."""
    grid = np.stack(np.meshgrid(np.arange(-10.0, 10.0, 0.4), np.arange(-6.0, 6.0, 0.4)), -1).reshape(-1, 2)
    ground = np.column_stack([grid, np.full(len(grid), -1.6)])
    wall_grid = np.stack(np.meshgrid(np.arange(-6.0, 6.0, 0.3), np.arange(-1.5, 2.0, 0.3)), -1).reshape(-1, 2)
    wall = np.column_stack([np.full(len(wall_grid), 8.0), wall_grid])
    car = np.random.default_rng(5).uniform([3.0, -3.0, -1.5], [7.0, -1.4, -0.2], (400, 3))
    points = np.concatenate([ground, wall, car]).astype(np.float32)
    labels = np.concatenate([np.full(len(ground), 40), np.full(len(wall), 50), np.full(len(car), 10)])
    return points, labels.astype(np.uint32)


POINTS, LABELS = good_points()


def fields(points=POINTS, labels=LABELS, **extra) -> dict:
    return {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "label": labels, **extra}


def cloud(stamp: int, frame: str = FRAME, **columns):
    return encode_cloud(stamp, frame, columns or fields())


def odometry(stamp: int, translation=TRANSLATION, quaternion=QUATERNION, child: str = FRAME):
    msg = pose_to_odometry(np.eye(4), stamp, "map", child)
    position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
    position.x, position.y, position.z = (float(v) for v in translation)
    orientation.x, orientation.y, orientation.z, orientation.w = (float(v) for v in quaternion)
    return msg


def node_default_mapper(**options) -> ConvBKIMapper:
    """The mapper object a node started with the shipped parameters file builds over BOUNDS
    (free space, clamping and the movers' rules as the file says); ``options`` override."""
    config = MapperConfig.from_params_file(config_dir() / "mapper.yaml")
    return ConvBKIMapper(config.replace(**{"local_bounds": (BOUNDS[:3], BOUNDS[3:]), "device": "cpu", **options}))


def offline_map(scans: int, translation=TRANSLATION) -> ConvBKIMapper:
    """The good cloud integrated ``scans`` times at POSE (moved to ``translation``) by the mapper
    object the node uses."""
    label_map = load_label_map("semantic_kitti")
    mapper = node_default_mapper()
    pose = pose_from_translation_quaternion(np.asarray(translation, np.float64), QUATERNION)
    for _ in range(scans):
        mapper.integrate(POINTS, label_map.to_learning(LABELS), pose)
    return mapper


@dataclass(frozen=True)
class Stats:
    """The node's counters, as one /diagnostics report gives them."""

    scans_in: int
    integrated: int
    dropped: int
    reasons: dict
    odometry_in: int
    odometry_rejected: int
    voxels: int
    map_version: int
    maps_published: int
    level: int
    message: str
    last_save: str
    publishers: dict  # per input: publishers matched by the node's reader

    @classmethod
    def parse(cls, array) -> "Stats":
        status = array.status[0]
        values = {item.key: item.value for item in status.values}
        reasons = {key.removeprefix("dropped."): int(value) for key, value in values.items()
                   if key.startswith("dropped.")}
        return cls(int(values["scans_in"]), int(values["integrated"]), int(values["dropped"]), reasons,
                   int(values["odometry_in"]), int(values["odometry_rejected"]), int(values["map_voxels"]),
                   int(values["map_version"]), int(values["maps_published"]), status.level[0], status.message,
                   values.get("last_save", ""),
                   {key.removeprefix("publishers."): int(value) for key, value in values.items()
                    if key.startswith("publishers.")})


class Rig:
    """A running mapper node, a probe that publishes its inputs and reads its map, and its log."""

    def __init__(self, folder: Path, *parameters: str, prefix: tuple[str, ...] = (), namespace: str = "",
                 watch_map: bool = True, map_file: Path | None = None, odometry: bool = True,
                 diagnostics_period: float = 0.2, wait: bool = True):
        """``namespace``: run the node in it ("/robot1"); its topics and services move there.
        ``watch_map``: subscribe to ``semantic_map`` (into ``maps``); ``map_file``: the node's map file
        (default ``folder/maps/map.npz``); ``odometry``: whether the node reads odometry (not with
        pose_source tf). ``diagnostics_period``: the node's /diagnostics period, which paces every
        ``stats`` (0.05 s: a test waits a quarter as long for each counter it reads; a test that
        counts reports as time keeps 0.2 s). ``wait``: False returns once the node is started, to
        start several at once (a node's start leaves a core idle); ``wait_ready`` then waits."""
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.folder = folder
        self.namespace = namespace
        self.map_file = map_file or folder / "maps" / "map.npz"
        if map_file is None:
            self.map_file.parent.mkdir(parents=True, exist_ok=True)
        self.domain = domain = domain_id()
        remap = ("-r", f"__ns:={namespace}") if namespace else ()
        # The node writes only inside map_folder: the rig's folder holds the maps folder and the PLY.
        self.map_folder = Path(os.path.commonpath([self.map_file.parent, folder]))
        self.process = start("convbki_ros.main", domain, "--ros-args", *remap, "-p", f"local_bounds:={BOUNDS}",
                             "-p", "device:=cpu", "-p", "publish_period:=0.2", "-p", "map_period:=0.2",
                             "-p", f"diagnostics_period:={diagnostics_period}",
                             "-p", "pose_wait_timeout:=1.5", "-p", f"map_file:={self.map_file}",
                             "-p", f"ply_file:={folder / 'shown.ply'}", "-p", f"map_folder:={self.map_folder}",
                             *parameters,
                             prefix=prefix)
        self.log = NodeLog(self.process)
        self.probe = Probe(domain)
        self.maps = self.probe.subscribe(PointCloud2, f"{namespace}/semantic_map", latched=True) if watch_map else []
        self.diagnostics = self.probe.subscribe(DiagnosticArray, "/diagnostics")
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.cloud_publisher = self.probe.node.create_publisher(PointCloud2, f"{namespace}/cloud_in", qos)
        self.odometry_publisher = self.probe.node.create_publisher(Odometry, f"{namespace}/odom", qos)
        self.stamp = START
        self._tf_publishers: dict[str, object] = {}
        self._reads_odometry = odometry
        self._closed = False
        if wait:
            try:
                self.wait_ready()
            except BaseException:
                self.close()  # no node left running when it never became ready
                raise

    def wait_ready(self) -> "Rig":
        """Wait until the node is ready and its inputs are matched (done by the constructor
        unless ``wait=False``)."""
        connected = self.probe.spin_until(lambda: self.cloud_publisher.get_subscription_count()
                                          and (self.odometry_publisher.get_subscription_count()
                                               or not self._reads_odometry)
                                          and self.log.find("mapper ready"), timeout=60)
        assert connected, self.log.text()
        return self

    # -- inputs --------------------------------------------------------------------------
    def next_stamp(self, step: float = 1.0) -> int:
        self.stamp += round(step * SECOND)
        return self.stamp

    def publish(self, *messages) -> None:
        for msg in messages:
            (self.cloud_publisher if hasattr(msg, "point_step") else self.odometry_publisher).publish(msg)

    def publish_tf(self, *transforms, static: bool = False) -> None:
        """geometry_msgs/TransformStamped on /tf (or /tf_static, transient local as tf2 sends it),
        once the node subscribes."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from tf2_msgs.msg import TFMessage

        topic = "/tf_static" if static else "/tf"
        if topic not in self._tf_publishers:
            durability = DurabilityPolicy.TRANSIENT_LOCAL if static else DurabilityPolicy.VOLATILE
            publisher = self.probe.node.create_publisher(
                TFMessage, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=durability))
            assert self.probe.spin_until(lambda: publisher.get_subscription_count() > 0, WAIT), f"no one on {topic}"
            self._tf_publishers[topic] = publisher
        self._tf_publishers[topic].publish(TFMessage(transforms=list(transforms)))

    def integrate_good_cloud(self, translation=TRANSLATION) -> "Stats":
        """Odometry and the good cloud at a new stamp; waits until the node integrated it."""
        before = self.stats()
        stamp = self.next_stamp()
        self.publish(odometry(stamp, translation), cloud(stamp))
        return self.wait_stats(lambda s: s.integrated == before.integrated + 1)

    # -- observations --------------------------------------------------------------------
    def wait_log(self, pattern: str, since: int, count: int = 1) -> list[re.Match]:
        """Spin the probe (so maps keep arriving) until ``pattern`` shows up ``count`` times."""
        assert self.probe.spin_until(lambda: len(self.log.find(pattern, since)) >= count, WAIT), \
            f"no {pattern!r} in the node's output:\n{self.log.text(since)}"
        return self.log.find(pattern, since)

    def stats(self) -> Stats:
        """The node's counters as of now: the first /diagnostics report received after this call."""
        seen = len(self.diagnostics)
        assert self.probe.spin_until(lambda: len(self.diagnostics) > seen, WAIT), "no /diagnostics report"
        return Stats.parse(self.diagnostics[seen])

    def wait_stats(self, done) -> Stats:
        found: list[Stats] = []

        def check() -> bool:
            found.append(self.stats())
            return done(found[-1])

        assert self.probe.spin_until(check, WAIT), f"counters never reached the expected state: {found[-1]}"
        return found[-1]

    def shown_voxels(self) -> int:
        """How many voxels the node's map shows now (not emptied by the rays): the count of its
        ``export_ply``, which writes the shown voxels (to ``ply_file``, outside the maps folder)."""
        exported = self.call("export_ply")
        found = re.fullmatch(r"wrote (\d+) voxels to .*", exported.message)
        assert exported.success and found, exported.message
        return int(found.group(1))

    def map_message(self, voxels: int):
        """The latest /semantic_map once it holds ``voxels`` voxels."""
        assert self.probe.spin_until(lambda: self.maps and self.maps[-1].width == voxels, WAIT), \
            f"/semantic_map has {self.maps[-1].width if self.maps else None} voxels, expected {voxels}"
        return self.maps[-1]

    def set_parameters(self, **values) -> list:
        """Set the node's parameters (types as given: an int is sent as an INTEGER); the results."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        client = self.probe.node.create_client(SetParameters, f"{self.namespace}/convbki_mapper/set_parameters")
        assert self.probe.spin_until(client.service_is_ready, WAIT)
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()
                                                    for name, value in values.items()])
        future = client.call_async(request)
        assert self.probe.spin_until(future.done, WAIT)
        return future.result().results

    def parameter(self, name: str):
        """The node's value of parameter ``name``, as rclpy reads it."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        client = self.probe.node.create_client(GetParameters, f"{self.namespace}/convbki_mapper/get_parameters")
        assert self.probe.spin_until(client.service_is_ready, WAIT)
        future = client.call_async(GetParameters.Request(names=[name]))
        assert self.probe.spin_until(future.done, WAIT)
        return parameter_value_to_python(future.result().values[0])

    def call(self, service: str):
        """Call the node's Trigger service ``service`` ("save_map", "reset", "export_ply")."""
        from std_srvs.srv import Trigger

        return self.probe.call(Trigger, f"{self.namespace}/convbki_mapper/{service}")

    def close(self) -> str:
        """Stop the node (Ctrl-C, unless it has ended) and the probe; the node's whole output.
        Closing again only returns the output."""
        if not self._closed:
            self._closed = True
            self.probe.close()
        return self.log.close()


def close_together(*rigs: Rig) -> list[str]:
    """Close ``rigs``, their nodes stopping side by side (Ctrl-C to each first); their outputs."""
    import contextlib
    import subprocess

    for rig in rigs:
        if rig.process.poll() is None:
            rig.process.send_signal(signal.SIGINT)
    for rig in rigs:  # ended before ``close``, which would send a second Ctrl-C to a node still stopping
        with contextlib.suppress(subprocess.TimeoutExpired):  # ``close`` then kills it
            rig.process.wait(timeout=10)
    return [rig.close() for rig in rigs]


def expect_file_holds(path: Path, expected: ConvBKIMapper) -> None:
    reloaded = offline_map(0)
    reloaded.load(path)
    indices, alpha = reloaded.items()
    want_indices, want_alpha = expected.items()
    order, want_order = np.lexsort(indices.T), np.lexsort(want_indices.T)
    np.testing.assert_array_equal(indices[order], want_indices[want_order])
    np.testing.assert_allclose(alpha[order], want_alpha[want_order], rtol=1e-6)

"""``mapper``: the ConvBKI semantic mapping node (``convbki_mapper``).

Run with ``ros2 run convbki_ros mapper --ros-args --params-file config/mapper.yaml``
or ``python -m convbki_ros.mapper --ros-args ...``.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import textwrap
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from convbki_core.kernels import KernelFileError, load_kernel_file
from convbki_core.labels import load_label_map
from convbki_core.mapfile import MapFileError
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_core.ply import write_voxels_ply
from convbki_ros.dds import publish_asynchronously, use_large_data_profile
from convbki_ros.pointcloud import CloudError, decode_cloud, encode_cloud, encode_map_cloud, variance_cloud_fields
from convbki_ros.pose_buffer import OdometryBuffer, PoseStatus, pose_problem
from convbki_ros.ros_args import strip_ros_args
from convbki_ros.transforms import pose_from_translation_quaternion, seconds_to_ns, stamp_to_ns

PROG = "mapper"
NODE_NAME = "convbki_mapper"

# (name, default, meaning and unit): the node's parameters, as in config/mapper.yaml.
PARAMETERS: tuple[tuple[str, object, str], ...] = (
    ("kernel_file", "",
     "kernel file (YAML); \"\" = the shipped compound kernel "
     "(share/convbki_ros/config/kernels/semantic_kitti_compound.yaml)"),
    ("num_classes", 20, "number of semantic classes C, class 0 = unlabeled; count"),
    ("resolution", 0.2, "voxel edge length; metres"),
    ("filter_size", 5, "convolution filter edge f (odd); voxels"),
    ("local_bounds", [-40.0, -40.0, -2.6, 40.0, 40.0, 2.6],
     "local map window around the sensor, [min_x, min_y, min_z, max_x, max_y, max_z]; metres"),
    ("prior", 0.001, "Dirichlet prior concentration of every class in every voxel; unitless"),
    ("label_space", "raw",
     "meaning of the input `label` field: raw (SemanticKITTI raw ids) or learning (0..num_classes-1)"),
    ("map_frame", "map", "frame id of the published map"),
    ("max_variance", 0.0,
     "leave out voxels whose variance of the expected class exceeds this; unitless; 0.0 = no filter"),
    ("publish_period", 1.0, "period of the /semantic_map publisher; seconds"),
    ("device", "auto", "torch device: auto (CUDA when present, else CPU), cpu, cuda[:N]"),
    ("input_qos", "reliable",
     "QoS of cloud_in and odom: reliable (bag replay) or sensor_data (live, best effort)"),
    ("map_file", "", "map file loaded at start when present, written by ~/save_map; \"\" = none; path"),
    ("autosave_period", 0.0, "save the map to map_file every this many seconds; 0.0 = never"),
    ("save_on_shutdown", True, "save the map to map_file when the node stops (SIGINT/SIGTERM); bool"),
    ("ply_file", "", "file written by ~/export_ply; \"\" = map_file with the suffix .ply, else convbki_map.ply"),
    ("publish_local", True, "publish /semantic_map/local (the window around the sensor) after each update; bool"),
    ("cloud_queue_size", 20, "clouds waiting to be integrated (2 s at 10 Hz); when full the oldest is dropped; count"),
    ("pose_wait_timeout", 2.0, "how long a cloud waits for odometry covering its stamp before it is dropped; "
     "seconds"),
    ("stats_period", 10.0, "period of the counters line in the log (scans in, integrated, dropped); seconds"),
    ("max_points_per_cloud", 2_000_000,
     "clouds with more points (width * height) are dropped on arrival with a warning, before any decoding, "
     "so that a runaway source cannot exhaust memory; count; 0 = no limit"),
    ("max_pose_jump", 10.0,
     "two consecutive odometry poses further apart than this are a jump: warned, and clouds stamped between "
     "them are dropped rather than placed half way; metres; 0.0 = no check"),
    ("reset_on_pose_jump", False,
     "on a pose jump, also clear the map and the odometry before the jump (a new map starts there); bool"),
    ("stamp_backwards_tolerance", 1.0,
     "odometry stamped more than this before the newest odometry means time went backwards (a restarted "
     "bag): the odometry history and the waiting clouds are dropped; seconds"),
    ("reset_on_stamp_backwards", False,
     "when time goes backwards, also clear the map; false keeps it (a replayed bag adds to it); bool"),
    ("odometry_timeout", 5.0,
     "while clouds arrive but no usable odometry has for this long, warn every this many seconds; seconds"),
    ("refuse_bad_map_file", False,
     "exit (code 2) when map_file exists but cannot be loaded, instead of starting with an empty map; bool"),
)


def _epilog() -> str:
    lines = [
        f"ROS 2 node {NODE_NAME}.",
        "",
        "topics:",
        "  subscribes cloud_in (sensor_msgs/PointCloud2: x, y, z and label or prob_0..prob_{C-1})",
        "             odom (nav_msgs/Odometry: pose of the cloud's frame)",
        "  publishes  /semantic_map (PointCloud2: x, y, z, rgb, label, variance, confidence;"
        " latched)",
        "             /semantic_map/variance (PointCloud2: x, y, z, intensity = variance)",
        "             /semantic_map/local (PointCloud2: the local window after each update)",
        "services: ~/save_map (Trigger), ~/reset, ~/export_ply (Trigger)",
        "",
        "parameters (name (default): meaning; unit):",
    ]
    for name, default, meaning in PARAMETERS:
        shown = '""' if default == "" else default
        lines.append(f"  {name} ({shown})")
        lines += textwrap.wrap(meaning, 86, initial_indent=" " * 6, subsequent_indent=" " * 6)
    lines += [
        "",
        "parameters are ROS parameters, not flags; pass them after --ros-args:",
        f"  ros2 run convbki_ros {PROG} --ros-args --params-file "
        "$(ros2 pkg prefix convbki_ros)/share/convbki_ros/config/mapper.yaml",
        f"  ros2 run convbki_ros {PROG} --ros-args -p resolution:=0.1 -p device:=cpu",
        "  remap topics with --ros-args -r cloud_in:=/kitti/velo/pointcloud -r odom:=/kitti/odom",
    ]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser; ROS arguments are removed before it runs."""
    return argparse.ArgumentParser(
        prog=PROG,
        description="ConvBKI online 3D semantic mapping node: integrates labelled LiDAR "
        "clouds at their odometry poses into a voxel map and publishes it.",
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        usage=f"{PROG} [-h] [--ros-args ROS_ARGS ...]",
    )


# ----------------------------------------------------------------------------------- the node

READ_WRITE = {"max_variance", "publish_period", "stats_period"}  # the rest are fixed at start


def problem_key(message: str) -> str:
    """A throttling key for a problem described in words: the message with its numbers blanked,
    so "data holds 10 bytes" and "data holds 12 bytes" are one problem, while a missing field and a
    wrong datatype are two (each gets its own warning)."""
    return re.sub(r"[-+]?\d[\d.eE+-]*", "#", message)


class WarningThrottle:
    """One warning per problem per ``period`` seconds; counts what it held back."""

    def __init__(self, logger, period: float = 5.0):
        self.logger = logger
        self.period = period
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warn(self, key: str, message: str, period: float | None = None) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < (self.period if period is None else period):
            self._held[key] = self._held.get(key, 0) + 1
            return
        held = self._held.pop(key, 0)
        self._last[key] = now
        self.logger.warning(message + (f" ({held} more like this since the last warning)" if held else ""))


@dataclass
class PendingCloud:
    """A received cloud on its way to the map."""

    msg: object
    received: float  # time.monotonic() at reception
    generation: int = 0  # the map generation it was received in; a reset makes it stale


@dataclass
class Counters:
    """What happened to the scans; logged every ``stats_period`` seconds."""

    scans_in: int = 0
    integrated: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    odometry_in: int = 0
    odometry_rejected: int = 0
    last_update_ms: float = 0.0
    last_publish_ms: float = 0.0

    def drop(self, reason: str, count: int = 1) -> None:
        if count:
            self.dropped[reason] = self.dropped.get(reason, 0) + count

    def line(self, queue_length: int, voxels: int) -> str:
        dropped = sum(self.dropped.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.dropped.items()))
        return (f"scans in {self.scans_in}, integrated {self.integrated}, dropped {dropped}"
                f"{f' ({reasons})' if reasons else ''}, odometry in {self.odometry_in} "
                f"(rejected {self.odometry_rejected}), queue {queue_length}, map voxels {voxels}, "
                f"last update {self.last_update_ms:.0f} ms, last map publish {self.last_publish_ms:.0f} ms")


def _import_ros():
    """rclpy and the message packages, imported on first use so that --help works without ROS."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    return rclpy, Node, PointCloud2, Odometry, Trigger


def make_node_class():
    """The node class, built after rclpy is imported."""
    _, Node, PointCloud2, Odometry, Trigger = _import_ros()
    from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
    from rclpy.clock import Clock, ClockType
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    class MapperNode(Node):
        """Subscribes labelled clouds and odometry, integrates them with ConvBKI, publishes the map."""

        def __init__(self, **node_options):
            super().__init__(NODE_NAME, **node_options)
            for name, default, meaning in PARAMETERS:
                self.declare_parameter(name, default, ParameterDescriptor(
                    description=meaning, read_only=name not in READ_WRITE))
            self.add_on_set_parameters_callback(self._check_parameters)
            self.warnings = WarningThrottle(self.get_logger())
            self.counters = Counters()
            self.label_map = load_label_map("semantic_kitti")
            self.mapper = self._make_mapper()
            self.map_lock = threading.Lock()
            self.map_version = 0
            self.published_version = -1
            self.saved_version = 0  # map_version at the last save (or load): autosave skips an unchanged map
            self.map_generation = 0  # bumped by every reset; clouds received before it are stale
            self._check_robustness_parameters()
            self.poses = OdometryBuffer(max_jump=self._param("max_pose_jump"))
            self.queue: deque[PendingCloud] = deque()
            self.queue_changed = threading.Condition()
            self.stopping = False
            self.newest_odometry_stamp: int | None = None  # ns, of accepted odometry
            self.started = time.monotonic()
            self.last_cloud_received: float | None = None
            self.last_odometry_received: float | None = None
            self.unreadable_map_file: str | None = None  # moved aside before the first save overwrites it
            self._load_map_at_start()

            input_qos = self._input_qos()
            self.create_subscription(PointCloud2, "cloud_in", self._on_cloud, input_qos)
            self.create_subscription(Odometry, "odom", self._on_odometry, input_qos)
            latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.map_publisher = self.create_publisher(PointCloud2, "/semantic_map", latched)
            self.variance_publisher = self.create_publisher(PointCloud2, "/semantic_map/variance", latched)
            self.local_publisher = self.create_publisher(PointCloud2, "/semantic_map/local", 2)
            self.create_service(Trigger, "~/save_map", self._on_save_map)
            self.create_service(Trigger, "~/reset", self._on_reset)
            self.create_service(Trigger, "~/export_ply", self._on_export_ply)
            # Housekeeping runs on the steady clock: with use_sim_time the ROS clock stops when a bag
            # pauses or ends, and the map must still be published and the counters logged.
            steady = Clock(clock_type=ClockType.STEADY_TIME)
            self.publish_due = False
            self.publish_timer = self.create_timer(self._param("publish_period"), self._request_publish, clock=steady)
            self.stats_timer = self.create_timer(self._param("stats_period"), self._log_counters, clock=steady)
            autosave = self._param("autosave_period")
            if autosave > 0:
                self.create_timer(autosave, self._autosave, clock=steady)
            self.create_timer(min(1.0, self._param("odometry_timeout") / 2), self._watch_odometry, clock=steady)
            self.worker = threading.Thread(target=self._work, name="convbki_update", daemon=True)
            self.worker.start()
            self.publisher_thread = threading.Thread(target=self._publish_loop, name="convbki_publish", daemon=True)
            self.publisher_thread.start()
            self.get_logger().info(
                f"ConvBKI mapper ready: {self.mapper.kernel.kind} kernel, {self.mapper.resolution} m voxels, "
                f"f = {self.mapper.kernel.filter_size}, window {self.mapper.geometry.dims.tolist()} voxels, "
                f"device {self.mapper.device}, map {self._param('map_frame')}; inputs "
                f"{self.resolve_topic_name('cloud_in')} + {self.resolve_topic_name('odom')}")

        # -- set-up ----------------------------------------------------------------------
        def _param(self, name: str):
            return self.get_parameter(name).value

        def _check_parameters(self, parameters) -> SetParametersResult:
            for parameter in parameters:
                if parameter.name in ("publish_period", "stats_period") and not parameter.value > 0:
                    return SetParametersResult(successful=False, reason=f"{parameter.name} must be > 0")
                if parameter.name == "max_variance" and parameter.value < 0:
                    return SetParametersResult(successful=False, reason="max_variance must be >= 0")
            return SetParametersResult(successful=True)

        def _make_mapper(self) -> ConvBKIMapper:
            kernel_file = self._param("kernel_file") or str(kernel_path("semantic_kitti_compound"))
            config = load_kernel_file(kernel_file)
            if config.num_classes != self._param("num_classes"):
                raise ValueError(f"{kernel_file}: kernel has {config.num_classes} classes, num_classes is "
                                 f"{self._param('num_classes')}")
            if self._param("label_space") not in ("raw", "learning"):
                raise ValueError(f"label_space must be raw or learning, got {self._param('label_space')!r}")
            bounds = list(self._param("local_bounds"))
            if len(bounds) != 6:
                raise ValueError(f"local_bounds needs 6 numbers (min xyz, max xyz), got {len(bounds)}")
            return ConvBKIMapper(config, local_bounds=(tuple(bounds[:3]), tuple(bounds[3:])),
                                 prior=self._param("prior"), resolution=self._param("resolution"),
                                 filter_size=self._param("filter_size"), device=self._param("device"),
                                 frame_id=self._param("map_frame"), ignore_classes=self.label_map.ignore_classes)

        def _check_robustness_parameters(self) -> None:
            for name in ("max_points_per_cloud", "max_pose_jump", "stamp_backwards_tolerance"):
                if self._param(name) < 0:
                    raise ValueError(f"{name} must be >= 0, got {self._param(name)}")
            if not self._param("odometry_timeout") > 0:
                raise ValueError(f"odometry_timeout must be > 0, got {self._param('odometry_timeout')}")

        def _input_qos(self):
            kind = self._param("input_qos")
            if kind == "sensor_data":
                return qos_profile_sensor_data
            if kind != "reliable":
                raise ValueError(f"input_qos must be reliable or sensor_data, got {kind!r}")
            return QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE)

        def _load_map_at_start(self) -> None:
            path = self._param("map_file")
            if not path or not Path(path).exists():
                return
            try:
                self.mapper.load(path)
            except MapFileError as error:
                if self._param("refuse_bad_map_file"):
                    raise MapFileError(f"{error} (refuse_bad_map_file is true: not starting)") from None
                self.unreadable_map_file = path
                self.get_logger().error(
                    f"{error}; starting with an EMPTY map. The file is kept: the first save moves it to "
                    f"{path}.unreadable before writing the new map (set refuse_bad_map_file to exit instead)")
                return
            self.map_version += 1
            self.saved_version = self.map_version
            self.get_logger().info(f"loaded {len(self.mapper)} voxels from {path}")

        # -- inputs (executor thread: cheap, no maths) -------------------------------------
        def _on_cloud(self, msg) -> None:
            self.counters.scans_in += 1
            self.last_cloud_received = time.monotonic()
            stamp = stamp_to_ns(msg.header.stamp)
            # Checks that need no decoding run here, so that a cloud that can never be used does
            # not wait for odometry nor sit in the queue (a 5 M point cloud is 80 MB), nor count
            # as a sign of time going backwards.
            points = int(msg.width) * int(msg.height)
            limit = int(self._param("max_points_per_cloud"))
            if limit and points > limit:
                self.counters.drop("too large")
                self.warnings.warn("too large", f"dropping cloud stamped {stamp / 1e9:.3f} s: {points} points "
                                   f"({len(msg.data) / 1e6:.0f} MB), more than max_points_per_cloud = {limit}")
                return
            if points == 0:
                self.counters.drop("empty")
                self.warnings.warn("empty", f"dropping empty cloud stamped {stamp / 1e9:.3f} s "
                                   f"(width {msg.width} x height {msg.height})")
                return
            with self.queue_changed:
                queue_limit = max(1, int(self._param("cloud_queue_size")))
                while len(self.queue) >= queue_limit:
                    self.queue.popleft()
                    self.counters.drop("queue full")
                    self.warnings.warn("queue", f"update queue full ({queue_limit} clouds waiting): dropping the "
                                       "oldest cloud; the map update is slower than the input rate")
                self.queue.append(PendingCloud(msg, time.monotonic(), self.map_generation))
                self.queue_changed.notify()

        def _on_odometry(self, msg) -> None:
            self.counters.odometry_in += 1
            stamp = stamp_to_ns(msg.header.stamp)
            position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
            translation = [position.x, position.y, position.z]
            quaternion = [orientation.x, orientation.y, orientation.z, orientation.w]
            problem = pose_problem(translation, quaternion)
            if problem:
                self.counters.odometry_rejected += 1
                self.warnings.warn("odometry " + problem_key(problem),
                                   f"ignoring odometry stamped {stamp / 1e9:.3f} s: {problem}")
                return
            self.last_odometry_received = time.monotonic()
            self._check_time_going_backwards(stamp)
            pose = pose_from_translation_quaternion(translation, quaternion)
            with self.queue_changed:
                previous = self.poses.latest_stamp
                jump = self.poses.add(stamp, pose, msg.child_frame_id)
                self.queue_changed.notify()
            if jump is None:
                return
            after = f"after {previous / 1e9:.3f} s" if previous is not None and previous < stamp else "out of order"
            if self._param("reset_on_pose_jump"):
                with self.queue_changed:
                    self.poses.drop_before(stamp)
                action = "map reset (reset_on_pose_jump): a new map starts at the new pose"
                self._reset_map()
            else:
                action = "map kept; clouds stamped inside the jump are dropped"
            self.warnings.warn("jump", f"odometry jumped {jump:.2f} m at {stamp / 1e9:.3f} s ({after}; "
                               f"max_pose_jump = {self._param('max_pose_jump')} m): {action}")

        def _check_time_going_backwards(self, stamp: int) -> None:
            """Notice time going backwards (a bag played again, a restarted source) on the odometry.

            Only odometry that passed its checks counts. Clouds are left out on purpose: they
            may lag the odometry by seconds (segmentation keeps the capture stamp) and arrive
            in any order, and a malformed cloud with a wild stamp must change nothing.
            """
            newest = self.newest_odometry_stamp
            if newest is None or stamp > newest:
                self.newest_odometry_stamp = stamp
                return
            if newest - stamp <= seconds_to_ns(self._param("stamp_backwards_tolerance")):
                return
            self.newest_odometry_stamp = stamp
            # The odometry kept belongs to the old timeline: a cloud of the new one must never be
            # placed with it, and the clouds still waiting belong to the old one.
            with self.queue_changed:
                self.poses.clear()
                stale = len(self.queue)
                self.queue.clear()
                self.counters.drop("time reset", stale)
            reset = self._param("reset_on_stamp_backwards")
            if reset:
                self._reset_map()
            self.warnings.warn("time", f"time went backwards by {(newest - stamp) / 1e9:.3f} s (odometry stamped "
                               f"{stamp / 1e9:.3f} s after input stamped {newest / 1e9:.3f} s; a restarted bag?): "
                               f"odometry history cleared, {stale} waiting clouds dropped, "
                               f"{'map reset (reset_on_stamp_backwards)' if reset else 'map kept'}")

        def _watch_odometry(self) -> None:
            """Warn every odometry_timeout seconds while clouds come in and odometry does not."""
            timeout = self._param("odometry_timeout")
            now = time.monotonic()
            if self.last_cloud_received is None or now - self.last_cloud_received > timeout:
                return  # no input at all (nothing played yet, or the bag ended): nothing to say
            since = now - (self.last_odometry_received or self.started)
            if since < timeout:
                return
            what = "no usable odometry" if self.counters.odometry_in else "no odometry at all"
            self.warnings.warn("no odometry", f"{what} on {self.resolve_topic_name('odom')} for {since:.1f} s "
                               f"while clouds arrive on {self.resolve_topic_name('cloud_in')}: clouds cannot be "
                               "placed (check the odom remapping, its QoS and its publisher)", period=timeout)

        def _reset_map(self) -> None:
            """Clear the map; clouds received before now are stale (their poses may be too)."""
            with self.queue_changed:
                self.map_generation += 1
            with self.map_lock:
                self.mapper.reset()
                self.map_version += 1
            self._request_publish()

        # -- the update (worker thread) ---------------------------------------------------
        def _work(self) -> None:
            """The update thread: integrates queued clouds in order, off the executor."""
            while True:
                with self.queue_changed:
                    while not self.queue and not self.stopping:
                        self.queue_changed.wait(0.5)
                    if self.stopping:
                        return
                    chosen = self._next_cloud()
                    if chosen is None:  # every queued cloud still waits for its odometry
                        self.queue_changed.wait(0.02)
                        continue
                    pending, lookup = chosen
                try:
                    self._integrate(pending, lookup)
                except Exception as error:  # never let one scan stop the mapping thread
                    self.counters.drop("error")
                    self.get_logger().error(f"scan not integrated: {error.__class__.__name__}: {error}")

        def _next_cloud(self):
            """The oldest queued cloud that can be decided now (call with ``queue_changed`` held).

            A cloud whose odometry has not arrived does not hold up the clouds behind it: the
            update is a sum, so the order of integration does not change the map. A cloud is
            decided when its pose is known, or when it has waited ``pose_wait_timeout``.
            """
            timeout = self._param("pose_wait_timeout")
            now = time.monotonic()
            for position, pending in enumerate(self.queue):
                if pending.generation != self.map_generation:
                    del self.queue[position]
                    return pending, None
                lookup = self.poses.lookup(stamp_to_ns(pending.msg.header.stamp))
                waiting = lookup.status in (PoseStatus.WAIT, PoseStatus.EMPTY)
                if not waiting or now - pending.received >= timeout:
                    del self.queue[position]
                    return pending, lookup
            return None

        def _publish_loop(self) -> None:
            """The publishing thread: a map of a million voxels takes a while to encode and send,
            so it runs beside the updates (the map is only locked while it is copied)."""
            while True:
                with self.queue_changed:
                    while not self.publish_due and not self.stopping:
                        self.queue_changed.wait(0.5)
                    if self.stopping:
                        return
                    self.publish_due = False
                try:
                    self._publish_map()
                except Exception as error:
                    self.get_logger().error(f"publishing the map failed: {error.__class__.__name__}: {error}")

        def _request_publish(self) -> None:
            with self.queue_changed:
                self.publish_due = True
                self.queue_changed.notify_all()

        def _integrate(self, pending: PendingCloud, lookup) -> None:
            msg = pending.msg
            if lookup is None:
                self.counters.drop("map reset")
                self.warnings.warn("stale", "dropping a cloud received before the map was reset")
                return
            if lookup.status is not PoseStatus.FOUND:
                reason = {PoseStatus.EMPTY: "no odometry received yet",
                          PoseStatus.TOO_OLD: "the cloud is older than the odometry kept",
                          PoseStatus.JUMP: "the odometry jumped between the poses around its stamp",
                          PoseStatus.WAIT: f"no odometry covered its stamp within "
                                           f"{self._param('pose_wait_timeout')} s"}[lookup.status]
                self.counters.drop("pose jump" if lookup.status is PoseStatus.JUMP else "no pose")
                latest = self.poses.latest_stamp
                latest_text = f"; latest odometry {latest / 1e9:.3f} s" if latest is not None else ""
                self.warnings.warn(f"pose {lookup.status.value}",
                                   f"dropping cloud stamped {stamp_to_ns(msg.header.stamp) / 1e9:.3f} s: "
                                   f"{reason}{latest_text}")
                return
            if lookup.child_frame_id and msg.header.frame_id and lookup.child_frame_id != msg.header.frame_id:
                self.counters.drop("frame mismatch")
                self.warnings.warn("frame", f"dropping cloud in frame '{msg.header.frame_id}': odometry is for "
                                   f"'{lookup.child_frame_id}'")
                return
            try:
                cloud = decode_cloud(msg, self.mapper.num_classes)
            except CloudError as error:
                self.counters.drop("bad cloud")
                self.warnings.warn("cloud " + problem_key(str(error)), f"dropping cloud: {error}")
                return
            if not len(cloud):
                self.counters.drop("no finite points")
                self.warnings.warn("no finite", f"dropping cloud: all {cloud.total_points} points have NaN/inf "
                                   "coordinates (or probabilities)")
                return
            if cloud.dropped_non_finite:
                self.warnings.warn("nan", f"{cloud.dropped_non_finite} of {cloud.total_points} points with NaN/inf "
                                   "coordinates (or probabilities) dropped; the rest are integrated")
            values = cloud.probabilities
            if values is None:
                values = self._learning_labels(cloud.labels)
                if values is None:
                    self.counters.drop("unknown labels")
                    return
            with self.map_lock:
                if pending.generation != self.map_generation:  # a reset came while it was decoded
                    self.counters.drop("map reset")
                    return
                result = self.mapper.integrate(cloud.points, values, lookup.pose)
                self.map_version += 1
            self.counters.integrated += 1
            self.counters.last_update_ms = result.timing_ms["total"]
            if self._param("publish_local") and self.local_publisher.get_subscription_count():
                with self.map_lock:
                    local = self.mapper.local_voxels()
                self.local_publisher.publish(encode_map_cloud(msg.header.stamp, self._param("map_frame"), local,
                                                              self.label_map.colors))

        def _learning_labels(self, labels):
            """The cloud's labels as learning ids; unknown ids are warned about and become ignored
            class 0. None (and a warning) when no label is known: the cloud would add nothing, and
            such a cloud usually means a wrong label_space."""
            space = self._param("label_space")
            if space == "raw":
                unknown = self.label_map.unknown_raw(labels)
            else:
                unknown = (labels < 0) | (labels >= self.mapper.num_classes)
            count = int(np.count_nonzero(unknown))
            if count:
                examples = ", ".join(str(v) for v in np.unique(labels[unknown])[:5])
                known = f"{self.label_map.name} label map" if space == "raw" else \
                    f"learning ids 0..{self.mapper.num_classes - 1}"
                if count == labels.size:
                    self.warnings.warn("all unknown", f"dropping cloud: all {count} label ids are unknown to the "
                                       f"{known} (e.g. {examples}); is label_space ({space}) right?")
                    return None
                self.warnings.warn("unknown", f"{count} of {labels.size} points carry label ids unknown to the "
                                   f"{known} (e.g. {examples}); they are ignored")
            if space == "raw":
                return self.label_map.to_learning(labels)
            return np.where(unknown, 0, labels)

        # -- outputs ---------------------------------------------------------------------
        def _publish_map(self) -> None:
            """Publish /semantic_map and /semantic_map/variance if the map changed and anyone listens.

            Both topics are latched; with no subscriber the (possibly large) map is not encoded
            at all, and a subscriber that joins later gets the current map at the next tick.
            """
            listeners = self.map_publisher.get_subscription_count() + \
                self.variance_publisher.get_subscription_count()
            if not listeners:
                return
            started = time.perf_counter()
            with self.map_lock:
                if self.map_version == self.published_version:
                    return
                version = self.map_version
                indices, alpha = self.mapper.items()
            voxels = self.mapper.voxel_set(indices, alpha)
            max_variance = self._param("max_variance")
            mask = voxels.variance <= max_variance if max_variance > 0 else None
            stamp = self.get_clock().now().nanoseconds
            frame = self._param("map_frame")
            if self.map_publisher.get_subscription_count():
                self.map_publisher.publish(encode_map_cloud(stamp, frame, voxels, self.label_map.colors, mask=mask))
            if self.variance_publisher.get_subscription_count():
                fields = variance_cloud_fields(voxels)
                if mask is not None:
                    fields = {name: values[mask] for name, values in fields.items()}
                self.variance_publisher.publish(encode_cloud(stamp, frame, fields))
            self.published_version = version
            self.counters.last_publish_ms = 1e3 * (time.perf_counter() - started)

        def _log_counters(self) -> None:
            with self.queue_changed:
                queue_length = len(self.queue)
            self.get_logger().info(self.counters.line(queue_length, len(self.mapper)))

        # -- services --------------------------------------------------------------------
        def save_map(self) -> tuple[bool, str]:
            """Write the map to map_file (atomically: a failed save leaves the previous file as it was)."""
            path = self._param("map_file")
            if not path:
                return False, "map_file parameter is empty: nowhere to save"
            try:
                if self.unreadable_map_file == path and os.path.lexists(path):
                    os.replace(path, path + ".unreadable")
                    self.get_logger().warning(f"moved the unreadable map file {path} to {path}.unreadable")
                self.unreadable_map_file = None
                # Copy under the lock (a fraction of a second), write without it: updates go on
                # while a large map is written to disk.
                with self.map_lock:
                    snapshot = self.mapper.snapshot()
                    version = self.map_version
                snapshot.write(path)
                count = len(snapshot)
                self.saved_version = version
            except (OSError, ValueError) as error:
                return False, f"could not save {path}: {getattr(error, 'strerror', None) or error}"
            return True, f"saved {count} voxels to {path}"

        def _on_save_map(self, request, response):
            response.success, response.message = self.save_map()
            self._log_outcome(response.success, response.message)
            return response

        def _on_reset(self, request, response):
            self._reset_map()
            response.success, response.message = True, "map reset: 0 voxels"
            self.get_logger().info(response.message)
            return response

        def _on_export_ply(self, request, response):
            path = self._param("ply_file")
            if not path:
                map_file = self._param("map_file")
                path = str(Path(map_file).with_suffix(".ply")) if map_file else "convbki_map.ply"
            try:
                # Copy under the lock; statistics and the file are done without it (as for saves).
                with self.map_lock:
                    indices, alpha = self.mapper.items()
                voxels = self.mapper.voxel_set(indices, alpha)
                count = write_voxels_ply(voxels, path, max_variance=self._param("max_variance") or None)
                response.success, response.message = True, f"wrote {count} voxels to {path}"
            except OSError as error:
                response.success, response.message = False, f"could not write {path}: {error.strerror or error}"
            return response

        def _autosave(self) -> None:
            if self._param("map_file") and self.map_version != self.saved_version:
                ok, message = self.save_map()
                self._log_outcome(ok, f"autosave: {message}")

        def _log_outcome(self, ok: bool, message: str) -> None:
            # Two call sites on purpose: rclpy remembers the severity of each logging call site
            # and raises (stopping the node) when one line logs at two severities.
            if ok:
                self.get_logger().info(message)
            else:
                self.get_logger().error(message)

        # -- shutdown --------------------------------------------------------------------
        def stop(self) -> None:
            """Stop the update thread (the scan in progress finishes) and save when asked to."""
            with self.queue_changed:
                self.stopping = True
                self.queue_changed.notify_all()
            self.worker.join(timeout=1.5)
            self.publisher_thread.join(timeout=0.3)
            path = self._param("map_file")
            if not (self._param("save_on_shutdown") and path and self.map_version):
                return
            if self.map_version != self.saved_version:
                message = self.save_map()[1]
            else:
                message = f"the map is unchanged since it was last saved to (or loaded from) {path}"
            print(f"[{NODE_NAME}] on shutdown: {message}", file=sys.stderr)

    return MapperNode


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    build_parser().parse_args(strip_ros_args(args))
    rclpy = _import_ros()[0]
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    use_large_data_profile()
    publish_asynchronously()  # a large map being sent must not stall the update thread
    rclpy.init(args=args)
    node = None
    try:
        # The executor exists before the node says "ready", so a Ctrl-C right after it lands in spin().
        executor = SingleThreadedExecutor()
        node = make_node_class()()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, KernelFileError, OSError) as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    except Exception:
        # Ctrl-C shuts the context down from the signal handler; an executor that was just
        # building its wait set then fails with an RCLError. That is a shutdown, not a crash.
        if rclpy.ok():
            raise
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the save short
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())

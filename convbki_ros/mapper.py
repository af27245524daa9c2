"""``mapper``: the ConvBKI semantic mapping node (``convbki_mapper``).

Run with ``ros2 run convbki_ros mapper --ros-args --params-file config/mapper.yaml``
or ``python -m convbki_ros.mapper --ros-args ...``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import textwrap
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from convbki_core.kernels import KernelFileError, load_kernel_file
from convbki_core.labels import load_label_map
from convbki_core.mapfile import MapFileError
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path
from convbki_ros.dds import use_large_data_profile
from convbki_ros.pointcloud import CloudError, decode_cloud, encode_cloud, encode_map_cloud, variance_cloud_fields
from convbki_ros.pose_buffer import OdometryBuffer, PoseStatus
from convbki_ros.ros_args import strip_ros_args
from convbki_ros.transforms import odometry_to_pose, stamp_to_ns

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
    ("cloud_queue_size", 10, "clouds waiting to be integrated; when full the oldest is dropped; count"),
    ("pose_wait_timeout", 2.0, "how long a cloud waits for odometry covering its stamp before it is dropped; "
     "seconds"),
    ("stats_period", 10.0, "period of the counters line in the log (scans in, integrated, dropped); seconds"),
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


class WarningThrottle:
    """One warning per problem per ``period`` seconds; counts what it held back."""

    def __init__(self, logger, period: float = 5.0):
        self.logger = logger
        self.period = period
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warn(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < self.period:
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
    decoded: object = None


@dataclass
class Counters:
    """What happened to the scans; logged every ``stats_period`` seconds."""

    scans_in: int = 0
    integrated: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    last_update_ms: float = 0.0
    last_publish_ms: float = 0.0

    def drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def line(self, queue_length: int, voxels: int) -> str:
        dropped = sum(self.dropped.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.dropped.items()))
        return (f"scans in {self.scans_in}, integrated {self.integrated}, dropped {dropped}"
                f"{f' ({reasons})' if reasons else ''}, queue {queue_length}, map voxels {voxels}, "
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
            self.poses = OdometryBuffer()
            self.queue: deque[PendingCloud] = deque()
            self.queue_changed = threading.Condition()
            self.stopping = False
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
                self.map_version += 1
                self.get_logger().info(f"loaded {len(self.mapper)} voxels from {path}")
            except MapFileError as error:
                self.get_logger().error(f"{error}; starting with an empty map")

        # -- inputs (executor thread: cheap, no maths) -------------------------------------
        def _on_cloud(self, msg) -> None:
            self.counters.scans_in += 1
            with self.queue_changed:
                limit = max(1, int(self._param("cloud_queue_size")))
                while len(self.queue) >= limit:
                    self.queue.popleft()
                    self.counters.drop("queue full")
                    self.warnings.warn("queue", f"update queue full ({limit} clouds waiting): dropping the oldest "
                                       "cloud; the map update is slower than the input rate")
                self.queue.append(PendingCloud(msg, time.monotonic()))
                self.queue_changed.notify()

        def _on_odometry(self, msg) -> None:
            pose = odometry_to_pose(msg)
            with self.queue_changed:
                self.poses.add(stamp_to_ns(msg.header.stamp), pose, msg.child_frame_id)
                self.queue_changed.notify()

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
            if lookup.status is not PoseStatus.FOUND:
                reason = {PoseStatus.EMPTY: "no odometry received yet",
                          PoseStatus.TOO_OLD: "the cloud is older than the odometry kept",
                          PoseStatus.WAIT: f"no odometry covered its stamp within "
                                           f"{self._param('pose_wait_timeout')} s"}[lookup.status]
                self.counters.drop("no pose")
                latest = self.poses.latest_stamp
                latest_text = f"; latest odometry {latest / 1e9:.3f} s" if latest is not None else ""
                self.warnings.warn("pose", f"dropping cloud stamped {stamp_to_ns(msg.header.stamp) / 1e9:.3f} s: "
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
                self.warnings.warn("cloud", f"dropping cloud: {error}")
                return
            values = cloud.probabilities
            if values is None:
                values = cloud.labels
                if self._param("label_space") == "raw":
                    unknown = self.label_map.unknown_raw(values)
                    if unknown.any():
                        self.warnings.warn("labels", f"{int(unknown.sum())} points carry label ids unknown to the "
                                           "SemanticKITTI label map; they are ignored")
                    values = self.label_map.to_learning(values)
            if cloud.dropped_non_finite:
                self.warnings.warn("nan", f"{cloud.dropped_non_finite} points with NaN/inf coordinates dropped")
            with self.map_lock:
                result = self.mapper.integrate(cloud.points, values, lookup.pose)
                self.map_version += 1
            self.counters.integrated += 1
            self.counters.last_update_ms = result.timing_ms["total"]
            if result.stats.unknown_label:
                self.warnings.warn("unknown", f"{result.stats.unknown_label} points with labels outside "
                                   f"0..{self.mapper.num_classes - 1} ignored (label_space is "
                                   f"{self._param('label_space')})")
            if self._param("publish_local") and self.local_publisher.get_subscription_count():
                with self.map_lock:
                    local = self.mapper.local_voxels()
                self.local_publisher.publish(encode_map_cloud(msg.header.stamp, self._param("map_frame"), local,
                                                              self.label_map.colors))

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
            path = self._param("map_file")
            if not path:
                return False, "map_file parameter is empty: nowhere to save"
            try:
                with self.map_lock:
                    self.mapper.save(path)
                    count = len(self.mapper)
            except (OSError, ValueError) as error:
                return False, f"could not save {path}: {getattr(error, 'strerror', None) or error}"
            return True, f"saved {count} voxels to {path}"

        def _on_save_map(self, request, response):
            response.success, response.message = self.save_map()
            (self.get_logger().info if response.success else self.get_logger().error)(response.message)
            return response

        def _on_reset(self, request, response):
            with self.map_lock:
                self.mapper.reset()
                self.map_version += 1
            self._request_publish()
            response.success, response.message = True, "map reset: 0 voxels"
            self.get_logger().info(response.message)
            return response

        def _on_export_ply(self, request, response):
            path = self._param("ply_file")
            if not path:
                map_file = self._param("map_file")
                path = str(Path(map_file).with_suffix(".ply")) if map_file else "convbki_map.ply"
            try:
                with self.map_lock:
                    count = self.mapper.export_ply(path, max_variance=self._param("max_variance") or None)
                response.success, response.message = True, f"wrote {count} voxels to {path}"
            except OSError as error:
                response.success, response.message = False, f"could not write {path}: {error.strerror or error}"
            return response

        def _autosave(self) -> None:
            if self._param("map_file"):
                ok, message = self.save_map()
                (self.get_logger().info if ok else self.get_logger().error)(f"autosave: {message}")

        # -- shutdown --------------------------------------------------------------------
        def stop(self) -> None:
            """Stop the update thread (the scan in progress finishes) and save when asked to."""
            with self.queue_changed:
                self.stopping = True
                self.queue_changed.notify_all()
            self.worker.join(timeout=1.5)
            self.publisher_thread.join(timeout=0.3)
            if self._param("save_on_shutdown") and self._param("map_file") and self.map_version:
                message = self.save_map()[1]
                print(f"[{NODE_NAME}] on shutdown: {message}", file=sys.stderr)

    return MapperNode


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    build_parser().parse_args(strip_ros_args(args))
    rclpy = _import_ros()[0]
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    use_large_data_profile()
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

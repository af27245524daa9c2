"""``MapperNode``: the ConvBKI mapping node (``convbki_mapper``), a plain rclpy node class.

Threads, so that no input waits on a slow output:

* the executor's: clouds and odometry arrive (cheap checks only, then the queue), services
  and timers run. Saves and exports are in their own callback group, so with a
  multi-threaded executor (what ``main`` uses) a large file being written never holds up
  the inputs;
* the update thread: takes the next cloud whose pose is known, decodes it and integrates
  it into the map (``ConvBKIMapper``);
* the publishing thread: encodes and sends the map topics; the map is locked only while it
  is copied.

The node can be added to any executor (``executor.add_node(MapperNode())``); with a
single-threaded one, saves block the inputs while they write.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from convbki_core.labels import load_label_map
from convbki_core.records import RECORD, packed_palette, records_from_alpha
from convbki_ros.map_files import MapFiles
from convbki_ros.mapping import MappingCore
from convbki_ros.params import NODE_NAME, PARAMETERS, check_choice, declare
from convbki_ros.pointcloud import encode_cloud, records_cloud
from convbki_ros.status import ERROR, OK, WARN, MapperStatus, WarningThrottle, diagnostic_values

LEVELS = {OK: DiagnosticStatus.OK, WARN: DiagnosticStatus.WARN, ERROR: DiagnosticStatus.ERROR}
# Odometry is small and may arrive in bursts (a reliable reader delivers in order, so one
# lost message holds up the rest until it is repeated): keep every pose of such a burst.
ODOMETRY_DEPTH = 200
LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class MapperNode(Node):
    """Subscribes labelled clouds and odometry, integrates them with ConvBKI, publishes the map.

    ``node_options`` go to ``rclpy.node.Node`` (namespace, context, parameter_overrides, ...).
    Raises ``StartupError`` (a ``ValueError``), ``KernelFileError`` or ``MapFileError`` with a
    one-line message on bad start-up input.
    """

    def __init__(self, **node_options):
        super().__init__(NODE_NAME, **node_options)
        self.status = MapperStatus()
        self.warnings = WarningThrottle(self.get_logger())
        self.label_map = load_label_map("semantic_kitti")
        self.palette = packed_palette(self.label_map.colors)
        self.core = MappingCore(self, self.status, self.warnings, self.label_map)
        self.files = MapFiles(self)
        self.files.load_at_start()

        inputs, odometry_group, file_io, housekeeping = (MutuallyExclusiveCallbackGroup() for _ in range(4))
        # Clouds and odometry in groups of their own: a cloud being queued never delays odometry.
        self.create_subscription(PointCloud2, "cloud_in", self.core.on_cloud, self._input_qos(20),
                                 callback_group=inputs)
        self.create_subscription(Odometry, "odom", self.core.on_odometry, self._input_qos(ODOMETRY_DEPTH),
                                 callback_group=odometry_group)
        self.map_publisher = self.create_publisher(PointCloud2, "semantic_map", LATCHED)
        self.variance_publisher = self.create_publisher(PointCloud2, "semantic_map/variance", LATCHED)
        self.local_publisher = self.create_publisher(PointCloud2, "semantic_map/local", 2)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/save_map", self.files.on_save_map, callback_group=file_io)
        self.create_service(Trigger, "~/export_ply", self.files.on_export_ply, callback_group=file_io)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=housekeeping)

        # Housekeeping runs on the steady clock: with use_sim_time the ROS clock stops when a bag
        # pauses or ends, and the map must still be published and the counters reported.
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._groups = {"housekeeping": housekeeping, "file_io": file_io}
        self._period_timers: dict[str, object] = {}
        self._timer_callbacks = {"publish_period": (self._request_publish, "housekeeping"),
                                 "stats_period": (self._log_counters, "housekeeping"),
                                 "autosave_period": (self.files.autosave, "file_io"),
                                 "odometry_timeout": (self.core.watch_odometry, "housekeeping"),
                                 "diagnostics_period": (self._publish_diagnostics, "housekeeping")}
        for name in self._timer_callbacks:
            self._restart_timer(name)
        self.add_post_set_parameters_callback(self._on_parameters_changed)

        self.outputs_changed = threading.Condition()
        self.publish_due = False
        self.local_due = False
        self.core.on_integrated = self._request_local
        self.update_thread = threading.Thread(target=self.core.run, name="convbki_update", daemon=True)
        self.update_thread.start()
        self.publisher_thread = threading.Thread(target=self._publish_loop, name="convbki_publish", daemon=True)
        self.publisher_thread.start()
        mapper = self.core.mapper
        self.get_logger().info(
            f"ConvBKI mapper ready: {mapper.kernel.kind} kernel, {mapper.resolution} m voxels, "
            f"f = {mapper.kernel.filter_size}, window {mapper.geometry.dims.tolist()} voxels, "
            f"device {mapper.device}, {self.core.mount_text()}; inputs {self.resolve_topic_name('cloud_in')} + "
            f"{self.resolve_topic_name('odom')}")

    def param(self, name: str):
        return self.get_parameter(name).value

    # -- set-up and run-time parameters ---------------------------------------------------
    def declare_all(self, kernel_values: dict[str, object]) -> None:
        """Declare every parameter but ``kernel_file`` (declared first, to read the kernel)."""
        for spec in PARAMETERS:
            if spec.name != "kernel_file":
                declare(self, spec, kernel_values.get(spec.name))

    def _input_qos(self, depth: int):
        if check_choice("input_qos", self.param("input_qos")) == "sensor_data":
            return QoSProfile(depth=max(depth, qos_profile_sensor_data.depth),
                              reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
        return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

    def _restart_timer(self, name: str) -> None:
        """(Re)create the timer driven by parameter ``name``; a period of 0 means none."""
        if name in self._period_timers:
            self.destroy_timer(self._period_timers.pop(name))
        callback, group = self._timer_callbacks[name]
        period = float(self.param(name))
        if name == "odometry_timeout":
            period = min(1.0, period / 2)  # the watcher looks often; it warns once per timeout
        if period > 0:
            self._period_timers[name] = self.create_timer(period, callback, clock=self._steady,
                                                   callback_group=self._groups[group])

    def _on_parameters_changed(self, parameters) -> None:
        for parameter in parameters:
            if parameter.name in self._timer_callbacks:
                self._restart_timer(parameter.name)
            elif parameter.name == "max_pose_jump":
                self.core.set_max_pose_jump(parameter.value)
            if parameter.name in ("max_variance", "publish_local"):
                self._request_publish(force=True)
            self.get_logger().info(f"parameter {parameter.name} is now {parameter.value}")

    # -- outputs ----------------------------------------------------------------------------
    def _request_publish(self, force: bool = False) -> None:
        with self.outputs_changed:
            self.publish_due = True
            if force:
                self.core.published_version = -1
            self.outputs_changed.notify_all()

    def _request_local(self) -> None:
        with self.outputs_changed:
            self.local_due = True
            self.outputs_changed.notify_all()

    def _publish_loop(self) -> None:
        """The publishing thread. The local window is sent after updates, the newest one only and
        at most once per ``local_period``: when updates come faster than it can be encoded or
        watched, intermediate windows are skipped rather than queued, so watching the map never
        slows mapping down."""
        last_local = -1e9
        while True:
            with self.outputs_changed:
                while not self.core.stopping:
                    local_wait = last_local + self.param("local_period") - time.monotonic()
                    if self.publish_due or (self.local_due and local_wait <= 0):
                        break
                    self.outputs_changed.wait(min(0.5, local_wait) if self.local_due else 0.5)
                if self.core.stopping:
                    return
                publish_map = self.publish_due
                publish_local = self.local_due and local_wait <= 0
                self.publish_due = False
                self.local_due = self.local_due and not publish_local
            if publish_local:
                last_local = time.monotonic()
            try:
                if publish_local:
                    self._publish_local()
                if publish_map:
                    self._publish_map()
            except Exception as error:  # a failed publish must not end the thread
                self.get_logger().error(f"publishing failed: {error.__class__.__name__}: {error}")

    def _publish_local(self) -> None:
        if self.param("publish_local") and self.local_publisher.get_subscription_count():
            self.local_publisher.publish(self.core.local_cloud(self.core.frame, self.palette))

    def _publish_map(self) -> None:
        """``semantic_map`` and ``semantic_map/variance`` when the map changed and anyone listens.

        Both are latched; with no subscriber the (possibly large) map is not encoded at all,
        and a subscriber that joins later gets the current map at the next tick.
        """
        map_listeners = self.map_publisher.get_subscription_count()
        variance_listeners = self.variance_publisher.get_subscription_count()
        if not (map_listeners or variance_listeners):
            return
        started = time.perf_counter()
        copied = self.core.map_copy_if_changed()
        if copied is None:
            return
        indices, alpha, version = copied
        resolution = self.core.mapper.resolution
        stamp = self.get_clock().now().nanoseconds
        frame = self.core.frame
        max_variance = self.param("max_variance")
        if max_variance > 0 or variance_listeners:
            records = records_from_alpha(indices, alpha, resolution, self.palette)
            if max_variance > 0:
                records = records[records["variance"] <= max_variance]
            def fill(out):
                np.copyto(out, records)
        else:  # straight into the message
            records = None

            def fill(out):
                records_from_alpha(indices, alpha, resolution, self.palette, out)
        count = len(indices) if records is None else len(records)
        if map_listeners:
            self.map_publisher.publish(records_cloud(stamp, frame, RECORD, count, fill))
        if variance_listeners:
            fields = {name: records[name] for name in ("x", "y", "z")}
            self.variance_publisher.publish(encode_cloud(stamp, frame, {**fields, "intensity": records["variance"]}))
        self.core.published_version = version
        self.status.published(1e3 * (time.perf_counter() - started))

    def _snapshot(self):
        return self.status.snapshot(len(self.core.queue), self.core.queue.waiting_for_pose(), len(self.core.mapper),
                                    self.core.map_version)

    def _log_counters(self) -> None:
        self.get_logger().info(self._snapshot().line())

    def _publish_diagnostics(self) -> None:
        snapshot = self._snapshot()
        level, message = self.status.health(snapshot, self.param("odometry_timeout"))
        status = DiagnosticStatus(level=LEVELS[level], name=f"{self.get_fully_qualified_name()}: mapping",
                                  message=message, hardware_id=self.core.frame,
                                  values=[KeyValue(key=k, value=v) for k, v in diagnostic_values(snapshot)])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)

    # -- services -----------------------------------------------------------------------------
    def _on_reset(self, request, response):
        self.core.reset_map()
        self._request_publish()
        response.success, response.message = True, "map reset: 0 voxels"
        self.get_logger().info(response.message)
        return response

    # -- shutdown -----------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the threads (the scan in progress finishes) and save when asked to."""
        self.core.stop()
        with self.outputs_changed:
            self.outputs_changed.notify_all()
        self.update_thread.join(timeout=1.5)
        self.publisher_thread.join(timeout=0.3)
        message = self.files.save_on_shutdown()
        if message:
            print(f"[{NODE_NAME}] on shutdown: {message}", file=sys.stderr)




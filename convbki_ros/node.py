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

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from convbki_core.datasets.labels import load_label_map
from convbki_core.records import packed_palette
from convbki_ros.map_files import MapFiles
from convbki_ros.mapping import MappingCore
from convbki_ros.outputs import MapOutputs
from convbki_ros.params import NODE_NAME, PARAMETERS, check_choice, declare
from convbki_ros.status import ERROR, OK, WARN, MapperStatus, WarningThrottle, diagnostic_values

LEVELS = {OK: DiagnosticStatus.OK, WARN: DiagnosticStatus.WARN, ERROR: DiagnosticStatus.ERROR}
# Odometry is small and may arrive in bursts (a reliable reader delivers in order, so one
# lost message holds up the rest until it is repeated): keep every pose of such a burst.
ODOMETRY_DEPTH = 200


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
        # The reader keeps as many clouds as the queue: DDS may deliver a burst after holding
        # messages back, and a shorter history would drop the oldest of it.
        self.create_subscription(PointCloud2, "cloud_in", self.core.on_cloud,
                                 self._input_qos(self.param("cloud_queue_size")), callback_group=inputs)
        self.create_subscription(Odometry, "odom", self.core.on_odometry, self._input_qos(ODOMETRY_DEPTH),
                                 callback_group=odometry_group)
        self.outputs = MapOutputs(self)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/save_map", self.files.on_save_map, callback_group=file_io)
        self.create_service(Trigger, "~/export_ply", self.files.on_export_ply, callback_group=file_io)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=housekeeping)

        # Housekeeping runs on the steady clock: with use_sim_time the ROS clock stops when a bag
        # pauses or ends, and the map must still be published and the counters reported.
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._groups = {"housekeeping": housekeeping, "file_io": file_io}
        self._period_timers: dict[str, object] = {}
        self._timer_callbacks = {"publish_period": (lambda: self.outputs.request("cycle"), "housekeeping"),
                                 "map_period": (lambda: self.outputs.request("map"), "housekeeping"),
                                 "stats_period": (self._log_counters, "housekeeping"),
                                 "autosave_period": (self.files.autosave, "file_io"),
                                 "odometry_timeout": (self.core.watch_odometry, "housekeeping"),
                                 "diagnostics_period": (self._publish_diagnostics, "housekeeping")}
        for name in self._timer_callbacks:
            self._restart_timer(name)
        self.add_post_set_parameters_callback(self._on_parameters_changed)

        self.core.on_integrated = lambda: self.outputs.request("local")
        self.update_thread = threading.Thread(target=self.core.run, name="convbki_update", daemon=True)
        self.update_thread.start()
        self.outputs.start()
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
            if parameter.name == "max_variance":  # the shown map changes as a whole
                self.outputs.request("cycle", refresh=True)
                self.outputs.request("map")
            self.get_logger().info(f"parameter {parameter.name} is now {parameter.value}")

    # -- reports ----------------------------------------------------------------------------
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
        self.outputs.request("cycle")
        self.outputs.request("map")
        response.success, response.message = True, "map reset: 0 voxels"
        self.get_logger().info(response.message)
        return response

    # -- shutdown -----------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop the threads (the scan in progress finishes) and save when asked to."""
        self.core.stop()
        self.outputs.stop()
        self.update_thread.join(timeout=1.5)
        message = self.files.save_on_shutdown()
        if message:
            print(f"[{NODE_NAME}] on shutdown: {message}", file=sys.stderr)




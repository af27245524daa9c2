"""``MapperNode``: the ConvBKI mapping node (``convbki_mapper``), a plain rclpy node class.

Threads, so that no input waits on a slow output:

* the executor's: clouds and odometry arrive (cheap checks only, then the queue), services
  and timers run;
* the file thread: saves, loads and exports, one after the other; their services await it,
  so a large file being written never holds up the inputs;
* the update thread: takes the next cloud whose pose is known, decodes it and integrates
  it into the map (``ConvBKIMapper``);
* the publishing thread: encodes and sends the map topics; the map is locked only while it
  is copied.

Before it subscribes to anything and says "ready", the node compiles (or loads from the
cache) every kernel it will run (``convbki_core.warm_up``), so its first scan integrates as
fast as its tenth.

The node can be added to any executor (``executor.add_node(MapperNode())``); ``main`` uses
a single-threaded one (rclpy's multi-threaded executor holds the GIL in its dispatch loop
much of the time, which slowed the update thread's scans tenfold at times).
"""

from __future__ import annotations

import os
import sys
import threading

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry, Path
from nav_msgs.srv import GetMap
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from convbki_core.compiled import kernel_cache
from convbki_core.io.labels import load_label_map
from convbki_core.outputs.records import packed_palette
from convbki_ros.files.map_files import MapFiles
from convbki_ros.files.start import (
    check_map_file_at_start,
    close_scan_log_folder,
    read_map_file_at_start,
    scan_log_folder_at_start,
    use_scan_log_folder,
)
from convbki_ros.guard import CallbackGuard
from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.mapping.corrections import CorrectionRunner
from convbki_ros.outputs.cloud_encoding import encode_cloud
from convbki_ros.outputs.publisher import MapOutputs
from convbki_ros.outputs.status import ERROR, OK, WARN, MapperStatus, WarningThrottle, diagnostic_values
from convbki_ros.param_checks import check_box, check_choice, choice_problem, min_move_problem
from convbki_ros.params import (
    MIN_AUTOSAVE_PERIOD,
    NODE_NAME,
    PARAMETERS,
    SPECS,
    declare,
    integers_as_doubles,
    optional,
)
from convbki_ros.settings import read_start_settings

LEVELS = {OK: DiagnosticStatus.OK, WARN: DiagnosticStatus.WARN, ERROR: DiagnosticStatus.ERROR}
# Odometry is small and may arrive in bursts (a reliable reader delivers in order, so one
# lost message holds up the rest until it is repeated): keep every pose of such a burst.
ODOMETRY_DEPTH = 200


def memory_values(memory) -> list[tuple[str, object]]:
    """The map's memory (a ``MemoryState``) as /diagnostics key-value pairs."""
    return [("map_megabytes", f"{(memory.store_bytes + memory.lent_bytes) / 1e6:.1f}"),
            ("map_budget_megabytes", f"{memory.budget_bytes / 1e6:g}"), ("map_full", str(memory.full).lower()),
            ("map_voxels_dropped", memory.voxels_dropped)]


class MapperNode(Node):
    """Subscribes labelled clouds and odometry, integrates them with ConvBKI, publishes the map.

    ``node_options`` go to ``rclpy.node.Node`` (namespace, context, parameter_overrides, ...).
    Raises ``StartupError`` (a ``ValueError``), ``KernelFileError`` or ``MapFileError`` with a
    one-line message on bad start-up input.
    """

    def __init__(self, **node_options):
        # Before rclpy's Node builds its own parameter services, which come through create_service.
        self.guard = CallbackGuard(None)
        super().__init__(NODE_NAME, **node_options)
        self.guard.logger = self.get_logger()
        self.status = MapperStatus()
        # On simulated time a bag's /clock follows the stamps it plays: an arrival minus its stamp says nothing.
        self.status.odometry_delay_measured = not self.get_parameter("use_sim_time").value
        self.warnings = WarningThrottle(self.get_logger())
        self.label_map = load_label_map("semantic_kitti")
        self.palette = packed_palette(self.label_map.colors)
        settings = read_start_settings(self, self.label_map)
        write_folder = check_map_file_at_start(self)
        start_map = read_map_file_at_start(self)
        self.log_place = scan_log_folder_at_start(self, write_folder)
        # The mapper (torch, compiled kernels) is loaded only once every parameter has passed: a
        # bad one is said at once, not after seconds of loading.
        from convbki_ros.mapping.mapping_thread import MappingCore

        self.core = MappingCore(self, settings, self.status, self.warnings, self.label_map)
        self.files = MapFiles(self, write_folder)
        use_scan_log_folder(self, self.core.mapper, self.log_place)
        self.files.load_at_start(start_map)
        self._warm_up()

        inputs, odometry_group, file_io, housekeeping = (MutuallyExclusiveCallbackGroup() for _ in range(4))
        # Clouds and odometry in groups of their own: a cloud being queued never delays odometry.
        # The reader keeps as many clouds as the queue: DDS may deliver a burst after holding
        # messages back, and a shorter history would drop the oldest of it.
        self.create_subscription(PointCloud2, "cloud_in", self.core.on_cloud,
                                 self._input_qos(self.param("cloud_queue_size")), callback_group=inputs,
                                 event_callbacks=self._count_publishers("cloud_in"))
        if self.core.pose_source == "odometry":  # with poses from TF alone there is no odometry to read
            self.create_subscription(Odometry, "odom", self.core.on_odometry, self._input_qos(ODOMETRY_DEPTH),
                                     callback_group=odometry_group, event_callbacks=self._count_publishers("odom"))
        self.status.uses_odometry = self.core.pose_source == "odometry"
        self.outputs = MapOutputs(self)
        # A SLAM's optimised keyframes: the scans the map holds move where it now says they were.
        self.corrections = CorrectionRunner(self.core, self, self.warnings)
        # Raw: a Path's pose count is checked before it is decoded (max_path_poses).
        self.create_subscription(Path, "pose_corrections", self.corrections.on_path,
                                 QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.VOLATILE), callback_group=housekeeping,
                                 event_callbacks=self._count_publishers("pose_corrections"), raw=True)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "~/save_map", self.files.on_save_map, callback_group=file_io)
        self.create_service(Trigger, "~/load_map", self.files.on_load_map, callback_group=file_io)
        self.create_service(Trigger, "~/export_ply", self.files.on_export_ply, callback_group=file_io)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=housekeeping)
        self.create_service(Trigger, "~/clear_box", self._on_clear_box, callback_group=housekeeping)
        self.create_service(GetMap, "~/get_costmap", self._on_get_costmap, callback_group=file_io)

        # Housekeeping runs on the steady clock: with use_sim_time the ROS clock stops when a bag
        # pauses or ends, and the map must still be published and the counters reported.
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._times_full = 0  # how often the map had filled when last said
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
        # Integers for number parameters at run time, as at start; paths taken inside map_folder.
        self.add_pre_set_parameters_callback(self.guard.parameter_filter(self._prepare_parameters))
        self.add_on_set_parameters_callback(self.guard.parameter_check(self._check_parameters))
        self.add_post_set_parameters_callback(self.guard.call("applying parameters", self._on_parameters_changed))

        self.core.on_integrated = lambda: self.outputs.request("local")
        self.update_thread = threading.Thread(target=self.core.run, name="convbki_update", daemon=True)
        self.update_thread.start()
        self.corrections.start()
        self.outputs.start()
        self.status.ready()
        mapper = self.core.mapper
        self.get_logger().info(
            f"ConvBKI mapper ready: {mapper.kernel.kind} kernel, {mapper.resolution} m voxels, "
            f"f = {mapper.kernel.filter_size}, window {mapper.geometry.dims.tolist()} voxels, "
            f"device {mapper.device}, {self.core.mount_text()}; inputs {self.resolve_topic_name('cloud_in')}"
            + (f" + {self.resolve_topic_name('odom')}" if self.status.uses_odometry else " + TF"))

    def param(self, name: str):
        return self.get_parameter(name).value

    # -- every callback guarded (convbki_ros.guard): no request or message ends the node ------------
    def create_subscription(self, msg_type, topic, callback, *args, **kwargs):
        return super().create_subscription(msg_type, topic, self.guard.call(f"a message on {topic}", callback),
                                           *args, **kwargs)

    def create_service(self, srv_type, srv_name, callback, *args, **kwargs):
        return super().create_service(srv_type, srv_name, self.guard.service(f"service {srv_name}", callback),
                                      *args, **kwargs)

    def create_timer(self, timer_period_sec, callback, *args, **kwargs):
        name = getattr(callback, "__qualname__", "")
        return super().create_timer(timer_period_sec, self.guard.call(f"a timer ({name})", callback), *args, **kwargs)

    def _warm_up(self) -> None:
        """Every kernel mapping and its outputs run was compiled with the mapper; the node's own
        cloud decoder too, before the node subscribes and says ready."""
        points = np.zeros((4, 3), np.float32)
        for fields in ({"label": np.zeros(4, np.uint32)},
                       {f"prob_{c}": np.full(4, 1.0, np.float32) for c in range(self.core.mapper.num_classes)}):
            decode_cloud(encode_cloud(0, "warm_up", {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
                                                     **fields}), self.core.mapper.num_classes)
        note = kernel_cache().note
        if note:
            self.get_logger().warning(note)
        self.get_logger().info(self.core.warm_up_report.line())

    # -- set-up and run-time parameters ---------------------------------------------------
    def declare_all(self, kernel_values: dict[str, object]) -> None:
        """Declare every parameter but ``kernel_file`` (declared first, to read the kernel)."""
        for spec in PARAMETERS:
            if spec.name != "kernel_file":
                declare(self, spec, kernel_values.get(spec.name))

    def _count_publishers(self, name: str) -> SubscriptionEventCallbacks:
        """Event callbacks that keep the count of publishers the reader of input ``name`` has
        matched, reported on /diagnostics (a player can wait for it before its first message)."""
        self.status.publishers_matched(name, 0)
        return SubscriptionEventCallbacks(matched=lambda info: self.status.publishers_matched(name, info.current_count))

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

    def _prepare_parameters(self, parameters) -> list:
        """Integers given for numbers become doubles; a relative map_file or ply_file is taken
        inside map_folder (so ``ros2 param get`` shows the file written)."""
        prepared = []
        for parameter in map(integers_as_doubles, parameters):
            if parameter.name in ("map_file", "ply_file") and isinstance(parameter.value, str) and parameter.value \
                    and not os.path.isabs(parameter.value):
                parameter = Parameter(parameter.name, Parameter.Type.STRING, self.files.folder.resolve(parameter.value))
            prepared.append(parameter)
        return prepared

    def _check_parameters(self, parameters) -> SetParametersResult:
        """Values that pass their type and range but cannot be used are refused with the reason."""
        for parameter in parameters:
            if parameter.name in ("map_file", "ply_file"):
                problem = self.files.check_new_path(parameter.name, parameter.value)
            elif parameter.name == "use_sim_time":  # rclpy's own: else a caller could hand the clock to /clock
                problem = "use_sim_time is read at start only (--ros-args -p use_sim_time:=true)"
            elif parameter.name == "autosave_period" and 0.0 < parameter.value < MIN_AUTOSAVE_PERIOD:
                problem = f"parameter autosave_period: {parameter.value:g} s is too often: 0 (never) or at least " \
                          f"{MIN_AUTOSAVE_PERIOD:g} s"
            elif parameter.name in ("clear_box_min", "clear_box_max"):
                problem = check_box(parameter.name, parameter.value)
            elif parameter.name == "correction_min_move":
                problem = min_move_problem(parameter.value)
            elif parameter.name in SPECS and SPECS[parameter.name].choices:
                problem = choice_problem(parameter.name, parameter.value)
            else:
                continue
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def _on_parameters_changed(self, parameters) -> None:
        for parameter in parameters:
            if parameter.name in self._timer_callbacks:
                self._restart_timer(parameter.name)
            elif parameter.name == "max_pose_jump":
                self.core.set_max_pose_jump(parameter.value)
            elif parameter.name == "transform_timeout":
                self.core.queue.transform_timeout = parameter.value
            elif parameter.name == "map_file":
                self.files.path_changed()
            if parameter.name == "max_variance":  # the shown map changes as a whole
                self.outputs.map_replaced(refresh_updates=True)
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
        memory = self.core.mapper.memory_state()
        for extra in (self.files.health(), self._memory_health(memory)):
            if extra is not None:
                extra_level, extra_message = extra
                message = extra_message if level == OK else f"{message}; {extra_message}"
                level = max(level, extra_level)
        status = DiagnosticStatus(level=LEVELS[level], name=f"{self.get_fully_qualified_name()}: mapping",
                                  message=message, hardware_id=self.core.frame,
                                  values=[KeyValue(key=k, value=v) for k, v in diagnostic_values(snapshot)])
        status.values.append(KeyValue(key="last_save", value=self.files.last_save or ""))
        status.values.append(KeyValue(key="queue_limit", value=str(self.param("cloud_queue_size"))))
        status.values.extend(KeyValue(key=k, value=v) for k, v in self.corrections.diagnostic_values())
        status.values.extend(KeyValue(key=k, value=str(v)) for k, v in self._guard_values() + memory_values(memory))
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)

    def _memory_health(self, memory) -> tuple[int, str] | None:
        """WARN while the map is full (``memory``: its ``MemoryState``, against max_map_megabytes):
        it stops growing; said once in the log each time it fills."""
        self._times_full = min(self._times_full, memory.times_full)  # a reset starts the count again
        if memory.times_full > self._times_full:
            self._times_full = memory.times_full
            self.get_logger().warning(
                f"the map is full: {(memory.store_bytes + memory.lent_bytes) / 1e6:.0f} MB of voxels reached "
                f"max_map_megabytes = {memory.budget_bytes / 1e6:g}; it stops growing (new ground that leaves the "
                "window is forgotten) while mapping goes on in the window")
        if not memory.full:
            return None
        return WARN, (f"map full (max_map_megabytes {memory.budget_bytes / 1e6:g}): {memory.voxels_dropped} voxels of "
                      "new ground forgotten")

    def _guard_values(self) -> list[tuple[str, object]]:
        """What no input may exceed: failed callbacks, refused transforms, the folder files go to."""
        errors = self.guard.errors
        listener = getattr(self.core.tf, "listener", None)
        return [("callback_errors", errors.count), ("callback_last_error", errors.last),
                ("tf_refused", listener.skipped if listener is not None else 0),
                ("map_folder", self.files.folder.describe())]

    # -- services -----------------------------------------------------------------------------
    def _on_reset(self, request, response):
        forgotten = self.core.reset_map("~/reset")
        self.outputs.map_replaced()
        response.success, response.message = True, f"map reset: forgot {forgotten} voxels{self._file_kept()}"
        self.get_logger().info(response.message)
        return response

    async def _on_get_costmap(self, request, response):
        """The whole map's costmap (nav_msgs/OccupancyGrid), computed on the file thread; an empty
        grid and one warning when it would have more than costmap_max_cells cells."""
        response.map = await self.files.on_file_thread(self._whole_costmap)
        return response

    def _whole_costmap(self):
        from convbki_ros.outputs.costmap import occupancy_grid, whole_grid

        indices, alpha, _ = self.core.map_copy()
        mapper, frame = self.core.mapper, self.core.frame
        if len(indices):
            span = indices[:, :2].max(axis=0) - indices[:, :2].min(axis=0) + 1
            cells, limit = int(span[0]) * int(span[1]), self.param("costmap_max_cells")
            if cells > limit:
                self.get_logger().warning(f"~/get_costmap: the whole map's grid would have {cells} cells "
                                          f"({span[0]} x {span[1]}), more than costmap_max_cells = {limit}: "
                                          "answered an empty grid; raise costmap_max_cells, or use "
                                          "semantic_map/costmap around the robot")
                indices, alpha = indices[:0], alpha[:0]
        grid = whole_grid(indices, alpha, mapper.resolution, mapper.prior, self.core.costmap_profile)
        return occupancy_grid(grid, self.get_clock().now().nanoseconds, frame)

    def _on_clear_box(self, request, response):
        box = [optional(self, name) for name in ("clear_box_min", "clear_box_max")]
        box = [None if corner is None else [float(v) for v in corner] for corner in box]
        problem = "set clear_box_min and clear_box_max" if None in box else \
            check_box("clear_box_min", box[0]) or check_box("clear_box_max", box[1])
        if not problem and not all(low <= high for low, high in zip(*box)):
            problem = f"clear_box_min {box[0]} is not below clear_box_max {box[1]} on every axis"
        if problem:
            response.success = False
            response.message = f"{problem} (x, y, z in the map frame '{self.core.frame}', m) first"
            self.get_logger().warning(response.message)
            return response
        forgotten = self.core.clear_box(*box)
        if forgotten:
            self.outputs.map_replaced()
        response.success = True
        response.message = (f"forgot {forgotten} voxels in the box {box[0]} .. {box[1]} (frame '{self.core.frame}')"
                            f"{self._file_kept() if forgotten else ''}")
        self.get_logger().info(response.message)
        return response

    def _file_kept(self) -> str:
        if not self.files.file_may_hold_more():
            return ""
        return f"; {self.param('map_file')} keeps the map as it was until ~/save_map writes this one there"

    # -- shutdown -----------------------------------------------------------------------------
    def stop(self) -> bool:
        """Stop the threads (the scan in progress finishes) and save when asked to; False when
        that save failed (the map of this session is then not on disk)."""
        self.core.stop()
        self.corrections.stop()  # a correction under way stops before its next scan: the thread is joined
        self.outputs.stop()
        self.update_thread.join(timeout=1.5)
        self.files.close()
        saved, message = self.files.save_on_shutdown()
        close_scan_log_folder(self.core.mapper, self.log_place)  # after the save: the files it names stay
        if message:
            what = "on shutdown" if saved else "error on shutdown"
            print(f"[{NODE_NAME}] {what}: {message}", file=sys.stderr)
        return saved




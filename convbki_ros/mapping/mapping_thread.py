"""The node's mapping side: inputs in, the map updated, on its own thread.

``MappingCore`` builds the ``ConvBKIMapper`` from the node's checked start-up settings
(``settings``), takes clouds and odometry from the executor (cheap checks only: a cloud that
can never be used is refused on arrival, before it waits or fills the queue), and runs the
update thread, which places each cloud at its sensor pose (odometry interpolated at the
cloud's stamp, times the sensor's mount) and integrates it. Bad input never touches the map:
every rejection is counted and warned about once per problem (throttled).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_core.io.map_file import MapSetupError, SetupDifference, read_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.warm_up import WarmUpReport, warm_up
from convbki_ros.inputs.cloud_decoding import CloudError, decode_cloud
from convbki_ros.inputs.pose_buffer import PoseStatus, pose_problem
from convbki_ros.inputs.sync import NO_MAP_TRANSFORM, CloudQueue, Decision, Missing, PendingCloud, SensorFrames, Verdict
from convbki_ros.inputs.tf_buffer import make_tf_lookup
from convbki_ros.inputs.transforms import seconds_to_ns, stamp_to_ns
from convbki_ros.outputs.costmap import rolling_grid
from convbki_ros.outputs.status import problem_key
from convbki_ros.params import StartupError
from convbki_ros.settings import StartSettings

NO_POSE_REASONS = {
    PoseStatus.EMPTY: "no odometry received yet",
    PoseStatus.TOO_OLD: "the cloud is older than the odometry kept",
    PoseStatus.JUMP: "the odometry jumped between the poses around its stamp",
    PoseStatus.OUTAGE: "it was taken during an outage of the odometry",
}
DROP_REASONS = {PoseStatus.JUMP: "pose jump", PoseStatus.OUTAGE: "odometry outage"}
TF_CACHE_S = 60.0  # seconds of TF kept: clouds may wait in the queue that long behind the newest


class MappingCore:
    """Inputs, the cloud queue, the update thread and the map, for ``MapperNode``."""

    def __init__(self, node, settings: StartSettings, status, warnings, label_map):
        self.node, self.status, self.warnings, self.label_map = node, status, warnings, label_map
        self.pose_source = settings.pose_source
        # TF is read (tf2_ros where a ROS 2 install has it, else the package's own buffer) unless
        # nothing can need it: the odometry's own frame and a fixed mount.
        self.tf, self.tf_missing = make_tf_lookup(node, TF_CACHE_S)
        self.frames = SensorFrames(settings.mount, self.tf, settings.map_frame)
        if self.tf is None and self.pose_source == "tf":
            raise StartupError(f"pose_source tf needs TF, which cannot be read here: {self.tf_missing}")
        if self.tf is None:
            node.get_logger().warning(f"TF is not read: {self.tf_missing}")
        # Every kernel is compiled (or loaded) while the map's window is allocated and filled.
        with ThreadPoolExecutor(max_workers=1) as pool:
            warming = pool.submit(warm_up, settings.mapper, settings.kernel)
            self.mapper = ConvBKIMapper(settings.mapper, settings.kernel)
            self.warm_up_report: WarmUpReport = warming.result()
        self.queue = CloudQueue(max_pose_jump=node.param("max_pose_jump"), placer=self._place,
                                locate=self._locate_by_tf if self.pose_source == "tf" else None)
        self.queue.transform_timeout = node.param("transform_timeout")
        self.costmap_profile = settings.costmap_profile
        self.map_lock = threading.Lock()
        self.map_version = 0  # bumped by every change of the map
        # Bumped whenever the map loses evidence (a reset, a forgotten box) or is replaced by a load:
        # a map file saved before then may hold what the map no longer does.
        self.lineage = 0
        self.forgotten_by: str | None = None  # what last made the map lose evidence, for the user
        self.newest_odometry_stamp: int | None = None  # ns, of accepted odometry
        self.odometry_frame: str | None = None
        self.last_stamp = None  # header stamp of the last integrated cloud
        self.position = np.zeros(3)  # the sensor's position in the map at the last integrated cloud
        self.on_integrated = lambda: None  # set by the node: the local window may be published

    @property
    def stopping(self) -> bool:
        return self.queue.stopping

    # -- set-up ----------------------------------------------------------------------------
    def mount_text(self) -> str:
        """The pose source, in words, for the start-up line."""
        if self.pose_source == "tf":
            return f"poses from TF ('{self.frames.map_frame}' -> each cloud's frame)"
        if self.frames.fixed is not None:
            mount = "sensor mount from base_to_sensor"
        else:
            mount = "sensor mount from TF" if self.tf is not None else "clouds in the odometry's child frame"
        if self.frames.map_frame and self.tf is not None:
            mount += f", map in '{self.frames.map_frame}' through TF where the odometry's frame differs"
        return f"poses from odometry, {mount}"

    def _place(self, pending: PendingCloud, lookup) -> tuple[np.ndarray | None, Missing | None]:
        """The cloud frame's pose in the map, from its odometry (the queue asks, lock held)."""
        return self.frames.place(self.odometry_frame or "", lookup, pending.msg.header.frame_id,
                                 stamp_to_ns(pending.msg.header.stamp))

    def _locate_by_tf(self, pending: PendingCloud):
        return self.frames.locate(pending.msg.header.frame_id, stamp_to_ns(pending.msg.header.stamp))

    def set_max_pose_jump(self, metres: float) -> None:
        with self.queue.changed:
            self.queue.poses.max_jump = float(metres)

    @property
    def frame(self) -> str:
        """The frame the map is built and published in: map_frame where TF takes the clouds
        into it, else the odometry's, once known."""
        if self.frames.map_frame and (self.tf is not None or self.pose_source == "tf"):
            return self.frames.map_frame
        return self.odometry_frame or self.mapper.frame_id

    # -- inputs (executor thread: cheap, no maths) -------------------------------------------
    def on_cloud(self, msg) -> None:
        self.status.cloud_received()
        stamp = stamp_to_ns(msg.header.stamp)
        points = int(msg.width) * int(msg.height)
        limit = int(self.node.param("max_points_per_cloud"))
        if limit and points > limit:
            self.status.drop("too large")
            self.warnings.warn("too large", f"dropping cloud stamped {stamp / 1e9:.3f} s: {points} points "
                               f"({len(msg.data) / 1e6:.0f} MB), more than max_points_per_cloud = {limit}")
            return
        if points == 0:
            self.status.drop("empty")
            self.warnings.warn("empty", f"dropping empty cloud stamped {stamp / 1e9:.3f} s "
                               f"(width {msg.width} x height {msg.height})")
            return
        queue_limit = int(self.node.param("cloud_queue_size"))
        megabytes = self.node.param("cloud_queue_megabytes")
        evicted = self.queue.push(msg, queue_limit, int(megabytes * 1e6), self.clock_ns())
        self.status.queued(len(self.queue))
        if not evicted:
            return
        full = f"update queue full ({len(self.queue)} clouds, {self.queue.bytes / 1e6:.0f} MB; cloud_queue_size " \
               f"{queue_limit}, cloud_queue_megabytes {megabytes:g})"
        if evicted.waiting_for_pose:
            self.status.drop("no pose", evicted.waiting_for_pose)
            latest = self.queue.poses.latest_stamp
            self.warnings.warn("queue no pose", f"{full}: dropping the oldest cloud, still waiting for odometry "
                               "covering its stamp (latest odometry "
                               f"{'none' if latest is None else f'{latest / 1e9:.3f} s'})")
        if evicted.ready:
            self.status.drop("queue full", evicted.ready)
            self.warnings.warn("queue", f"{full}: dropping the oldest cloud; the map update is slower than the "
                               "input rate")

    def clock_ns(self) -> int:
        """The node's clock (ROS time: the data's time under use_sim_time), in nanoseconds."""
        return self.node.get_clock().now().nanoseconds

    def on_odometry(self, msg) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
        translation = [position.x, position.y, position.z]
        quaternion = [orientation.x, orientation.y, orientation.z, orientation.w]
        problem = pose_problem(translation, quaternion)
        self.status.odometry_received(usable=problem is None)
        if problem:
            self.warnings.warn("odometry " + problem_key(problem),
                               f"ignoring odometry stamped {stamp / 1e9:.3f} s: {problem}")
            return
        self.status.odometry_delay(self.clock_ns() - stamp)
        self._note_odometry_frame(msg.header.frame_id)
        self._check_time_going_backwards(stamp)
        found, previous = self.queue.add_odometry(stamp, pose_from_translation_quaternion(translation, quaternion),
                                                  msg.child_frame_id)
        if found is None:
            return
        limit = f"max_pose_jump = {self.node.param('max_pose_jump')} m"
        after = "out of order" if previous is None or previous > stamp else f"after {previous / 1e9:.3f} s"
        if found.outage:
            # Odometry that stopped and resumed is the same odometry: the robot moved on meanwhile.
            self.warnings.warn("outage", f"odometry outage of {found.gap_s:.1f} s (none stamped between "
                               f"{(stamp - found.gap_s * 1e9) / 1e9:.3f} s and {stamp / 1e9:.3f} s); the pose after "
                               f"it is {found.distance:.2f} m away ({limit}): map kept; clouds stamped in the "
                               "outage are dropped")
            return
        action = self.on_pose_jump(stamp)
        text = f"odometry jumped {found.distance:.2f} m in {found.gap_s:.2f} s at {stamp / 1e9:.3f} s ({after}; " \
               f"{limit}): {action}"
        if self.node.param("on_pose_jump") == "keep":
            self.warnings.warn("jump", text)
        else:  # the map was reset or a file started: every one is said
            self.node.get_logger().warning(text)

    def on_pose_jump(self, stamp: int) -> str:
        """Apply parameter on_pose_jump to a jump at ``stamp``; what was done, in words."""
        choice = self.node.param("on_pose_jump")
        where = f"the pose jump at {stamp / 1e9:.3f} s"
        if choice == "new_file" and not self.node.files.path:
            return "map kept, as map_file is empty (on_pose_jump new_file needs it); clouds stamped inside the " \
                   "jump are dropped"
        if choice == "keep":
            return "map kept (on_pose_jump keep): the scans after it are added where the odometry now says; " \
                   "clouds stamped inside the jump are dropped"
        self.queue.forget_odometry(before=stamp)  # the new map starts at the new pose
        if choice == "new_file":
            return f"{self.node.files.start_new_segment(where)} (on_pose_jump new_file)"
        self.reset_map(f"a reset on {where}")
        return "map reset (on_pose_jump reset): a new map starts at the new pose"

    def _note_odometry_frame(self, frame: str) -> None:
        """The first odometry names its frame: the map's, unless map_frame names another that TF
        connects it to. Without TF a different map_frame cannot be honoured, so it is said once
        and not used."""
        if not frame or frame == self.odometry_frame:
            return
        wanted = self.frames.map_frame
        if self.odometry_frame is not None:
            self.node.get_logger().warning(f"the odometry's frame changed from '{self.odometry_frame}' to "
                                           f"'{frame}'; the map stays in '{self.frame}'")
            return
        through_tf = bool(wanted) and wanted != frame and self.tf is not None
        self.odometry_frame = frame
        with self.map_lock:
            loaded_frame = self.mapper.frame_id if len(self.mapper) else None
            self.mapper.frame_id = self.frame
        if through_tf:
            self.node.get_logger().info(f"the odometry is in '{frame}', the map in map_frame '{wanted}': each cloud "
                                        f"goes through TF '{wanted}' -> '{frame}' at its stamp")
        elif wanted and wanted != frame:
            self.node.get_logger().warning(
                f"map_frame is '{wanted}' but the odometry is in '{frame}': the map is built and published in "
                f"'{frame}' (no transform between the two is applied: {self.tf_missing}); set map_frame to '' or "
                f"'{frame}'")
        if loaded_frame and loaded_frame != self.frame:
            self.node.get_logger().warning(f"the map loaded at start was built in '{loaded_frame}'; this node maps "
                                           f"in '{self.frame}': the new scans are added as if they were the same")

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
        if newest - stamp <= seconds_to_ns(self.node.param("stamp_backwards_tolerance")):
            return
        self.newest_odometry_stamp = stamp
        stale = self.queue.forget_odometry()
        self.status.drop("time reset", stale)
        reset = self.node.param("reset_on_stamp_backwards")
        if reset:
            self.reset_map(f"a reset when time went back at {stamp / 1e9:.3f} s")
        self.warnings.warn("time", f"time went backwards by {(newest - stamp) / 1e9:.3f} s (odometry stamped "
                           f"{stamp / 1e9:.3f} s after input stamped {newest / 1e9:.3f} s; a restarted bag?): "
                           f"odometry history cleared, {stale} waiting clouds dropped, "
                           f"{'map reset (reset_on_stamp_backwards)' if reset else 'map kept'}")

    def watch_odometry(self) -> None:
        """Warn every odometry_timeout seconds while clouds come in and odometry does not."""
        timeout = self.node.param("odometry_timeout")
        missing = self.status.odometry_missing(timeout)
        if missing is None:
            return
        what, since = missing
        topics = self.node.resolve_topic_name("odom"), self.node.resolve_topic_name("cloud_in")
        self.warnings.warn("no odometry", f"{what} on {topics[0]} for {since:.1f} s while clouds arrive on "
                           f"{topics[1]}: clouds cannot be placed (check the odom remapping, its QoS and its "
                           "publisher)", period=timeout)

    def reset_map(self, why: str) -> int:
        """Clear the map; clouds received before now are stale (their poses may be too). Returns
        how many voxels it forgot; ``why`` says what asked for it (for the user)."""
        return self.take_and_reset(why)[0]

    def take_and_reset(self, why: str, keep: bool = False):
        """``reset_map``, returning (voxels forgotten, a snapshot of the map before, when ``keep``):
        both under one hold of the lock, so no scan falls between the two."""
        self.queue.new_generation()
        with self.map_lock:
            forgotten = len(self.mapper)
            snapshot = self.mapper.snapshot() if keep else None
            self.mapper.reset()
            self._lost_evidence(why)
        return forgotten, snapshot

    def clear_box(self, box_min, box_max) -> int:
        """Forget the voxels whose centres lie in the box (map frame, m); returns how many."""
        with self.map_lock:
            forgotten = len(self.mapper.forget_box(box_min, box_max))
            if forgotten:
                self._lost_evidence("~/clear_box")
        return forgotten

    def load_map(self, path: str, contents: tuple | None = None) -> tuple[int, int]:
        """Replace the map with a map file's; (voxels loaded, voxels replaced). The file is read
        (unless its ``read_map`` ``contents`` are given) and checked without the lock (mapping
        goes on meanwhile): ``MapFileError`` when it cannot be read or was built for another
        grid, classes, prior or frame, and the map is untouched."""
        metadata, indices, alpha = contents if contents is not None else read_map(path, with_scan_log=True)
        self.mapper.check_compatible(path, metadata)
        frame = metadata.get("frame_id") or None
        known = (self.frame if self.odometry_frame or self.frames.map_frame else None) or None
        if frame and known and frame != known:
            raise MapSetupError(f"{path}: the map was built in frame '{frame}', this node maps in '{known}'",
                                [SetupDifference("frame_id", frame, known)])
        with self.map_lock:
            replaced = len(self.mapper)
            self.mapper.replace_with(metadata, indices, alpha)
            if frame and not known:
                self.mapper.frame_id = frame
            if self.mapper.sensor_position is not None:
                self.position = self.mapper.sensor_position.copy()
            self._lost_evidence(f"~/load_map of {path}" if replaced else None)
        return len(indices), replaced

    def replace_mapper(self, mapper) -> None:
        """Put ``mapper`` in the place of the map (a correction's; call with the map lock held)."""
        self.mapper = mapper
        self.map_version += 1

    def _lost_evidence(self, why: str | None) -> None:
        """The map changed other than by adding evidence (call with the map lock held)."""
        self.map_version += 1
        self.lineage += 1
        if why:
            self.forgotten_by = why

    # -- the update thread ---------------------------------------------------------------------
    def run(self) -> None:
        """Integrate queued clouds as their poses become known, until ``stop()``."""
        while True:
            name = "transform_timeout" if self.pose_source == "tf" else "pose_wait_timeout"
            decision = self.queue.next(lambda name=name: self.node.param(name), self.clock_ns)
            if decision is None:
                return
            try:
                self._integrate(decision)
            except Exception as error:  # never let one scan stop the mapping thread
                self.status.drop("error")
                self.node.get_logger().error(f"scan not integrated: {error.__class__.__name__}: {error}")

    def stop(self) -> None:
        self.queue.stop()

    def _integrate(self, decision: Decision) -> None:
        msg, lookup = decision.pending.msg, decision.lookup
        if decision.verdict is Verdict.STALE:
            self.status.drop("map reset")
            self.warnings.warn("stale", "dropping a cloud received before the map was reset")
            return
        if decision.verdict is Verdict.NO_POSE:
            self._no_pose(msg, lookup)
            return
        if decision.verdict is Verdict.NO_TRANSFORM:
            missing = decision.missing or Missing(NO_MAP_TRANSFORM, "")
            self.status.drop(missing.reason)
            self.warnings.warn("transform " + problem_key(missing.detail),
                               f"dropping cloud stamped {stamp_to_ns(msg.header.stamp) / 1e9:.3f} s in frame "
                               f"'{msg.header.frame_id}' after waiting transform_timeout = "
                               f"{self.queue.transform_timeout:g} s ({missing.reason}): {missing.detail}")
            return
        sensor_pose = decision.pose
        try:
            cloud = decode_cloud(msg, self.mapper.num_classes)
        except CloudError as error:
            self.status.drop("bad cloud")
            self.warnings.warn("cloud " + problem_key(str(error)), f"dropping cloud: {error}")
            return
        if not len(cloud):
            self.status.drop("no usable points")
            text = cloud.bad_points_text()
            self.warnings.warn("no usable " + problem_key(text), f"dropping cloud: no usable point ({text})")
            return
        if cloud.dropped:
            self.warnings.warn("bad points " + problem_key(cloud.bad_points_text()),
                               f"{cloud.bad_points_text()}; the rest are integrated")
        values, moving = cloud.probabilities, None
        if values is None:
            values = self._learning_labels(cloud.labels)
            if values is None:
                self.status.drop("unknown labels")
                return
            if self.node.param("label_space") == "raw" and self.node.param("moving_labels"):
                moving = self.label_map.is_moving(cloud.labels)
                moving = moving if moving.any() else None
        with self.map_lock:
            if decision.pending.generation != self.queue.generation:  # a reset came while it was decoded
                self.status.drop("map reset")
                return
            result = self.mapper.integrate(cloud.points, values, sensor_pose, moving,
                                           stamp_ns=stamp_to_ns(msg.header.stamp), mount=self._mount(decision))
            self.map_version += 1
            self.last_stamp = msg.header.stamp
            self.position = sensor_pose[:3, 3]
        self.status.integrated_one(result.timing_ms["total"])
        self.on_integrated()

    def _mount(self, decision: Decision) -> np.ndarray | None:
        """The cloud frame's pose on the body whose poses a SLAM corrects (the odometry's child
        frame), for the scan log; None (the cloud's own frame) with poses from TF."""
        lookup = decision.lookup
        if self.pose_source == "tf" or lookup is None:
            return None
        mount, _ = self.frames.mount(lookup.child_frame_id, decision.pending.msg.header.frame_id,
                                     stamp_to_ns(decision.pending.msg.header.stamp))
        return mount

    def _no_pose(self, msg, lookup) -> None:
        status = lookup.status
        reason = lookup.reason or NO_POSE_REASONS.get(status) or \
            f"no odometry covered its stamp within pose_wait_timeout = {self.node.param('pose_wait_timeout')} s"
        self.status.drop(DROP_REASONS.get(status, "no pose"))
        latest = self.queue.poses.latest_stamp
        latest_text = f"; latest odometry {latest / 1e9:.3f} s" if latest is not None else ""
        self.warnings.warn(f"pose {status.value}", f"dropping cloud stamped {stamp_to_ns(msg.header.stamp) / 1e9:.3f}"
                           f" s: {reason}{latest_text}")

    def _learning_labels(self, labels: np.ndarray) -> np.ndarray | None:
        """The cloud's labels as learning ids; unknown ids are warned about and become ignored
        class 0. None (and a warning) when no label is known: the cloud would add nothing, and
        such a cloud usually means a wrong label_space."""
        space = self.node.param("label_space")
        num_classes = self.mapper.num_classes
        unknown = self.label_map.unknown_raw(labels) if space == "raw" else (labels < 0) | (labels >= num_classes)
        count = int(np.count_nonzero(unknown))
        if count:
            examples = ", ".join(str(v) for v in np.unique(labels[unknown])[:5])
            known = f"{self.label_map.name} label map" if space == "raw" else f"learning ids 0..{num_classes - 1}"
            if count == labels.size:
                self.warnings.warn("all unknown", f"dropping cloud: all {count} label ids are unknown to the "
                                   f"{known} (e.g. {examples}); is label_space ({space}) right?")
                return None
            self.warnings.warn("unknown", f"{count} of {labels.size} points carry label ids unknown to the "
                               f"{known} (e.g. {examples}); they are ignored")
        return self.label_map.to_learning(labels) if space == "raw" else np.where(unknown, 0, labels)

    # -- what the outputs show (taken under the lock, encoded and sent without it) ------------
    def take_changes(self, everything: bool = False):
        """``MapChanges`` since the last call (``everything``: every voxel of the map)."""
        with self.map_lock:
            return self.mapper.take_changes(everything)

    def take_change_records(self, palette: np.ndarray, everything: bool = False):
        """(removed, changed voxels' indices, their records) since the last take (``everything``:
        every voxel of the map); the records made where the map lives."""
        with self.map_lock:
            return self.mapper.take_change_records(palette, everything)

    def map_copy(self):
        """(indices, alpha, map_version) of the whole map."""
        with self.map_lock:
            indices, alpha = self.mapper.items()
            return indices, alpha, self.map_version

    def rolling_costmap(self, size: float, window_extent: float):
        """(map_version, the planner's rolling grid around the sensor), from the window in place."""
        with self.map_lock:
            mapper = self.mapper
            grid = rolling_grid(mapper.window, mapper.resolution, mapper.prior, self.costmap_profile, self.position,
                                size, window_extent)
            return self.map_version, grid

    def window_records(self, palette: np.ndarray):
        """(map_version, the sensor's position (x, y, z) in the map, records of the window's voxels)."""
        with self.map_lock:
            return self.map_version, self.position.copy(), self.mapper.window_records(palette)

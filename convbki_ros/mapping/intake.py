"""The mapping side's inputs, on the executor thread: clouds and odometry taken in with cheap
checks only (no maths). A cloud that can never be used is refused on arrival, before it waits or
fills the queue; odometry that passed its checks goes to the pose history, and a pose jump, an
outage or time going backwards is acted on (``on_pose_jump``, ``reset_on_stamp_backwards``) and
said. Every rejection is counted and warned about once per problem (throttled).
"""

from __future__ import annotations

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_ros.inputs.pose_buffer import pose_problem
from convbki_ros.inputs.tf_buffer import MAX_FRAME_ID_LENGTH
from convbki_ros.inputs.transforms import seconds_to_ns, stamp_to_ns
from convbki_ros.outputs.status import problem_key


def frame_id_problem(*frame_ids: str) -> str | None:
    """Why a message's frame ids cannot be used (None when they can): longer than TF keeps."""
    for frame in frame_ids:
        if len(frame) > MAX_FRAME_ID_LENGTH:
            return f"a frame id of {len(frame)} characters, more than {MAX_FRAME_ID_LENGTH}"
    return None


class InputIntake:
    """``MappingCore``'s executor-thread side (a part of it: it uses the core's node, status,
    warnings, queue, frames and map, and its ``reset_map``)."""

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
        problem = self._size_problem(msg, points)
        frame_problem = frame_id_problem(msg.header.frame_id) if problem is None else None
        if frame_problem:
            problem = "bad cloud", frame_problem
        if problem:
            reason, text = problem
            self.status.drop(reason)
            self.warnings.warn(reason + " " + problem_key(text), f"dropping cloud stamped {stamp / 1e9:.3f} s: {text}")
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

    def _size_problem(self, msg, points: int) -> tuple[str, str] | None:
        """(drop reason, words) for a cloud whose data is over max_cloud_megabytes or disagrees with
        its header (height rows of row_step bytes, each holding width points of point_step bytes),
        checked before it is queued: a header claiming one point may carry gigabytes."""
        size = len(msg.data)
        limit = self.node.param("max_cloud_megabytes")
        if size > limit * 1e6:
            return "too large", f"{size / 1e6:.1f} MB of data, more than max_cloud_megabytes = {limit:g}"
        height, row_step = int(msg.height), int(msg.row_step)
        if points and row_step < int(msg.width) * int(msg.point_step):
            return "bad cloud", (f"row_step {row_step} is smaller than width * point_step = {msg.width} * "
                                 f"{msg.point_step}")
        if size != height * row_step:
            return "bad cloud", (f"its data is {size} bytes, {'more' if size > height * row_step else 'fewer'} than "
                                 f"its header says: height * row_step = {height} * {row_step} = {height * row_step}")
        return None

    def clock_ns(self) -> int:
        """The node's clock (ROS time: the data's time under use_sim_time), in nanoseconds."""
        return self.node.get_clock().now().nanoseconds

    def on_odometry(self, msg) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
        translation = [position.x, position.y, position.z]
        quaternion = [orientation.x, orientation.y, orientation.z, orientation.w]
        problem = pose_problem(translation, quaternion) or frame_id_problem(msg.header.frame_id, msg.child_frame_id)
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

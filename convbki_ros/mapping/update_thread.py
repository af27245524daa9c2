"""The mapping side's update thread: each queued cloud, once its pose is known (or given up),
decoded, its labels checked against the label map, and integrated into the map under the map
lock at its sensor pose; a cloud that cannot be placed or used is dropped, counted and warned
about once per problem (throttled), and never touches the map.
"""

from __future__ import annotations

import numpy as np

from convbki_ros.inputs.cloud_decoding import CloudError, decode_cloud
from convbki_ros.inputs.pose_buffer import PoseStatus
from convbki_ros.inputs.sync import NO_MAP_TRANSFORM, Decision, Missing, Verdict
from convbki_ros.inputs.transforms import stamp_to_ns
from convbki_ros.outputs.status import problem_key

NO_POSE_REASONS = {
    PoseStatus.EMPTY: "no odometry received yet",
    PoseStatus.TOO_OLD: "the cloud is older than the odometry kept",
    PoseStatus.JUMP: "the odometry jumped between the poses around its stamp",
    PoseStatus.OUTAGE: "it was taken during an outage of the odometry",
}
DROP_REASONS = {PoseStatus.JUMP: "pose jump", PoseStatus.OUTAGE: "odometry outage"}


class ScanIntegration:
    """``MappingCore``'s update thread (a part of it: it uses the core's node, status, warnings,
    queue, frames, label map and map, under the core's map lock)."""

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
            finally:
                self.queue.finished()

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

"""Clouds waiting for their pose: the bounded queue, the odometry lookup and the sensor mount.

A cloud is placed with the odometry interpolated at its stamp (``pose_buffer``). On a real
robot the odometry is the pose of ``base_link`` (its ``child_frame_id``) in ``odom`` while
the LiDAR publishes in its own frame, mounted on the base by a static transform; the
sensor's pose is then odometry x mount. The mount comes from the ``base_to_sensor``
parameter, or from TF (``/tf_static``) where tf2_ros is installed.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from enum import Enum

import numpy as np

from convbki_ros.pose_buffer import OdometryBuffer, PoseBreak, PoseLookup, PoseStatus
from convbki_ros.transforms import stamp_to_ns, transform_to_pose


@dataclass
class PendingCloud:
    """A received cloud on its way to the map."""

    msg: object
    generation: int = 0  # the map generation it was received in; a reset makes it stale
    received_clock_ns: int = 0  # the node's clock at reception (the data's time under use_sim_time)

    @property
    def nbytes(self) -> int:
        return len(self.msg.data)


class Verdict(Enum):
    PLACE = "place"  # its pose is known
    STALE = "stale"  # received before a map reset
    NO_POSE = "no pose"  # waited pose_wait_timeout, or can never be placed


@dataclass
class Decision:
    pending: PendingCloud
    verdict: Verdict
    lookup: PoseLookup | None = None


@dataclass
class Evicted:
    """Clouds pushed out of a full queue: those still waiting for odometry, and those not."""

    waiting_for_pose: int = 0
    ready: int = 0

    def __bool__(self) -> bool:
        return bool(self.waiting_for_pose or self.ready)


class CloudQueue:
    """Clouds waiting to be integrated, oldest first, at most ``limit`` clouds and ``byte_limit``
    bytes; the odometry history.

    One condition guards both: a cloud becomes ready when odometry arrives. A cloud whose
    odometry has not arrived does not hold up the clouds behind it: the update is a sum, so
    the order of integration does not change the map. How long a cloud may wait for its
    odometry is bounded by the queue (room for the clouds behind it), and optionally by a time
    in the node's clock, so a source that pauses (and the odometry with it) loses nothing.
    """

    def __init__(self, max_pose_jump: float):
        self.changed = threading.Condition()
        self.clouds: deque[PendingCloud] = deque()
        self.bytes = 0
        self.poses = OdometryBuffer(max_jump=max_pose_jump)
        self.generation = 0  # bumped by every map reset
        self.stopping = False

    def push(self, msg, limit: int, byte_limit: int = 0, clock_ns: int = 0) -> Evicted:
        """Queue ``msg`` (``clock_ns``: the node's clock now); the oldest clouds are pushed out
        until it fits in ``limit`` clouds and ``byte_limit`` bytes (0: no byte limit)."""
        pending = PendingCloud(msg, self.generation, clock_ns)
        with self.changed:
            evicted = Evicted()
            while self.clouds and (len(self.clouds) >= max(1, limit) or
                                   (byte_limit and self.bytes + pending.nbytes > byte_limit)):
                if self._waiting(self._take(0)):
                    evicted.waiting_for_pose += 1
                else:
                    evicted.ready += 1
            self.clouds.append(pending)
            self.bytes += pending.nbytes
            self.changed.notify_all()
            return evicted

    def __len__(self) -> int:
        with self.changed:
            return len(self.clouds)

    def waiting_for_pose(self) -> int:
        """Queued clouds whose odometry has not come yet."""
        with self.changed:
            return sum(self._waiting(pending) for pending in self.clouds)

    def _lookup(self, pending: PendingCloud) -> PoseLookup:
        return self.poses.lookup(stamp_to_ns(pending.msg.header.stamp))

    def _waiting(self, pending: PendingCloud, lookup: PoseLookup | None = None) -> bool:
        """Whether the odometry covering ``pending``'s stamp may still come."""
        return (lookup or self._lookup(pending)).status in (PoseStatus.WAIT, PoseStatus.EMPTY)

    def _take(self, position: int) -> PendingCloud:
        """Remove the cloud at ``position`` from the queue (lock held)."""
        pending = self.clouds[position]
        del self.clouds[position]
        self.bytes -= pending.nbytes
        return pending

    def next(self, pose_wait_timeout: float, clock_ns=lambda: 0) -> Decision | None:
        """Block until a cloud can be decided (or ``stop()``); None when stopping.

        ``pose_wait_timeout``: seconds of the node's clock (``clock_ns()``) a cloud may wait for
        its odometry; 0 = as long as the queue has room for it.
        """
        with self.changed:
            while not self.stopping:
                decision = self._decide(pose_wait_timeout, clock_ns)
                if decision is not None:
                    return decision
                # Nothing queued: sleep until something arrives. Clouds waiting for odometry:
                # wake up in time for the first one's timeout too.
                self.changed.wait(0.5 if not self.clouds or not pose_wait_timeout else 0.02)
            return None

    def _decide(self, timeout: float, clock_ns) -> Decision | None:
        now = clock_ns() if timeout else 0
        for position, pending in enumerate(self.clouds):
            if pending.generation != self.generation:
                return Decision(self._take(position), Verdict.STALE)
            lookup = self._lookup(pending)
            if not self._waiting(pending, lookup) or (timeout and now - pending.received_clock_ns >= timeout * 1e9):
                self._take(position)
                return Decision(pending, Verdict.PLACE if lookup.status is PoseStatus.FOUND else Verdict.NO_POSE,
                                lookup)
        return None

    def add_odometry(self, stamp: int, pose: np.ndarray, child_frame: str) -> tuple[PoseBreak | None, int | None]:
        """Keep one odometry pose; returns (the break before it or None, the previous newest stamp)."""
        with self.changed:
            previous = self.poses.latest_stamp
            found = self.poses.add(stamp, pose, child_frame)
            self.changed.notify_all()
            return found, previous

    def forget_odometry(self, before: int | None = None) -> int:
        """Forget the odometry (all of it, or that stamped before ``before``). Forgetting all of
        it also drops the waiting clouds, which belong to the old timeline; returns their count."""
        with self.changed:
            if before is not None:
                self.poses.drop_before(before)
                return 0
            self.poses.clear()
            stale = len(self.clouds)
            self.clouds.clear()
            self.bytes = 0
            return stale

    def new_generation(self) -> None:
        """A map reset: clouds received before it are stale (their poses may be too)."""
        with self.changed:
            self.generation += 1

    def stop(self) -> None:
        with self.changed:
            self.stopping = True
            self.changed.notify_all()


class SensorMount:
    """The pose of a cloud's frame in the odometry's child frame.

    ``fixed``: the ``base_to_sensor`` parameter as a 4x4 pose (child <- cloud frame), used for
    every cloud frame that is not the child frame. Without it, TF's static transforms are
    asked when tf2_ros is importable (``attach_tf``). ``find`` returns (pose, None) or
    (None, why not).
    """

    def __init__(self, fixed: np.ndarray | None):
        self.fixed = fixed
        self.tf_buffer = None
        self._listener = None

    def attach_tf(self, node) -> bool:
        """Listen to TF when tf2_ros exists (a ROS 2 install); False where it does not."""
        if self.fixed is not None:
            return False
        try:
            from tf2_ros import Buffer, TransformListener
        except ImportError:
            return False
        self.tf_buffer = Buffer()
        self._listener = TransformListener(self.tf_buffer, node, spin_thread=False)
        return True

    def find(self, child_frame: str, cloud_frame: str) -> tuple[np.ndarray | None, str | None]:
        if not cloud_frame or not child_frame or cloud_frame == child_frame:
            return np.eye(4), None
        if self.fixed is not None:
            return self.fixed, None
        if self.tf_buffer is None:
            return None, (f"the cloud's frame '{cloud_frame}' is not the odometry's child frame '{child_frame}' "
                          "and no mount is known: set base_to_sensor [x, y, z, qx, qy, qz, qw] (the pose of "
                          f"'{cloud_frame}' in '{child_frame}')")
        from rclpy.time import Time

        try:
            transform = self.tf_buffer.lookup_transform(child_frame, cloud_frame, Time())
        except Exception as error:  # tf2's LookupException, ConnectivityException, ExtrapolationException
            return None, (f"no transform from '{child_frame}' to the cloud's frame '{cloud_frame}' in TF "
                          f"({error.__class__.__name__}); publish the mount on /tf_static or set base_to_sensor")
        return transform_to_pose(transform), None

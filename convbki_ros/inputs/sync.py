"""Clouds waiting for their pose: the bounded queue, the odometry lookup and the sensor mount.

A cloud is placed with the odometry interpolated at its stamp (``pose_buffer``). On a real
robot the odometry is the pose of ``base_link`` (its ``child_frame_id``) in ``odom`` while
the LiDAR publishes in its own frame, mounted on the base by a static transform; the
sensor's pose is then odometry x mount. The mount comes from the ``base_to_sensor``
parameter, or from TF. A map in another frame than the odometry's (a SLAM's ``map`` over the
robot's ``odom``) takes TF's ``map -> odom`` at the cloud's stamp in front; with TF as the
pose source, the whole pose of the cloud's frame in the map comes from TF.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from convbki_ros.inputs.pose_buffer import OdometryBuffer, PoseBreak, PoseLookup, PoseStatus
from convbki_ros.inputs.transforms import stamp_to_ns


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
    NO_TRANSFORM = "no transform"  # its odometry is known, the TF it needs did not come in time


# Drop reasons of a cloud whose odometry is known but whose TF never came (Verdict.NO_TRANSFORM):
NO_MOUNT = "no mount"  # the sensor's mount on the odometry's child frame (base_to_sensor or /tf_static)
NO_MAP_TRANSFORM = "no transform"  # map_frame -> the odometry's frame, or map_frame -> the cloud's frame


@dataclass(frozen=True)
class Missing:
    """What a cloud's placement still lacks: the drop reason (``NO_MOUNT``, ``NO_MAP_TRANSFORM``),
    the name the log, /diagnostics and the docs give it, and the detail in words."""

    reason: str
    detail: str


@dataclass
class Decision:
    pending: PendingCloud
    verdict: Verdict
    lookup: PoseLookup | None = None
    pose: np.ndarray | None = None  # PLACE: the cloud frame's pose in the map frame
    missing: Missing | None = None  # NO_TRANSFORM: what is missing


# A cloud's pose in the map once its odometry is known: (pose, None), or (None, what is missing).
Placer = Callable[[PendingCloud, PoseLookup], tuple[np.ndarray | None, Missing | None]]


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

    def __init__(self, max_pose_jump: float, placer: Placer | None = None,
                 locate: Callable[[PendingCloud], PoseLookup] | None = None):
        """``placer``: the cloud's final pose from its odometry (the mount, TF in front), which may
        have to wait for TF; default: the odometry's pose. ``locate``: the cloud's pose from
        elsewhere than the odometry (TF as the pose source); default: the odometry history."""
        self.placer = placer or (lambda pending, lookup: (lookup.pose, None))
        self.locate = locate
        self.transform_timeout = 1.0  # seconds of the node's clock a cloud may wait for the placer
        self.changed = threading.Condition()
        self.clouds: deque[PendingCloud] = deque()
        self.bytes = 0
        self.poses = OdometryBuffer(max_jump=max_pose_jump)
        self.generation = 0  # bumped by every map reset
        self.stopping = False
        self.waiting_for_transform = False  # a cloud with its odometry waits for TF
        # The stamp (ns) of the cloud the update thread took and has not finished with: neither
        # queued nor logged yet, it is on its way into the map (a correction waits for it).
        self.in_flight: int | None = None
        # The stamp (ns) of the newest cloud received: how far the live map lags behind the sensor.
        self.newest_ns: int | None = None

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
            stamp = stamp_to_ns(msg.header.stamp)
            self.newest_ns = stamp if self.newest_ns is None else max(self.newest_ns, stamp)
            self.changed.notify_all()
            return evicted

    def __len__(self) -> int:
        with self.changed:
            return len(self.clouds)

    def oldest_stamp(self) -> int | None:
        """The stamp (ns) of the oldest queued cloud, None when none is queued."""
        with self.changed:
            return min((stamp_to_ns(pending.msg.header.stamp) for pending in self.clouds), default=None)

    def ready(self) -> int:
        """Queued clouds whose odometry has come: the update thread's work at hand."""
        with self.changed:
            return sum(not self._waiting(pending) for pending in self.clouds)

    def waiting_for_pose(self) -> int:
        """Queued clouds whose odometry has not come yet."""
        with self.changed:
            return sum(self._waiting(pending) for pending in self.clouds)

    def _lookup(self, pending: PendingCloud) -> PoseLookup:
        if self.locate is not None:
            return self.locate(pending)
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

    def next(self, pose_wait_timeout, clock_ns=lambda: 0) -> Decision | None:
        """Block until a cloud can be decided (or ``stop()``); None when stopping.

        ``pose_wait_timeout``: seconds of the node's clock (``clock_ns()``) a cloud may wait for
        its odometry; 0 = as long as the queue has room for it. A callable is read at every look,
        so that a change at run time applies to the clouds already waiting.
        """
        read = pose_wait_timeout if callable(pose_wait_timeout) else lambda: pose_wait_timeout
        with self.changed:
            while not self.stopping:
                pose_wait_timeout = read()
                decision = self._decide(pose_wait_timeout, clock_ns)
                if decision is not None:
                    self.in_flight = stamp_to_ns(decision.pending.msg.header.stamp)
                    return decision
                # Nothing queued: sleep until something arrives. Clouds waiting for odometry:
                # wake up in time for the first one's timeout too; for TF, which may come
                # through a listener that tells no one, look again soon.
                polling = pose_wait_timeout or self.waiting_for_transform or self.locate is not None
                self.changed.wait(0.5 if not self.clouds or not polling else 0.02)
            return None

    def finished(self) -> None:
        """The update thread is done with the cloud ``next`` gave it (integrated or dropped)."""
        with self.changed:
            self.in_flight = None
            self.changed.notify_all()

    def _decide(self, timeout: float, clock_ns) -> Decision | None:
        now = clock_ns()
        self.waiting_for_transform = False

        def expired(pending: PendingCloud, seconds: float) -> bool:
            return bool(seconds) and now - pending.received_clock_ns >= seconds * 1e9

        for position, pending in enumerate(self.clouds):
            if pending.generation != self.generation:
                return Decision(self._take(position), Verdict.STALE)
            if not pending.received_clock_ns:  # received before the clock ran (use_sim_time, no /clock yet)
                pending.received_clock_ns = now
            lookup = self._lookup(pending)
            if self._waiting(pending, lookup) and not expired(pending, timeout):
                continue
            if lookup.status is not PoseStatus.FOUND:
                return Decision(self._take(position), Verdict.NO_POSE, lookup)
            pose, missing = self.placer(pending, lookup)
            if pose is not None:
                return Decision(self._take(position), Verdict.PLACE, lookup, pose)
            if expired(pending, self.transform_timeout):
                return Decision(self._take(position), Verdict.NO_TRANSFORM, lookup, missing=missing)
            self.waiting_for_transform = True
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


class SensorFrames:
    """Where a cloud's frame is in the map frame, from its odometry, its mount and TF.

    ``mount``: the ``base_to_sensor`` parameter as a 4x4 pose (odometry child <- cloud frame),
    used for every cloud frame that is not the child frame; None: TF is asked (``tf``, an
    object with ``lookup(target, source, stamp_ns)`` raising ``LookupError``, or None where no
    TF can be read). ``map_frame``: the map's frame; "" or the odometry's frame needs no TF.
    """

    def __init__(self, mount: np.ndarray | None, tf=None, map_frame: str = ""):
        self.fixed = mount
        self.tf = tf
        self.map_frame = map_frame

    def _tf(self, target: str, source: str, stamp: int) -> tuple[np.ndarray | None, str | None]:
        if self.tf is None:
            return None, "TF cannot be read here (no tf2_msgs for rclpy)"
        try:
            return self.tf.lookup(target, source, stamp), None
        except LookupError as error:
            return None, str(error)

    def mount(self, child_frame: str, cloud_frame: str, stamp: int) -> tuple[np.ndarray | None, str | None]:
        """The pose of ``cloud_frame`` in the odometry's child frame at ``stamp``."""
        if not cloud_frame or not child_frame or cloud_frame == child_frame:
            return np.eye(4), None
        if self.fixed is not None:
            return self.fixed, None
        if self.tf is None:
            return None, (f"the cloud's frame '{cloud_frame}' is not the odometry's child frame '{child_frame}' "
                          "and no mount is known: set base_to_sensor [x, y, z, qx, qy, qz, qw] (the pose of "
                          f"'{cloud_frame}' in '{child_frame}')")
        pose, why = self._tf(child_frame, cloud_frame, stamp)
        if pose is None:
            return None, f"no mount in TF ({why}); publish it on /tf_static or set base_to_sensor"
        return pose, None

    def map_from(self, odometry_frame: str, stamp: int) -> tuple[np.ndarray | None, str | None]:
        """The pose of the odometry's frame in the map frame at ``stamp`` (identity when they are one)."""
        if not self.map_frame or not odometry_frame or self.map_frame == odometry_frame:
            return np.eye(4), None
        pose, why = self._tf(self.map_frame, odometry_frame, stamp)
        if pose is None:
            return None, f"no transform from map_frame '{self.map_frame}' to the odometry's '{odometry_frame}' ({why})"
        return pose, None

    def place(self, odometry_frame: str, lookup: PoseLookup, cloud_frame: str,
              stamp: int) -> tuple[np.ndarray | None, Missing | None]:
        """The cloud frame's pose in the map: TF's map <- odometry frame, the odometry, the mount."""
        mount, why = self.mount(lookup.child_frame_id, cloud_frame, stamp)
        if mount is None:
            return None, Missing(NO_MOUNT, why)
        in_front, why = self.map_from(odometry_frame, stamp)
        if in_front is None:
            return None, Missing(NO_MAP_TRANSFORM, why)
        return in_front @ lookup.pose @ mount, None

    def locate(self, cloud_frame: str, stamp: int) -> PoseLookup:
        """TF as the pose source: the pose of ``cloud_frame`` in the map frame at ``stamp``
        (WAIT, with the reason, while TF does not have it)."""
        pose, why = self._tf(self.map_frame, cloud_frame, stamp)
        if pose is None:
            return PoseLookup(PoseStatus.WAIT, reason=f"no transform from '{self.map_frame}' to the cloud's frame "
                              f"'{cloud_frame}' ({why})")
        return PoseLookup(PoseStatus.FOUND, pose, cloud_frame)

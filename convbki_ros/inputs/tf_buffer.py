"""A TF buffer in numpy: the node's own stand-in for tf2_ros.Buffer, bounded by count.

The mapper needs the pose of a cloud's frame in the map frame at the cloud's stamp, and the
tree of frames that gives it is published on ``/tf`` (moving joints, odometry) and
``/tf_static`` (mounts). tf2_ros is part of a full ROS 2 install but not of the pip wheels
this project also runs from; ``tf2_msgs`` (the message type) is much lighter. So
``TransformBuffer`` keeps the tree itself, in every install: tf2's buffer is bounded by time
alone, and since anyone on the domain can publish /tf, this one is bounded by count as well
(``MAX_FRAMES``, ``MAX_RECORDS``, ``MAX_FRAME_ID_LENGTH``).

Conventions are those of ``transforms``: a pose is a 4x4 matrix ``parent <- child``, stamps
are integer nanoseconds. ``lookup(target, source)`` is ``target <- source`` (what tf2's
``lookup_transform(target_frame, source_frame, time)`` returns).

What the buffer does, and where it follows tf2:

* Every frame has at most one parent at a time; each edge is stored under its child. A
  dynamic edge keeps its records sorted by stamp (out-of-order arrivals are placed in order,
  a repeated stamp replaces) and forgets those older than ``cache_seconds`` behind its own
  newest record. A static edge holds one pose valid at every time; a new one replaces it.
* A child's parent may change (a relocalisation re-parenting ``odom``): each record carries
  its parent and the record at or before the asked time decides it, so the latest parent
  wins from its first stamp on. Between two records with different parents the earlier one
  is held, not interpolated (as tf2 does). Whichever kind, static or dynamic, was added last
  to a child is the one kept: a static transform for a child discards its dynamic records
  and the other way round, so one child never has two answers.
* A lookup walks both frames up to their common ancestor, at the asked stamp; only the edges
  on that path matter. Between two records the pose is interpolated (translation linearly,
  rotation by slerp); outside an edge's records it is an error, never an extrapolation.
* Stamp None (or 0, tf2's ``Time()``) means the latest time at which every dynamic edge on
  the path is known: the oldest of their newest stamps. Static edges do not constrain it.
* Transforms are checked before they are kept (finite, a unit quaternion within
  ``pose_buffer.QUATERNION_NORM_TOLERANCE``, non-empty and distinct frame ids; a leading
  '/' is stripped as tf2 does), since one bad mount would misplace every scan.
* Frames are only forgotten by ``clear()``, so "unknown" means never seen. A lookup between a frame and
  itself is the identity once the frame is known.
* A loop in the tree (a parent of its own ancestor) or a chain deeper than
  ``MAX_GRAPH_DEPTH`` is reported, never walked for ever.

No rclpy at import time: ``TransformListener`` and ``make_tf_lookup`` import the ROS
packages when called.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from convbki_core.geometry.poses import interpolate_pose, pose_from_translation_quaternion
from convbki_ros.inputs.pose_buffer import pose_problem
from convbki_ros.inputs.transforms import stamp_to_ns

MAX_GRAPH_DEPTH = 100  # parents walked above a frame before giving up (tf2 uses the same bound)
# Bounds by count, beside the time the cache covers: anyone on the domain can publish /tf, and a
# flood of frames or of records stamped a nanosecond apart must not exhaust the node's memory.
MAX_FRAMES = 1000  # child frames kept; transforms for more are refused
MAX_RECORDS = 100_000  # dynamic records over all frames; each frame keeps its share of them, newest first
MIN_RECORDS_PER_FRAME = 100  # what a frame keeps however many frames share the records
MAX_FRAME_ID_LENGTH = 256  # characters; a longer frame id is refused
RIGID_TOLERANCE = 1e-6  # how far R^T R may be from I in a pose passed to add()
TF_QUEUE_DEPTH = 100  # the history depth tf2_ros's listener subscribes with
SKIP_WARNING_PERIOD_S = 10.0  # at most one warning this often about skipped transforms


class TransformError(LookupError):
    """A transform that cannot be had; the message names the frames and why in one line."""


class UnknownFrameError(TransformError):
    """A frame no transform has mentioned."""


class ConnectivityError(TransformError):
    """Two frames in different trees, a loop, or a chain too deep to walk."""


class ExtrapolationError(TransformError):
    """A stamp outside the records of an edge the lookup needs."""


class InvalidTransformError(TransformError, ValueError):
    """A transform or a frame id that is refused (non-finite, not a rotation, empty, self-referencing)."""


def _seconds(stamp_ns: int) -> str:
    """Stamp in seconds for messages: milliseconds, or nanoseconds when milliseconds would hide a difference."""
    if stamp_ns % 1_000_000 == 0:
        return f"{stamp_ns / 1e9:.3f} s"
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return f"{sec}.{nanosec:09d} s"


def _frame_id(name: Any, role: str) -> str:
    frame = str(name).lstrip("/")
    if not frame:
        raise InvalidTransformError(f"the {role} frame id is empty")
    if len(frame) > MAX_FRAME_ID_LENGTH:
        raise InvalidTransformError(f"the {role} frame id is {len(frame)} characters long, more than "
                                    f"{MAX_FRAME_ID_LENGTH}")
    return frame


def _checked_pose(pose: Any, parent: str, child: str) -> np.ndarray:
    matrix = np.asarray(pose, dtype=np.float64)
    what = f"transform '{parent}' -> '{child}'"
    if matrix.shape != (4, 4):
        raise InvalidTransformError(f"{what}: a pose must be 4x4, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise InvalidTransformError(f"{what}: the pose is not finite")
    rotation = matrix[:3, :3]
    if (not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=RIGID_TOLERANCE)
            or not np.allclose(rotation.T @ rotation, np.eye(3), rtol=0.0, atol=RIGID_TOLERANCE)
            or np.linalg.det(rotation) < 0.0):
        raise InvalidTransformError(f"{what}: the pose is not a rigid transform (rotation and translation)")
    return matrix.copy()


def _inverse(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose (transpose the rotation) without a general matrix inverse."""
    inverse = np.eye(4)
    inverse[:3, :3] = pose[:3, :3].T
    inverse[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inverse


@dataclass
class _Edge:
    """The transforms ``parent <- child`` of one child: dynamic records, or one static pose."""

    child: str
    stamps: list[int] = field(default_factory=list)
    parents: list[str] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    static_parent: str | None = None
    static_pose: np.ndarray | None = None

    @property
    def is_static(self) -> bool:
        return self.static_parent is not None

    def set_static(self, parent: str, pose: np.ndarray) -> None:
        self.stamps.clear()
        self.parents.clear()
        self.poses.clear()
        self.static_parent, self.static_pose = parent, pose

    def insert(self, stamp: int, parent: str, pose: np.ndarray, cache_ns: int, keep: int) -> None:
        """Add a record (a repeated stamp replaces), then forget those older than ``cache_ns``
        behind the newest and all but the newest ``keep``."""
        self.static_parent = self.static_pose = None
        position = bisect.bisect_left(self.stamps, stamp)
        if position < len(self.stamps) and self.stamps[position] == stamp:
            self.parents[position], self.poses[position] = parent, pose
        else:
            self.stamps.insert(position, stamp)
            self.parents.insert(position, parent)
            self.poses.insert(position, pose)
        cut = max(bisect.bisect_left(self.stamps, self.stamps[-1] - cache_ns), len(self.stamps) - keep)
        if cut > 0:
            del self.stamps[:cut], self.parents[:cut], self.poses[:cut]

    @property
    def newest(self) -> int | None:
        """The newest record's stamp; None for a static edge (valid at every time)."""
        return None if self.is_static else self.stamps[-1]

    def _record_at(self, stamp: int | None) -> int:
        """Index of the record at or before ``stamp`` (the first one before them all, the newest for None)."""
        if stamp is None:
            return len(self.stamps) - 1
        return max(bisect.bisect_right(self.stamps, stamp) - 1, 0)

    def parent_at(self, stamp: int | None) -> str:
        if self.static_parent is not None:
            return self.static_parent
        return self.parents[self._record_at(stamp)]

    def pose_at(self, stamp: int | None) -> np.ndarray:
        """``parent_at(stamp) <- child`` at ``stamp``; ExtrapolationError outside the records."""
        if self.static_pose is not None:
            return self.static_pose
        if stamp is None:
            return self.poses[-1]
        first, last = self.stamps[0], self.stamps[-1]
        if stamp < first or stamp > last:
            known = f"only at {_seconds(first)}" if first == last else f"from {_seconds(first)} to {_seconds(last)}"
            direction = "past" if stamp < first else "future"
            raise ExtrapolationError(f"no transform '{self.parent_at(stamp)}' -> '{self.child}' at "
                                     f"{_seconds(stamp)}: it is known {known} (extrapolation into the {direction})")
        position = bisect.bisect_left(self.stamps, stamp)
        if self.stamps[position] == stamp:
            return self.poses[position]
        before = position - 1
        if self.parents[before] != self.parents[position]:
            return self.poses[before]  # re-parented in between: no pose half way between two parents
        fraction = (stamp - self.stamps[before]) / (self.stamps[position] - self.stamps[before])
        return interpolate_pose(self.poses[before], self.poses[position], fraction)


class TransformBuffer:
    """TF's tree of frames over the last ``cache_seconds``, looked up at any stamp in it (see the module's docstring).

    Thread-safe: a listener's callbacks may add while another thread looks up. Bounded by count
    too: at most ``MAX_FRAMES`` child frames, and ``MAX_RECORDS`` dynamic records shared among them
    (each frame keeps at least ``MIN_RECORDS_PER_FRAME``, its newest).
    """

    def __init__(self, cache_seconds: float = 10.0):
        if not cache_seconds > 0.0:
            raise ValueError(f"cache_seconds must be positive, got {cache_seconds!r}")
        self.cache_ns = round(float(cache_seconds) * 1e9)
        self._edges: dict[str, _Edge] = {}
        self._known: set[str] = set()
        self._lock = threading.RLock()

    # ------------------------------------------------------------------------- filling

    def add(self, parent: str, child: str, stamp_ns: Any, pose: np.ndarray, static: bool = False) -> None:
        """Keep ``pose`` (4x4 ``parent <- child``) at ``stamp_ns``, or for all times when ``static``.

        Raises InvalidTransformError (a ValueError) for an empty or self-referencing frame id
        or a pose that is not a finite rigid transform. A dynamic record older than the cache
        behind the edge's newest is dropped at once.
        """
        parent, child = _frame_id(parent, "parent"), _frame_id(child, "child")
        if parent == child:
            raise InvalidTransformError(f"transform '{parent}' -> '{child}' has the same frame on both ends")
        pose = _checked_pose(pose, parent, child)
        stamp = stamp_to_ns(stamp_ns)
        with self._lock:
            edge = self._edges.get(child)
            if edge is None:
                if len(self._edges) >= MAX_FRAMES:
                    raise InvalidTransformError(f"transform '{parent}' -> '{child}': {MAX_FRAMES} frames are known "
                                                "already, the most this buffer keeps")
                edge = self._edges[child] = _Edge(child)
            if static:
                edge.set_static(parent, pose)
            else:
                share = max(MIN_RECORDS_PER_FRAME, MAX_RECORDS // len(self._edges))
                edge.insert(stamp, parent, pose, self.cache_ns, share)
            self._known.update((parent, child))
            if len(self._known) > 2 * MAX_FRAMES:  # parents no record names any more are forgotten
                self._known = set(self._edges).union(
                    *({e.static_parent} if e.is_static else set(e.parents) for e in self._edges.values()))

    def add_message(self, tf_message: Any, static: bool = False) -> list[str]:
        """Keep every transform of a tf2_msgs/TFMessage (anything with ``.transforms`` of TransformStamped).

        Returns why each refused transform was skipped, one line each; empty when all were
        kept. One bad transform does not cost the others of the message.
        """
        skipped = []
        for transform in tf_message.transforms:
            parent, child = transform.header.frame_id, transform.child_frame_id
            try:
                parent, child = _frame_id(parent, "parent"), _frame_id(child, "child")
                t, r = transform.transform.translation, transform.transform.rotation
                translation = np.array([t.x, t.y, t.z], np.float64)
                rotation = np.array([r.x, r.y, r.z, r.w], np.float64)
                problem = pose_problem(translation, rotation)
                if problem is not None:
                    raise InvalidTransformError(f"transform '{parent}' -> '{child}': {problem}")
                pose = pose_from_translation_quaternion(translation, rotation)
                self.add(parent, child, transform.header.stamp, pose, static=static)
            except InvalidTransformError as error:
                why = str(error)
                skipped.append(why if why.startswith("transform '") else f"transform '{parent}' -> '{child}': {why}")
        return skipped

    def clear(self) -> None:
        """Forget everything (a bag looping back in time, say), frames included."""
        with self._lock:
            self._edges.clear()
            self._known.clear()

    # ------------------------------------------------------------------------- questions

    def frames(self) -> list[str]:
        """Every frame seen, as parent or child, sorted."""
        with self._lock:
            return sorted(self._known)

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: Any = None) -> np.ndarray:
        """The pose of ``source_frame`` in ``target_frame`` (4x4 ``target <- source``) at ``stamp_ns``.

        ``stamp_ns`` None or 0: the latest time the whole path is known. Raises a
        TransformError subclass naming the frames when there is no answer.
        """
        target, source = _frame_id(target_frame, "target"), _frame_id(source_frame, "source")
        stamp = None if stamp_ns is None else stamp_to_ns(stamp_ns)
        with self._lock:
            self._require_known(target, source)
            if target == source:
                return np.eye(4)
            if not stamp:
                stamp = self._latest_common(target, source)
            source_path, target_path = self._paths(target, source, stamp)
            source_pose = self._compose(source_path, stamp)  # ancestor <- source
            target_pose = self._compose(target_path, stamp)  # ancestor <- target
            return _inverse(target_pose) @ source_pose

    def can_transform(self, target_frame: str, source_frame: str, stamp_ns: Any = None) -> tuple[bool, str | None]:
        """(True, None) when ``lookup`` would answer, else (False, its error's message)."""
        try:
            self.lookup(target_frame, source_frame, stamp_ns)
        except TransformError as error:
            return False, str(error)
        return True, None

    def latest_stamp(self, target_frame: str, source_frame: str) -> int | None:
        """The latest stamp at which the path between the frames is known; None when it is all static.

        Raises UnknownFrameError or ConnectivityError as ``lookup`` does.
        """
        target, source = _frame_id(target_frame, "target"), _frame_id(source_frame, "source")
        with self._lock:
            self._require_known(target, source)
            return None if target == source else self._latest_common(target, source)

    # ------------------------------------------------------------------------- the walk

    def _require_known(self, *frames: str) -> None:
        unknown = list(dict.fromkeys(frame for frame in frames if frame not in self._known))
        if len(unknown) == 1:
            raise UnknownFrameError(f"frame '{unknown[0]}' is unknown")
        if unknown:
            raise UnknownFrameError(f"frames {' and '.join(repr(frame) for frame in unknown)} are unknown")

    def _path_up(self, frame: str, stamp: int | None) -> list[str]:
        """``frame``, its parent at ``stamp``, theirs, ... up to the root."""
        path = [frame]
        while (edge := self._edges.get(path[-1])) is not None:
            parent = edge.parent_at(stamp)
            if parent in path:
                loop = " -> ".join(f"'{name}'" for name in path[path.index(parent):] + [parent])
                raise ConnectivityError(f"the frames above '{frame}' form a loop (child -> parent): {loop}")
            if len(path) > MAX_GRAPH_DEPTH:
                raise ConnectivityError(f"more than {MAX_GRAPH_DEPTH} frames above '{frame}': "
                                        "the tree is too deep to walk")
            path.append(parent)
        return path

    def _paths(self, target: str, source: str, stamp: int | None) -> tuple[list[str], list[str]]:
        """The frames from source and from target up to (and including) their common ancestor."""
        source_up, target_up = self._path_up(source, stamp), self._path_up(target, stamp)
        in_target = {name: index for index, name in enumerate(target_up)}
        for index, name in enumerate(source_up):
            if name in in_target:
                return source_up[:index + 1], target_up[:in_target[name] + 1]
        raise ConnectivityError(f"'{target}' and '{source}' are not connected "
                                f"(trees rooted at '{target_up[-1]}' and '{source_up[-1]}')")

    def _edges_on(self, path: list[str]) -> Iterable[_Edge]:
        return (self._edges[name] for name in path[:-1])

    def _compose(self, path: list[str], stamp: int | None) -> np.ndarray:
        """``path[-1] <- path[0]``: the product of the edges along the path at ``stamp``."""
        pose = np.eye(4)
        for edge in self._edges_on(path):
            pose = edge.pose_at(stamp) @ pose
        return pose

    def _latest_common(self, target: str, source: str) -> int | None:
        source_path, target_path = self._paths(target, source, None)
        newest = [edge.newest for path in (source_path, target_path) for edge in self._edges_on(path)]
        dynamic = [stamp for stamp in newest if stamp is not None]
        return min(dynamic) if dynamic else None


# ----------------------------------------------------------------------------- ROS side


class TransformListener:
    """Fills a TransformBuffer from ``/tf`` and ``/tf_static``, with the QoS tf2_ros listens with.

    ``/tf``: reliable, volatile, keep last 100. ``/tf_static``: reliable, transient local, keep
    last 100, so the mounts published once at start-up still arrive to a late subscriber.
    Callbacks run in a reentrant group: the buffer has its own lock, and a mutually exclusive
    group would hold TF back behind a long cloud callback under a multi-threaded executor.
    Refused transforms are logged, at most one warning every SKIP_WARNING_PERIOD_S.
    """

    def __init__(self, node: Any, buffer: TransformBuffer, tf_topic: str = "/tf",
                 tf_static_topic: str = "/tf_static"):
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError as error:
            raise ImportError("listening to TF needs tf2_msgs (TFMessage) for rclpy, which is not importable: "
                              "source install/setup.bash (make setup builds it) or a ROS 2 install") from error
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.node = node
        self.buffer = buffer
        self.skipped = 0  # transforms refused so far
        group = ReentrantCallbackGroup()

        def qos(durability: Any) -> Any:
            return QoSProfile(depth=TF_QUEUE_DEPTH, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.RELIABLE, durability=durability)

        self._subscriptions = [
            node.create_subscription(TFMessage, tf_topic, lambda msg: self._on_message(msg, False, tf_topic),
                                     qos(DurabilityPolicy.VOLATILE), callback_group=group),
            node.create_subscription(TFMessage, tf_static_topic,
                                     lambda msg: self._on_message(msg, True, tf_static_topic),
                                     qos(DurabilityPolicy.TRANSIENT_LOCAL), callback_group=group),
        ]

    def _on_message(self, msg: Any, static: bool, topic: str) -> None:
        skipped = self.buffer.add_message(msg, static=static)
        if skipped:
            self.skipped += len(skipped)
            more = f" (and {len(skipped) - 1} more in the message)" if len(skipped) > 1 else ""
            self.node.get_logger().warning(f"{topic}: skipped {skipped[0]}{more}; {self.skipped} skipped in all",
                                           throttle_duration_sec=SKIP_WARNING_PERIOD_S)

    def destroy(self) -> None:
        """Unsubscribe both topics."""
        for subscription in self._subscriptions:
            self.node.destroy_subscription(subscription)
        self._subscriptions = []


class BufferLookup:
    """The project's TransformBuffer fed by its TransformListener: what ``make_tf_lookup`` gives without tf2_ros."""

    def __init__(self, buffer: TransformBuffer, listener: TransformListener | None):
        self.buffer = buffer
        self.listener = listener

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: Any = None) -> np.ndarray:
        return self.buffer.lookup(target_frame, source_frame, stamp_ns)

    def can_transform(self, target_frame: str, source_frame: str, stamp_ns: Any = None) -> tuple[bool, str | None]:
        return self.buffer.can_transform(target_frame, source_frame, stamp_ns)


def make_tf_lookup(node: Any, cache_seconds: float = 10.0) -> tuple[BufferLookup | None, str]:
    """TF for ``node``: (a lookup, which backend it is) or (None, why there is none).

    This module's TransformBuffer and TransformListener, which need only tf2_msgs, in every
    install: tf2_ros's buffer, where a ROS 2 install has it, is bounded by time alone, and anyone
    on the domain can publish /tf. None where tf2_msgs is missing, since nothing can receive /tf.
    """
    buffer = TransformBuffer(cache_seconds)
    try:
        listener = TransformListener(node, buffer)
    except ImportError as error:
        return None, f"{error}; frames other than the odometry's need the base_to_sensor parameter"
    return BufferLookup(buffer, listener), "convbki_ros.inputs.tf_buffer.TransformBuffer"

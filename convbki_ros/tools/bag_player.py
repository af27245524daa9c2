"""Publishing an open bag for ``play_bag``: one publisher per topic and type, the messages in
stamp order at the pace of their stamps (or of a ``NodePacer``), /clock, subscribers watched, and
at the end the acknowledgements awaited, so that what was not delivered can be said.

A message is published as the bag's CDR bytes, unchanged, when the bag's type hash equals
the installed message type's (the normal case); otherwise (or with ``--deserialize``) it is
deserialised with a rosbags typestore built from the bag's own definitions and converted
field by field into the installed rclpy class. Topics whose type has no installed Python
package (e.g. tf2_msgs with the PyPI wheels) are skipped with one line.

Bulky messages (point clouds, images) go out from a DDS participant of their own, the rest
(odometry, transforms, /clock) from another: Fast DDS drops now and then a small reliable
message that one participant sends while it is sending a multi-megabyte one, and repairs it
only at the writer's next heartbeat, seconds later. Sent from one participant, a bag's
odometry reached its subscribers in bursts up to 3 s late; from its own, on time.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from convbki_ros.tools.bag_reading import checked_messages, grouped, rclpy_message_class, to_rclpy

if TYPE_CHECKING:
    from convbki_ros.tools.node_pacing import NodePacer

CLOCK_TOPIC = "/clock"
DEPTH = 100
LATCHED_TOPICS = ("/tf_static",)  # replayed transient local, whatever the bag recorded
BEHIND_S = 1.0  # this far behind the bag's pace (in wall seconds), the replay resumes from where it is
FLUSH_TIMEOUT_S = 10.0  # how long the end waits for acknowledgements
SETTLE_S = 3.0  # after a pause: how long to watch for subscribers that DDS expires on resuming (an announcement period)
REDISCOVERY_S = 10.0  # after a pause: how long to wait for them to be found again
MATCHING_S = 10.0  # at the start: how much longer to wait for a subscriber already discovered to match
# Message types sent from the bulk participant (see the module's docstring).
BULK_TYPES = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointCloud", "sensor_msgs/msg/Image",
              "sensor_msgs/msg/CompressedImage")


@dataclass
class Channel:
    """One bag connection and how its messages get out."""

    topic: str  # topic published on (after --remap)
    msgtype: str
    publisher: Any = None
    cls: type | None = None
    raw: bool = True  # publish the CDR bytes as they are
    priority: int = 1  # order among messages sharing a timestamp: lower first
    skipped: str = ""
    count: int = field(default=0)


def _recorded_transient_local(connection: Any) -> bool:
    """Whether the bag recorded the topic's publishers as transient local (rosbag2's metadata)."""
    profiles = getattr(getattr(connection, "ext", None), "offered_qos_profiles", None) or []
    if isinstance(profiles, str):  # older rosbags: the metadata's YAML text
        return "durability: 1" in profiles or "transient_local" in profiles.lower()
    return any(getattr(getattr(profile, "durability", None), "name", "") == "TRANSIENT_LOCAL" for profile in profiles)


def _priority(msgtype: str) -> int:
    if msgtype.startswith(("tf2_msgs/", "nav_msgs/msg/Odometry", "geometry_msgs/msg/Transform")):
        return 0
    if msgtype.startswith("sensor_msgs/msg/PointCloud2"):
        return 2
    return 1


class BagPlayer:
    """Publishes one open bag through ``node``, its bulky messages through ``bulk_node`` (a node
    of another rclpy context, so another DDS participant; default: ``node``)."""

    def __init__(self, node: Any, reader: Any, args: argparse.Namespace, bulk_node: Any = None,
                 pacer: NodePacer | None = None):
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.node = node
        self.pacer = pacer
        self.pauses: list[float] = []  # seconds the player was behind the bag's pace, each time it resumed
        # (topic, seconds): subscribers that DDS forgot on resuming after a pause, and how long
        # they were missing (their participant's lease ran out in this process while it was stopped)
        self.forgotten: list[tuple[str, float]] = []
        self.bulk_node = bulk_node or node
        self.reader = reader
        self.args = args
        reliability = ReliabilityPolicy.RELIABLE if args.qos == "reliable" else ReliabilityPolicy.BEST_EFFORT
        self.qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=reliability,
                              durability=DurabilityPolicy.VOLATILE)
        self.remaps = dict(args.remap)
        self.channels: dict[int, Channel] = {}
        self.publishers: dict[tuple[str, str], Any] = {}
        self.subscribers: dict[tuple[str, str], int] = {}  # per publisher: matched subscriptions when last looked
        # per publisher: (subscribers gone, messages it had sent by then), one per departure
        self.departures: dict[tuple[str, str], list[tuple[int, int]]] = {}
        self.typestore = None
        self.clock_publisher = None
        self.clock_class = None
        for connection in reader.connections:
            self.channels[connection.id] = self._channel(connection)
        if args.clock:
            from rosgraph_msgs.msg import Clock

            self.clock_class = Clock
            self.clock_publisher = node.create_publisher(
                Clock, CLOCK_TOPIC, QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEPTH,
                                               reliability=ReliabilityPolicy.RELIABLE,
                                               durability=DurabilityPolicy.VOLATILE))

    def _channel(self, connection: Any) -> Channel:
        topic = self.remaps.get(connection.topic, connection.topic)
        channel = Channel(topic=topic, msgtype=connection.msgtype, priority=_priority(connection.msgtype))
        try:
            channel.cls = rclpy_message_class(connection.msgtype)
        except (ImportError, AttributeError, ValueError):
            channel.skipped = f"{connection.msgtype} is not installed for rclpy"
            self.node.get_logger().info(f"skipping {connection.topic}: {channel.skipped}")
            return channel
        key = (topic, connection.msgtype)
        owner = self.bulk_node if connection.msgtype in BULK_TYPES else self.node
        if key not in self.publishers:
            self.publishers[key] = owner.create_publisher(channel.cls, topic, self._qos_of(connection))
        channel.publisher = self.publishers[key]
        channel.raw = not self.args.deserialize and self._same_type(owner, channel.publisher, connection.digest)
        if not channel.raw:
            self._ensure_typestore()
        return channel

    def _qos_of(self, connection: Any) -> Any:
        """The replay's QoS, transient local where the bag's topic was latched: /tf_static (a
        robot's mounts, sent once at start) and any topic recorded with transient local
        durability, so that a subscriber that joins later still gets them."""
        from rclpy.qos import DurabilityPolicy, QoSProfile

        if not (connection.topic in LATCHED_TOPICS or _recorded_transient_local(connection)):
            return self.qos
        return QoSProfile(history=self.qos.history, depth=self.qos.depth, reliability=self.qos.reliability,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)

    @staticmethod
    def _same_type(node: Any, publisher: Any, digest: str | None) -> bool:
        """Whether the installed type's hash equals the bag's (then its CDR bytes are ours)."""
        if not digest:
            return False
        try:
            infos = node.get_publishers_info_by_topic(publisher.topic_name)
        except Exception:  # any graph error: fall back to converting
            return False
        hashes = {str(getattr(info, "topic_type_hash", "")) for info in infos
                  if info.node_name == node.get_name() and info.node_namespace == node.get_namespace()}
        return digest in hashes

    def _ensure_typestore(self) -> None:
        """Typestores for deserialising: the bag's own definitions, Jazzy's for what the bag lacks."""
        if self.typestore is not None:
            return
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        bag_store = get_typestore(Stores.EMPTY)
        for connection in self.reader.connections:
            definition = connection.msgdef
            if not definition.data:
                continue
            try:
                if definition.format.name == "IDL":
                    bag_store.register(get_types_from_idl(definition.data))
                else:
                    bag_store.register(get_types_from_msg(definition.data, connection.msgtype))
            except Exception as error:  # fall back to the Jazzy definition
                self.node.get_logger().debug(f"{connection.topic}: bag's type definition not used ({error})")
        jazzy = get_typestore(Stores.ROS2_JAZZY)
        self.typestore = {c.msgtype: bag_store if c.msgtype in bag_store.types else jazzy
                          for c in self.reader.connections}

    def plays(self, msgtype: str) -> bool:
        """The bag has a topic of ``msgtype`` ("nav_msgs/msg/Path") that the replay publishes."""
        return any(channel.msgtype == msgtype and not channel.skipped for channel in self.channels.values())

    def wait_for_subscribers(self, timeout: float) -> bool:
        """Block until every publisher has a subscriber, or ``timeout``. Topics nobody subscribes
        to are given up 1 s after the first match; one whose subscriber either participant has
        already discovered is waited for (the other participant is still matching it), up to
        ``MATCHING_S`` past ``timeout``: on a loaded machine the second participant can take
        seconds to match, and what it sends before that reaches no one."""
        publishers = [*self.publishers.values(), *([self.clock_publisher] if self.clock_publisher else [])]
        if not publishers or timeout <= 0:
            return False
        started = time.monotonic()
        first_match = None
        while time.monotonic() < started + timeout + MATCHING_S:
            pending = [p for p in publishers if p.get_subscription_count() == 0]
            if not pending:
                return True
            if len(pending) < len(publishers) and first_match is None:
                first_match = time.monotonic()
            discovered = [p for p in pending if any(node.count_subscribers(p.topic_name)
                                                    for node in {self.node, self.bulk_node})]
            if not discovered and (time.monotonic() > started + timeout or
                                   (first_match is not None and time.monotonic() - first_match > 1.0)):
                break
            time.sleep(0.02)
        missing = [p.topic_name for p in publishers if p.get_subscription_count() == 0]
        if missing:
            self.node.get_logger().info(f"starting with no subscriber on {', '.join(missing)}")
        return len(missing) < len(publishers)

    def _publish(self, channel: Channel, data: bytes, timestamp: int) -> None:
        if channel.raw:
            channel.publisher.publish(bytes(data))
        else:
            assert self.typestore is not None
            message = self.typestore[channel.msgtype].deserialize_cdr(bytes(data), channel.msgtype)
            channel.publisher.publish(to_rclpy(message, channel.cls))
        channel.count += 1  # per message, so Ctrl-C between two messages of one stamp counts the first

    def _publish_clock(self, timestamp: int) -> None:
        if self.clock_publisher is None:
            return
        msg = self.clock_class()
        msg.clock.sec, msg.clock.nanosec = divmod(int(timestamp), 1_000_000_000)
        self.clock_publisher.publish(msg)

    def play(self, ok: Callable[[], bool]) -> int:
        """Publish every message; returns how many went out. Stops early when ``ok()`` is False."""
        wanted = [c for c in self.reader.connections if not self.channels[c.id].skipped]
        if not wanted:
            return 0
        total = sum(c.msgcount for c in wanted)
        bar = _progress_bar(total)
        rate = self.args.rate or (float("inf") if self.pacer else 1.0)
        start_wall = None
        first_stamp = None
        previous = None
        # Count the subscribers before the first message, so that one leaving before the first
        # look after publishing is still seen to go.
        self._watch_subscribers()
        try:
            messages = checked_messages(self.reader.messages(connections=wanted), str(self.args.bag))
            for timestamp, group in grouped(messages):
                if start_wall is None:
                    start_wall, first_stamp = time.monotonic(), timestamp
                if previous is None or timestamp >= previous:
                    target = start_wall + (timestamp - first_stamp) / 1e9 / rate
                    if not sleep_until(target, ok):
                        break
                    behind = time.monotonic() - target  # the player was stopped, or the machine stalled
                    if behind > BEHIND_S:  # resume at the bag's pace from here, not with the backlog at once
                        self.pauses.append(behind)
                        self._rediscover(ok)
                        start_wall += time.monotonic() - target
                    previous = timestamp
                # else: out of order in the bag (split files): publish at once, keep the clock monotonic
                clouds = sum(self.channels[c.id].msgtype in BULK_TYPES for c, _ in group)
                if clouds and self.pacer is not None:
                    waited = time.monotonic()
                    if not self.pacer.wait_for_room(clouds, ok):
                        break
                    start_wall += time.monotonic() - waited  # waiting for the node is not falling behind
                self._publish_clock(max(timestamp, previous))
                for connection, data in sorted(group, key=lambda item: self.channels[item[0].id].priority):
                    self._publish(self.channels[connection.id], data, timestamp)
                if self.pacer is not None:
                    self.pacer.sent(clouds)
                self._watch_subscribers()
                if bar is not None:
                    bar.update(len(group))
        finally:
            if bar is not None:
                bar.close()
        return self.sent

    @property
    def sent(self) -> int:
        """Messages published so far (the clock excluded)."""
        return sum(channel.count for channel in self.channels.values())

    def _sent_on(self, key: tuple[str, str]) -> int:
        """Messages published so far through the publisher of ``key`` (topic, type): the bag may
        hold several connections of one topic."""
        return sum(c.count for c in self.channels.values() if c.publisher is self.publishers[key])

    def _rediscover(self, ok: Callable[[], bool]) -> None:
        """After a pause: give DDS the time to find the subscribers again before sending more.

        A stopped process hears nothing; when it resumes, its participant may first expire the
        subscribers' participants (their announcements are read after its lease timer ran) and
        then find them again, a second or so later. What is published in between reaches no one.
        """
        deadline = time.monotonic() + REDISCOVERY_S
        settle = time.monotonic() + SETTLE_S
        missing: dict[tuple[str, str], list[float]] = {}  # per publisher: first and last time seen short
        while ok() and time.monotonic() < deadline:
            back = True
            for key, publisher in self.publishers.items():
                if publisher.get_subscription_count() < self.subscribers.get(key, 0):
                    back = False
                    now = time.monotonic()
                    missing.setdefault(key, [now, now])[1] = now
            if back and time.monotonic() > settle:
                break
            time.sleep(0.05)
        for key, (first, last) in missing.items():
            self.forgotten.append((key[0], last - first + 0.05))

    def _watch_subscribers(self) -> None:
        """Notice a subscriber that goes away during the replay: what it had not yet acknowledged
        is lost to it, and DDS forgets that once it is gone."""
        for key, publisher in self.publishers.items():
            count, before = publisher.get_subscription_count(), self.subscribers.get(key, 0)
            if count < before:
                self.departures.setdefault(key, []).append((before - count, self._sent_on(key)))
            self.subscribers[key] = count

    def flush(self, timeout: float = FLUSH_TIMEOUT_S) -> list[str]:
        """Wait (bounded) until reliable subscribers acknowledged everything published; what was
        not delivered, a line per topic (empty when everything was)."""
        from rclpy.duration import Duration

        self._watch_subscribers()
        problems = []
        deadline = time.monotonic() + timeout
        for key, publisher in self.publishers.items():
            topic, sent = key[0], self._sent_on(key)
            left = max(0.0, deadline - time.monotonic())
            try:
                acked = publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))
            except Exception:  # an rmw without acknowledgements: nothing to learn
                acked = True
            if not acked:
                problems.append(f"{topic}: not every subscriber acknowledged the {sent} messages published "
                                f"(waited {timeout:g} s; a subscriber that stopped reading or fell behind)")
            for gone, after in self.departures.get(key, []):
                problems.append(f"{topic}: {gone} subscriber(s) went away after message {after} of {sent}: "
                                "what they had not acknowledged was not delivered")
        if self.clock_publisher is not None:
            with contextlib.suppress(Exception):  # the clock's last ticks matter to nobody after the end
                self.clock_publisher.wait_for_all_acked(Duration(nanoseconds=int(1e9)))
        return problems


def sleep_until(target: float, ok: Callable[[], bool]) -> bool:
    """Sleep until monotonic time ``target`` in short steps; False when ``ok()`` turns False."""
    while True:
        if not ok():
            return False
        left = target - time.monotonic()
        if left <= 0:
            return True
        time.sleep(min(left, 0.1))


def _progress_bar(total: int) -> Any:
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a pinned dependency
        return None
    return tqdm(total=total, desc="play_bag", unit="msg", file=sys.stderr, dynamic_ncols=True, mininterval=1.0)

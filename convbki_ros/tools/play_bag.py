"""``play_bag``: publish a rosbag2 on its topics, in stamp order (no ros2 bag needed).

Messages go out at ``--rate`` x the pace of their bag timestamps, timed against one
monotonic start instant (no drift accumulates). Messages sharing a timestamp go out
together, transforms and odometry before the clouds that need them. With ``--clock``,
/clock (rosgraph_msgs/Clock) carries each timestamp just before the messages stamped with it.
When the player falls far behind that pace (it was stopped, or the machine stalled), the replay
resumes from where it is at its pace instead of sending the backlog at once, which would
overflow the writers' and readers' histories.

With ``--wait-for-node NODE`` the clouds go out as fast as that node keeps up: the player
reads the node's ``/diagnostics`` (clouds received and queued) and keeps at most half of its
queue in flight, so a bag is mapped faster than real time with none dropped.

DDS matches the two ends of a connection separately: the player's writers can count a
subscriber whose reader has not yet matched them, and what is sent in between reaches no one.
The player therefore gives subscribers a second after its writers matched; with
``--wait-for-inputs NODE`` (implied by ``--wait-for-node``) it waits instead until the node's
``/diagnostics`` report a matched publisher on each of its inputs.

The player tells the truth about delivery: at the end it waits for every subscriber to
acknowledge every reliable message, and exits 1, naming the topic and the count, when some
were not acknowledged or a subscriber went away during the replay.

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from convbki_core.tools.cli import UserError, run
from convbki_ros.dds import use_large_data_profile
from convbki_ros.ros_args import only_ros_args, strip_ros_args
from convbki_ros.tools.bag_reading import checked_messages, grouped, open_bag, rclpy_message_class, to_rclpy

PROG = "play_bag"
NODE_NAME = "play_bag"
CLOCK_TOPIC = "/clock"
DEPTH = 100
LATCHED_TOPICS = ("/tf_static",)  # replayed transient local, whatever the bag recorded
NOT_DELIVERED = 1  # exit code: some messages were not acknowledged by a subscriber
BEHIND_S = 1.0  # this far behind the bag's pace (in wall seconds), the replay resumes from where it is
FLUSH_TIMEOUT_S = 10.0  # how long the end waits for acknowledgements
SETTLE_S = 3.0  # after a pause: how long to watch for subscribers that DDS expires on resuming (an announcement period)
REDISCOVERY_S = 10.0  # after a pause: how long to wait for them to be found again
MATCHING_S = 10.0  # at the start: how much longer to wait for a subscriber already discovered to match
# At the start, once the player's writers have matched: the subscriber's side matches them a
# moment later (on a loaded machine, most of a second), and volatile messages sent in between
# reach no one although the writer counts them delivered.
MATCH_GRACE_S = 1.0
DEFAULT_NODE = "/convbki_mapper"
NODE_SILENT_S = 15.0  # with --wait-for-node: the node sent no /diagnostics for this long: it is gone
LOST_AFTER_S = 10.0  # with --wait-for-node: clouds the node has not received after this long without progress are lost
NODE_START_TIMEOUT_S = 120.0  # a node on a fresh install compiles its kernels before it reports
# Message types sent from the bulk participant (see the module's docstring).
BULK_TYPES = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointCloud", "sensor_msgs/msg/Image",
              "sensor_msgs/msg/CompressedImage")


def rate_arg(text: str) -> float:
    """Playback rate: a positive float."""
    try:
        rate = float(text)
    except ValueError:
        rate = -1.0
    if not rate > 0.0 or rate == float("inf"):
        raise argparse.ArgumentTypeError(f"rate must be a positive number, got {text!r}")
    return rate


def seconds_arg(text: str) -> float:
    """A duration in seconds: a finite float >= 0."""
    try:
        seconds = float(text)
    except ValueError:
        seconds = -1.0
    if not 0.0 <= seconds < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text!r}")
    return seconds


def remap_arg(text: str) -> tuple[str, str]:
    """``FROM:=TO`` -> (FROM, TO)."""
    src, sep, dst = text.partition(":=")
    if not sep or not src or not dst:
        raise argparse.ArgumentTypeError(f"remap must be FROM:=TO, got {text!r}")
    return src, dst


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser; ROS arguments (--ros-args ...) are removed before it runs."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Publish the messages of a rosbag2 (mcap or sqlite3) on their topics "
        "in stamp order, paced by the stamps. ROS arguments (--ros-args -r ... ) are passed "
        "to the node. Exits 0 when every message is out and acknowledged by its subscribers (or on "
        "Ctrl-C), 1 when some were not (the topic and the count are named) or, with --wait-for-node, "
        "when the node did not receive or dropped clouds.",
    )
    p.add_argument("bag", metavar="BAG", help="bag directory (or its .mcap/.db3 file)")
    p.add_argument("--rate", default=None, type=rate_arg, metavar="R",
                   help="playback speed factor: 1 = real time, 2 = twice as fast "
                   "(default: 1, or as fast as the node keeps up with --wait-for-node)")
    p.add_argument("--wait-for-node", nargs="?", const=DEFAULT_NODE, default=None, metavar="NODE",
                   help="pace the clouds to the progress of NODE (fully qualified, default "
                   f"{DEFAULT_NODE}) as its /diagnostics report it: at most half of its cloud queue in flight, "
                   "none dropped; at the end, wait until it has taken every cloud and print what it did")
    p.add_argument("--wait-for-inputs", nargs="?", const=DEFAULT_NODE, default=None, metavar="NODE",
                   help="before the first message, wait until NODE (default "
                   f"{DEFAULT_NODE}) reports on /diagnostics a matched publisher on each of its inputs, so "
                   "that its first messages cannot be lost to DDS still matching the node's side (implied "
                   "by --wait-for-node; without either, a fixed second is given instead)")
    p.add_argument("--clock", action="store_true",
                   help="also publish /clock (rosgraph_msgs/Clock) from the bag stamps, "
                   "for nodes run with use_sim_time:=true")
    p.add_argument("--remap", action="append", default=[], type=remap_arg,
                   metavar="FROM:=TO",
                   help="publish topic FROM of the bag on topic TO; repeatable")
    p.add_argument("--qos", default="reliable", choices=("reliable", "best_effort"),
                   help=f"reliability of the publishers (keep last {DEPTH}, volatile); reliable suits "
                   "replay into a mapper, best_effort mimics a live sensor (default: %(default)s)")
    p.add_argument("--wait-subscribers", default=3.0, type=seconds_arg, metavar="S",
                   help="before the first message, wait up to S seconds for every topic to "
                   "have a subscriber (stops waiting 1 s after the first one matches), so "
                   "the first messages are not lost (default: %(default)s)")
    p.add_argument("--start-delay", default=0.0, type=seconds_arg, metavar="S",
                   help="sleep S seconds more before the first message (default: %(default)s; once "
                   "subscribers matched, a second is given for their side to match too, unless "
                   "--wait-for-inputs or --wait-for-node saw it match)")
    p.add_argument("--deserialize", action="store_true",
                   help="always deserialise and convert messages to the installed types "
                   "(slower; by default the bag's bytes are published unchanged when the "
                   "type hashes match)")
    return p


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


def _count(values: dict[str, str], key: str, default: int = 0) -> int:
    """A diagnostic value as a count (``default`` when missing or not a number)."""
    try:
        return int(values.get(key, default))
    except ValueError:
        return default


class NodeGone(Exception):
    """The node the replay is paced to stopped reporting."""


@dataclass
class NodeProgress:
    """What one /diagnostics report of the paced node says."""

    scans_in: int
    integrated: int
    dropped: int
    queue: int
    queue_limit: int
    reasons: dict[str, int]
    publishers: dict[str, int]  # per input of the node: the publishers its reader has matched


class NodePacer:
    """Paces the clouds to a mapper's progress as its /diagnostics report it (``--wait-for-node``).

    Clouds in flight are those sent that the node has not yet reported received, plus those in
    its queue; at most half of the node's queue (and of the writers' history) is let in flight,
    so neither the DDS histories nor the node's queue can overflow, whatever its speed.
    """

    def __init__(self, node: Any, target: str):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        self.target = target
        self.latest: NodeProgress | None = None
        self.heard = time.monotonic()
        self.baseline: NodeProgress | None = None
        self.published = 0
        self.lost = 0  # clouds given up as lost: sent, never received by the node
        self.progress_at = time.monotonic()  # when the node last received a cloud, or one was sent
        self.received_seen = 0
        self.dropped = self.missing = 0  # set by finish()
        self.first_sent: float | None = None
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_diagnostics(self, array: Any) -> None:
        for status in array.status:
            if status.name.split(":")[0] != self.target:
                continue
            values = {item.key: item.value for item in status.values}
            reasons = {key[len("dropped."):]: _count(values, key) for key in values if key.startswith("dropped.")}
            publishers = {key[len("publishers."):]: _count(values, key) for key in values
                          if key.startswith("publishers.")}
            self.latest = NodeProgress(_count(values, "scans_in"), _count(values, "integrated"),
                                       _count(values, "dropped"), _count(values, "queue"),
                                       _count(values, "queue_limit", 40), reasons, publishers)
            self.heard = time.monotonic()

    def _spin(self, seconds: float) -> None:
        self.executor.spin_once(timeout_sec=seconds)

    def wait_for_node(self, timeout: float, ok: Callable[[], bool]) -> bool:
        """Block until the node has reported once; False when ``ok()`` turned False."""
        deadline = time.monotonic() + timeout
        while self.latest is None:
            if not ok():
                return False
            if time.monotonic() > deadline:
                raise UserError(f"no /diagnostics from {self.target} within {timeout:g} s (is it running? "
                                "--wait-for-node takes its fully qualified name, e.g. /convbki_mapper)")
            self._spin(0.1)
        self.baseline = self.latest
        return True

    def wait_for_inputs(self, timeout: float, ok: Callable[[], bool]) -> list[str]:
        """Block until the node reports a matched publisher on each of its inputs (its readers
        have matched the player's writers, so nothing sent from now on is lost to matching), or
        ``timeout``; the inputs still without one. A node that reports no inputs has none to wait for."""
        deadline = time.monotonic() + timeout
        while True:
            unmatched = sorted(name for name, count in self.latest.publishers.items() if count < 1)
            if not unmatched or time.monotonic() > deadline or not ok():
                return unmatched
            self._spin(0.05)

    @property
    def window(self) -> int:
        assert self.latest is not None
        return max(1, min(DEPTH, self.latest.queue_limit) // 2)

    def received(self) -> int:
        assert self.latest is not None and self.baseline is not None
        received = self.latest.scans_in - self.baseline.scans_in
        if received > self.received_seen:
            self.received_seen, self.progress_at = received, time.monotonic()
        return received

    def in_flight(self) -> int:
        return max(0, self.published - self.lost - self.received()) + self.latest.queue

    def _give_up_stalled(self) -> bool:
        """Clouds sent that the node has not received while it went LOST_AFTER_S without
        receiving any are lost (DDS lost them, e.g. after the player was stopped): counted, and
        the replay goes on. True when some were given up now."""
        waiting = self.published - self.lost - self.received()
        if waiting <= 0 or time.monotonic() - self.progress_at < LOST_AFTER_S:
            return False
        self.lost += waiting
        self.progress_at = time.monotonic()
        return True

    def _check_alive(self) -> None:
        silent = time.monotonic() - self.heard
        if silent > NODE_SILENT_S:
            raise NodeGone(f"{self.target} sent no /diagnostics for {silent:.0f} s after {self.published} clouds")

    def wait_for_room(self, clouds: int, ok: Callable[[], bool]) -> bool:
        """Block until ``clouds`` more fit in flight; False when ``ok()`` turned False."""
        self._spin(0.0)
        while self.in_flight() + clouds > self.window:
            if not ok():
                return False
            self._check_alive()
            self._give_up_stalled()
            self._spin(0.05)
        return True

    def sent(self, clouds: int) -> None:
        if self.first_sent is None:
            self.first_sent = time.monotonic()
        self.published += clouds
        self.progress_at = time.monotonic()

    def finish(self, ok: Callable[[], bool]) -> str:
        """Wait until the node has received every cloud sent and emptied its queue (or stops
        reporting); what it did with them, in one line."""
        while ok():
            latest = self.latest
            received = self.received()
            if received >= self.published - self.lost and latest.integrated + latest.dropped >= latest.scans_in:
                break  # every cloud sent arrived (or was given up), every one that arrived was dealt with
            self._check_alive()
            self._give_up_stalled()
            self._spin(0.1)
        latest, baseline = self.latest, self.baseline
        dropped = latest.dropped - baseline.dropped
        reasons = ", ".join(f"{reason} {count - baseline.reasons.get(reason, 0)}"
                            for reason, count in sorted(latest.reasons.items())
                            if count > baseline.reasons.get(reason, 0))
        self.dropped = dropped
        self.missing = self.published - (latest.scans_in - baseline.scans_in)
        took = f" in {time.monotonic() - self.first_sent:.2f} s from the first" if self.first_sent else ""
        return (f"{self.target} received {latest.scans_in - baseline.scans_in} of {self.published} clouds, "
                f"integrated {latest.integrated - baseline.integrated}, dropped {dropped}"
                f"{f' ({reasons})' if reasons else ''}{took}")


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
        try:
            messages = checked_messages(self.reader.messages(connections=wanted), str(self.args.bag))
            for timestamp, group in grouped(messages):
                if start_wall is None:
                    start_wall, first_stamp = time.monotonic(), timestamp
                if previous is None or timestamp >= previous:
                    target = start_wall + (timestamp - first_stamp) / 1e9 / rate
                    if not _sleep_until(target, ok):
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


def _sleep_until(target: float, ok: Callable[[], bool]) -> bool:
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
    return tqdm(total=total, desc=PROG, unit="msg", file=sys.stderr, dynamic_ncols=True, mininterval=1.0)


def play(args: argparse.Namespace, ros_argv: list[str]) -> int:
    """The command's body: open the bag, start rclpy, publish, shut down."""
    reader = open_bag(args.bag)
    try:
        import rclpy
        from rclpy.executors import ExternalShutdownException

        bulk_context = rclpy.Context()
        try:
            use_large_data_profile(player=True)
            rclpy.init(args=ros_argv)
            rclpy.init(args=ros_argv, context=bulk_context)
        except Exception as error:  # rclpy's errors for bad --ros-args have no common public base
            raise UserError(f"cannot start ROS 2 ({str(error).strip().splitlines()[0]})") from None
        node = bulk_node = player = None
        started = time.monotonic()
        code = 0
        try:
            node = rclpy.create_node(NODE_NAME)
            bulk_node = rclpy.create_node(f"{NODE_NAME}_bulk", context=bulk_context)
            watched = args.wait_for_node or args.wait_for_inputs
            watch = NodePacer(node, watched) if watched else None
            if watch is not None and not watch.wait_for_node(NODE_START_TIMEOUT_S, rclpy.ok):
                return 0
            pacer = watch if args.wait_for_node else None
            player = BagPlayer(node, reader, args, bulk_node, pacer)
            matched = player.wait_for_subscribers(args.wait_subscribers)
            confirmed = False  # the node said its readers matched the player's writers
            if matched and watch is not None:
                unmatched = watch.wait_for_inputs(args.wait_subscribers + MATCHING_S, rclpy.ok)
                confirmed = not unmatched
                if unmatched:
                    node.get_logger().info(f"{watched} reports no publisher matched on {', '.join(unmatched)}; "
                                           "starting anyway")
            delay = args.start_delay + (MATCH_GRACE_S if matched and not confirmed else 0.0)
            if delay > 0 and not _sleep_until(time.monotonic() + delay, rclpy.ok):
                return 0
            started = time.monotonic()
            sent = player.play(rclpy.ok)
            elapsed = time.monotonic() - started
            finished = rclpy.ok()
            problems = player.flush() if finished else []
            counts = ", ".join(f"{c.topic} {c.count}" for c in player.channels.values() if not c.skipped)
            what = "published" if finished else "interrupted after"
            print(f"{PROG}: {what} {sent} messages in {elapsed:.2f} s ({counts})", file=sys.stderr)
            if player.pauses:
                print(f"{PROG}: resumed {len(player.pauses)} time(s) after falling behind the bag's pace (stopped "
                      f"or stalled), the longest {max(player.pauses):.1f} s; the replay went on at its pace from "
                      "there", file=sys.stderr)
            for topic, seconds in player.forgotten:
                print(f"{PROG}: after the stop, DDS had forgotten the subscribers of {topic} (their lease ran out "
                      f"while the player was stopped) and found them again within {seconds:.1f} s; messages "
                      "sent meanwhile may not have reached them", file=sys.stderr)
            if finished and pacer is not None:
                print(f"{PROG}: {pacer.finish(rclpy.ok)}", file=sys.stderr)
                if pacer.missing:
                    problems.append(f"{pacer.target} did not receive {pacer.missing} of the {pacer.published} "
                                    "clouds")
                if pacer.dropped:
                    problems.append(f"{pacer.target} dropped {pacer.dropped} clouds")
            for problem in problems:
                print(f"{PROG}: error: {problem}", file=sys.stderr)
            code = NOT_DELIVERED if problems else 0
        except NodeGone as gone:
            print(f"{PROG}: error: {gone}; stopping the replay", file=sys.stderr)
            code = NOT_DELIVERED
        except (KeyboardInterrupt, ExternalShutdownException):
            sent = player.sent if player is not None else 0
            print(f"{PROG}: interrupted after {sent} messages in {time.monotonic() - started:.2f} s", file=sys.stderr)
        finally:
            for each in (node, bulk_node):
                if each is not None:
                    each.destroy_node()
            rclpy.try_shutdown()
            bulk_context.try_shutdown()
    finally:
        reader.close()
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    return run(PROG, lambda parsed: play(parsed, [PROG, *only_ros_args(args)]), build_parser(), strip_ros_args(args))


if __name__ == "__main__":
    sys.exit(main())

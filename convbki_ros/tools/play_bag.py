"""``play_bag``: publish a rosbag2 on its topics, in stamp order (no ros2 bag needed).

Messages go out at ``--rate`` x the pace of their bag timestamps, timed against one
monotonic start instant (no drift accumulates). Messages sharing a timestamp go out
together, transforms and odometry before the clouds that need them. With ``--clock``,
/clock (rosgraph_msgs/Clock) carries each timestamp just before the messages stamped with it.

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
from convbki_ros.ros_args import strip_ros_args
from convbki_ros.tools.bag_reading import checked_messages, grouped, open_bag, rclpy_message_class, to_rclpy

PROG = "play_bag"
NODE_NAME = "play_bag"
CLOCK_TOPIC = "/clock"
DEPTH = 100
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
        "to the node. Exits 0 when every message is out (or on Ctrl-C).",
    )
    p.add_argument("bag", metavar="BAG", help="bag directory (or its .mcap/.db3 file)")
    p.add_argument("--rate", default=1.0, type=rate_arg, metavar="R",
                   help="playback speed factor: 1 = real time, 2 = twice as fast "
                   "(default: %(default)s)")
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
                   help="sleep S seconds more before the first message (default: %(default)s)")
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


def _priority(msgtype: str) -> int:
    if msgtype.startswith(("tf2_msgs/", "nav_msgs/msg/Odometry", "geometry_msgs/msg/Transform")):
        return 0
    if msgtype.startswith("sensor_msgs/msg/PointCloud2"):
        return 2
    return 1


class BagPlayer:
    """Publishes one open bag through ``node``, its bulky messages through ``bulk_node`` (a node
    of another rclpy context, so another DDS participant; default: ``node``)."""

    def __init__(self, node: Any, reader: Any, args: argparse.Namespace, bulk_node: Any = None):
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.node = node
        self.bulk_node = bulk_node or node
        self.reader = reader
        self.args = args
        reliability = ReliabilityPolicy.RELIABLE if args.qos == "reliable" else ReliabilityPolicy.BEST_EFFORT
        self.qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=reliability,
                              durability=DurabilityPolicy.VOLATILE)
        self.remaps = dict(args.remap)
        self.channels: dict[int, Channel] = {}
        self.publishers: dict[tuple[str, str], Any] = {}
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
            self.publishers[key] = owner.create_publisher(channel.cls, topic, self.qos)
        channel.publisher = self.publishers[key]
        channel.raw = not self.args.deserialize and self._same_type(owner, channel.publisher, connection.digest)
        if not channel.raw:
            self._ensure_typestore()
        return channel

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

    def wait_for_subscribers(self, timeout: float) -> None:
        """Block until every publisher has a subscriber, or ``timeout``. Topics nobody subscribes
        to are given up 1 s after the first match; one whose subscriber either participant has
        already discovered is waited for (the other participant is still matching it)."""
        publishers = [*self.publishers.values(), *([self.clock_publisher] if self.clock_publisher else [])]
        if not publishers or timeout <= 0:
            return
        deadline = time.monotonic() + timeout
        first_match = None
        while time.monotonic() < deadline:
            pending = [p for p in publishers if p.get_subscription_count() == 0]
            if not pending:
                return
            if len(pending) < len(publishers) and first_match is None:
                first_match = time.monotonic()
            discovered = [p for p in pending if any(node.count_subscribers(p.topic_name)
                                                    for node in {self.node, self.bulk_node})]
            if not discovered and first_match is not None and time.monotonic() - first_match > 1.0:
                break
            time.sleep(0.02)
        missing = [p.topic_name for p in publishers if p.get_subscription_count() == 0]
        if missing:
            self.node.get_logger().info(f"starting with no subscriber on {', '.join(missing)}")

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
        start_wall = None
        first_stamp = None
        previous = None
        try:
            messages = checked_messages(self.reader.messages(connections=wanted), str(self.args.bag))
            for timestamp, group in grouped(messages):
                if start_wall is None:
                    start_wall, first_stamp = time.monotonic(), timestamp
                if previous is None or timestamp >= previous:
                    target = start_wall + (timestamp - first_stamp) / 1e9 / self.args.rate
                    if not _sleep_until(target, ok):
                        break
                    previous = timestamp
                # else: out of order in the bag (split files): publish at once, keep the clock monotonic
                self._publish_clock(max(timestamp, previous))
                for connection, data in sorted(group, key=lambda item: self.channels[item[0].id].priority):
                    self._publish(self.channels[connection.id], data, timestamp)
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

    def flush(self, timeout: float = 5.0) -> None:
        """Wait (bounded) until reliable subscribers acknowledged everything published."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout
        for publisher in [*self.publishers.values(), self.clock_publisher]:
            if publisher is None:
                continue
            left = max(0.0, deadline - time.monotonic())
            with contextlib.suppress(Exception):  # best effort publishers, or an rmw without acks
                publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))


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
            use_large_data_profile()
            rclpy.init(args=ros_argv)
            rclpy.init(args=ros_argv, context=bulk_context)
        except Exception as error:  # rclpy's errors for bad --ros-args have no common public base
            raise UserError(f"cannot start ROS 2 ({str(error).strip().splitlines()[0]})") from None
        node = bulk_node = player = None
        started = time.monotonic()
        try:
            node = rclpy.create_node(NODE_NAME)
            bulk_node = rclpy.create_node(f"{NODE_NAME}_bulk", context=bulk_context)
            player = BagPlayer(node, reader, args, bulk_node)
            player.wait_for_subscribers(args.wait_subscribers)
            if args.start_delay > 0 and not _sleep_until(time.monotonic() + args.start_delay, rclpy.ok):
                return 0
            started = time.monotonic()
            sent = player.play(rclpy.ok)
            elapsed = time.monotonic() - started
            finished = rclpy.ok()
            if finished:
                player.flush()
            counts = ", ".join(f"{c.topic} {c.count}" for c in player.channels.values() if not c.skipped)
            what = "published" if finished else "interrupted after"
            print(f"{PROG}: {what} {sent} messages in {elapsed:.2f} s ({counts})", file=sys.stderr)
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
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    return run(PROG, lambda parsed: play(parsed, [PROG, *args]), build_parser(), strip_ros_args(args))


if __name__ == "__main__":
    sys.exit(main())

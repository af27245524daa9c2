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
``/diagnostics`` report a matched publisher on each of its inputs (``pose_corrections`` only
when the bag holds a Path: a SLAM's one Path of a loop closure lost to matching would leave the
map uncorrected).

The player tells the truth about delivery: at the end it waits for every subscriber to
acknowledge every reliable message, and exits 1, naming the topic and the count, when some
were not acknowledged or a subscriber went away during the replay.

This module is the command line and the run; the bag is read by ``bag_reading``, published by
``bag_player`` (raw or converted messages, the bulk participant) and paced by ``node_pacing``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from convbki_core.tools.cli import UserError, run
from convbki_ros.dds import use_large_data_profile
from convbki_ros.ros_args import only_ros_args, strip_ros_args
from convbki_ros.tools.bag_player import DEPTH, MATCHING_S, BagPlayer, sleep_until
from convbki_ros.tools.bag_reading import open_bag
from convbki_ros.tools.node_pacing import NodeGone, NodePacer

PROG = "play_bag"
NODE_NAME = "play_bag"
NOT_DELIVERED = 1  # exit code: some messages were not acknowledged by a subscriber
# At the start, once the player's writers have matched: the subscriber's side matches them a
# moment later (on a loaded machine, most of a second), and volatile messages sent in between
# reach no one although the writer counts them delivered.
MATCH_GRACE_S = 1.0
DEFAULT_NODE = "/convbki_mapper"
NODE_START_TIMEOUT_S = 120.0  # a node on a fresh install compiles its kernels before it reports
# Inputs of the node that a bag often has nothing for, by the message type that feeds them: the
# player waits for the node's reader of one only when the bag plays that type.
OPTIONAL_INPUTS = {"pose_corrections": "nav_msgs/msg/Path"}


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
                unplayed = [name for name, msgtype in OPTIONAL_INPUTS.items() if not player.plays(msgtype)]
                unmatched = watch.wait_for_inputs(args.wait_subscribers + MATCHING_S, rclpy.ok, unplayed)
                confirmed = not unmatched
                if unmatched:
                    node.get_logger().info(f"{watched} reports no publisher matched on {', '.join(unmatched)}; "
                                           "starting anyway")
            delay = args.start_delay + (MATCH_GRACE_S if matched and not confirmed else 0.0)
            if delay > 0 and not sleep_until(time.monotonic() + delay, rclpy.ok):
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

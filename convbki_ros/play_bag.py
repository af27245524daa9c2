"""``play_bag``: publish a rosbag2 on its topics, in stamp order (no ros2 bag needed)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

PROG = "play_bag"
ISSUE = 4


def strip_ros_args(argv: Sequence[str]) -> list[str]:
    """Remove ROS arguments (``--ros-args ... [--]``) from ``argv``, as rclpy does."""
    out: list[str] = []
    in_ros = False
    for arg in argv:
        if arg == "--ros-args":
            in_ros = True
        elif in_ros and arg == "--":
            in_ros = False
        elif not in_ros:
            out.append(arg)
    return out


def rate_arg(text: str) -> float:
    """Playback rate: a positive float."""
    try:
        rate = float(text)
    except ValueError:
        rate = -1.0
    if not rate > 0.0:
        raise argparse.ArgumentTypeError(f"rate must be a positive number, got {text!r}")
    return rate


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
        "in stamp order, paced by the stamps.",
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
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    build_parser().parse_args(strip_ros_args(args))
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

"""Command-line helpers shared by the ROS executables."""

from __future__ import annotations

from collections.abc import Sequence


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

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


def only_ros_args(argv: Sequence[str]) -> list[str]:
    """The ``--ros-args ... [--]`` parts of ``argv``, each closed: what to give ``rclpy.init``.
    The rest stays out of rcl, which would otherwise warn about a tool's own ``a:=b`` options
    as remap rules in a deprecated syntax."""
    out: list[str] = []
    in_ros = False
    for arg in argv:
        if arg == "--ros-args":
            in_ros = True
            out.append(arg)
        elif in_ros and arg == "--":
            in_ros = False
            out.append(arg)
        elif in_ros:
            out.append(arg)
    return out

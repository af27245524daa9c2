"""``mapper``: the ConvBKI semantic mapping node (``convbki_mapper``).

Run with ``ros2 run convbki_ros mapper --ros-args --params-file config/mapper.yaml``
or ``python -m convbki_ros.mapper --ros-args ...``.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence

PROG = "mapper"
NODE_NAME = "convbki_mapper"
ISSUE = 4

# (name, default, meaning and unit): the node's parameters, as in config/mapper.yaml.
PARAMETERS: tuple[tuple[str, object, str], ...] = (
    ("kernel_file", "",
     "kernel file (YAML); \"\" = the shipped compound kernel "
     "(share/convbki_ros/config/kernels/semantic_kitti_compound.yaml)"),
    ("num_classes", 20, "number of semantic classes C, class 0 = unlabeled; count"),
    ("resolution", 0.2, "voxel edge length; metres"),
    ("filter_size", 5, "convolution filter edge f (odd); voxels"),
    ("local_bounds", [-40.0, -40.0, -2.6, 40.0, 40.0, 2.6],
     "local map window around the sensor, [min_x, min_y, min_z, max_x, max_y, max_z]; "
     "metres"),
    ("prior", 0.001, "Dirichlet prior concentration of every class in every voxel; unitless"),
    ("label_space", "raw",
     "meaning of the input `label` field: raw (SemanticKITTI raw ids) or learning "
     "(0..num_classes-1)"),
    ("map_frame", "map", "frame id of the published map"),
    ("max_variance", 0.0,
     "leave out voxels whose variance of the expected class exceeds this; unitless; "
     "0.0 = no filter"),
    ("publish_period", 1.0, "period of the /semantic_map publisher; seconds"),
    ("device", "auto", "torch device: auto (CUDA when present, else CPU), cpu, cuda[:N]"),
    ("input_qos", "reliable",
     "QoS of cloud_in and odom: reliable (bag replay) or sensor_data (live, best effort)"),
    ("map_file", "",
     "map file loaded at start when present, written by ~/save_map; \"\" = none; path"),
    ("autosave_period", 0.0, "save the map to map_file every this many seconds; 0.0 = never"),
)


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


def _epilog() -> str:
    lines = [
        f"ROS 2 node {NODE_NAME}.",
        "",
        "topics:",
        "  subscribes cloud_in (sensor_msgs/PointCloud2: x, y, z and label or prob_0..prob_{C-1})",
        "             odom (nav_msgs/Odometry: pose of the cloud's frame)",
        "  publishes  /semantic_map (PointCloud2: x, y, z, rgb, label, variance, confidence;"
        " latched)",
        "             /semantic_map/variance (PointCloud2: x, y, z, intensity = variance)",
        "             /semantic_map/local (PointCloud2: the local window after each update)",
        "services: ~/save_map (Trigger), ~/reset, ~/export_ply (Trigger)",
        "",
        "parameters (name (default): meaning; unit):",
    ]
    for name, default, meaning in PARAMETERS:
        shown = '""' if default == "" else default
        lines.append(f"  {name} ({shown})")
        lines += textwrap.wrap(meaning, 86, initial_indent=" " * 6, subsequent_indent=" " * 6)
    lines += [
        "",
        "parameters are ROS parameters, not flags; pass them after --ros-args:",
        f"  ros2 run convbki_ros {PROG} --ros-args --params-file "
        "$(ros2 pkg prefix convbki_ros)/share/convbki_ros/config/mapper.yaml",
        f"  ros2 run convbki_ros {PROG} --ros-args -p resolution:=0.1 -p device:=cpu",
        "  remap topics with --ros-args -r cloud_in:=/kitti/velo/pointcloud -r odom:=/kitti/odom",
    ]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser; ROS arguments are removed before it runs."""
    return argparse.ArgumentParser(
        prog=PROG,
        description="ConvBKI online 3D semantic mapping node: integrates labelled LiDAR "
        "clouds at their odometry poses into a voxel map and publishes it.",
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        usage=f"{PROG} [-h] [--ros-args ROS_ARGS ...]",
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    build_parser().parse_args(strip_ros_args(args))
    print(f"{PROG}: not implemented yet (see issue {ISSUE})", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

"""``mapper``: the ConvBKI semantic mapping node (``convbki_mapper``).

Run with ``ros2 run convbki_ros mapper --ros-args --params-file config/mapper.yaml``
or ``python -m convbki_ros.main --ros-args ...``. The node itself is
``convbki_ros.node.MapperNode``; this module is its command line: ``--help`` (which needs no
ROS 2), start-up errors as one line with exit code 2, a single-threaded executor (the node
writes and reads files on a thread of its own, so a large save never holds up the inputs),
and exit code 1 when the map could not be saved on the way out (a supervisor or launch file
must learn that the session's map is lost).

Why not rclpy's MultiThreadedExecutor: its dispatch loop runs in Python under the GIL, and
with clouds and odometry arriving at 10 Hz it held the GIL most of the time, so the update
thread's scans took up to 1.4 s instead of 40 ms.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import textwrap
from collections.abc import Sequence

import yaml

from convbki_core.io.kernel_file import KernelFileError
from convbki_core.io.map_file import MapFileError
from convbki_ros.dds import publish_asynchronously, use_large_data_profile
from convbki_ros.params import NODE_NAME, NOT_SET, PARAMETERS, StartupError
from convbki_ros.ros_args import strip_ros_args

PROG = "mapper"
SAVE_FAILED = 1  # exit code: the save on shutdown failed


def _epilog() -> str:
    lines = [
        f"ROS 2 node {NODE_NAME}.",
        "",
        "topics (relative names: a namespaced node publishes under its namespace):",
        "  subscribes cloud_in (sensor_msgs/PointCloud2: x, y, z and label or prob_0..prob_{C-1})",
        "             odom (nav_msgs/Odometry: pose of child_frame_id in header.frame_id)",
        "  publishes  semantic_map (PointCloud2: x, y, z, rgb, label, variance, confidence; latched)",
        "             semantic_map/variance (PointCloud2: x, y, z, intensity = variance; latched)",
        "             semantic_map/updates (PointCloud2: the voxels that changed, label 0 = left the map)",
        "             semantic_map/view (PointCloud2: the map around the sensor; latched)",
        "             semantic_map/local (PointCloud2: the window around the sensor after updates)",
        "             /diagnostics (diagnostic_msgs/DiagnosticArray: counters, queue, timings; 1 Hz)",
        "services (std_srvs/Trigger): ~/save_map (writes map_file; the file it replaces becomes <map_file>.prev),",
        "          ~/load_map (replaces the map with map_file's), ~/reset, ~/clear_box (forgets the voxels",
        "          between clear_box_min and clear_box_max), ~/export_ply",
        "",
        "frames: the map is built in the odometry's frame. A cloud in the odometry's child frame is",
        "placed with the odometry; a cloud in another frame (a LiDAR mounted on base_link) also needs",
        "the mount: parameter base_to_sensor, or TF's /tf_static where tf2_ros is installed.",
        "",
        "start: every kernel is compiled (or loaded from numba's cache) before the node subscribes and says",
        "ready; NUMBA_CACHE_DIR moves the cache. map_file's folder is made, or refused (exit code 2) when it",
        "cannot be written. exit codes: 0, 2 bad start-up input, 1 the map could not be saved on shutdown.",
        "",
        "parameters (name (default): meaning; unit):",
    ]
    for spec in PARAMETERS:
        shown = '""' if spec.default == "" else "unset" if spec.default is NOT_SET else spec.default
        lines.append(f"  {spec.name} ({shown})")
        lines += textwrap.wrap(spec.describe(), 86, initial_indent=" " * 6, subsequent_indent=" " * 6)
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


def check_params_files(argv: Sequence[str]) -> None:
    """Every ``--params-file`` after ``--ros-args`` exists and is a YAML mapping (rcl would say
    so over several lines of its own)."""
    in_ros = False
    for position, arg in enumerate(argv):
        in_ros = (in_ros or arg == "--ros-args") and arg != "--"
        if not (in_ros and arg == "--params-file"):
            continue
        if position + 1 >= len(argv):
            raise StartupError("--params-file needs a file name")
        path = argv[position + 1]
        try:
            with open(path, encoding="utf-8") as stream:
                content = yaml.safe_load(stream)
        except OSError as error:
            raise StartupError(f"params file {path}: {error.strerror or error}") from None
        except (yaml.YAMLError, UnicodeDecodeError) as error:
            raise StartupError(f"params file {path} is not valid YAML: {' '.join(str(error).split())}") from None
        if not isinstance(content, dict) or not all(isinstance(v, dict) and "ros__parameters" in v
                                                    for v in content.values()):
            raise StartupError(f"params file {path}: expected '<node name or /**>: ros__parameters: {{...}}'")


def init_rclpy(rclpy, args: list[str]) -> None:
    """``rclpy.init`` with rcl's own error lines held back: a failure is one line of ours."""
    with tempfile.TemporaryFile(mode="w+") as captured:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)
        try:
            rclpy.init(args=args)
            failure = None
        except Exception as error:  # RCLError: unparsable arguments or params file
            failure = error
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        held_back = captured.read()
    if failure is not None:
        reason = " ".join(str(failure).split()).split(", at ")[0]
        raise StartupError(f"ROS 2 could not start: {reason}")
    if held_back:
        sys.stderr.write(held_back)


def spin(rclpy, executor, node) -> None:
    """``executor.spin()`` that outlives a failed callback: the node guards each of its own
    (``convbki_ros.guard``); whatever still reaches the executor is logged and counted the same
    way, and spinning goes on until the context shuts down (Ctrl-C, SIGTERM)."""
    from rclpy.executors import ExternalShutdownException

    while rclpy.ok():
        try:
            executor.spin_once()
        except (KeyboardInterrupt, ExternalShutdownException):
            return
        except Exception as error:
            if not rclpy.ok():
                return  # the context went down under the executor: a shutdown
            node.guard.failed("the executor", error)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    build_parser().parse_args(strip_ros_args(args))
    try:
        check_params_files(args)
        import rclpy
        from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        use_large_data_profile()
        publish_asynchronously()  # a large map being sent must not stall the update thread
        init_rclpy(rclpy, [sys.argv[0], *args])
    except StartupError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    from convbki_ros.node import MapperNode

    node = None
    saved = True
    try:
        # The executor exists before the node says "ready", so a Ctrl-C right after it lands in spin().
        executor = SingleThreadedExecutor()
        try:
            node = MapperNode()
        except (ValueError, KernelFileError, MapFileError, OSError) as error:  # StartupError is a ValueError
            print(f"{PROG}: error: {error}", file=sys.stderr)
            return 2
        except _rclpy.RCLError as error:  # e.g. ROS_SECURITY_ENABLE with a DDS built without security
            reason = " ".join(str(error).split()).split(", at ")[0]
            print(f"{PROG}: error: ROS 2 could not create the node: {reason}", file=sys.stderr)
            return 2
        executor.add_node(node)
        spin(rclpy, executor, node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # Ctrl-C shuts the context down from the signal handler; an executor that was just
        # building its wait set then fails with an RCLError. That is a shutdown, not a crash.
        if rclpy.ok():
            raise
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the save short
        if node is not None:
            saved = node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0 if saved else SAVE_FAILED


if __name__ == "__main__":
    sys.exit(main())

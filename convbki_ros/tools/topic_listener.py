"""A watcher of one topic, the way RViz or ``ros2 topic echo`` subscribes it (used by ``realtime_check``).

An rclpy node subscribes ``--topic`` with a reliable QoS, ``--qos latched`` (transient local,
what RViz uses for a latched map) or ``volatile``, keeping the last ``--depth`` messages. It
prints ``listener ready`` once subscribed, then one line per message received:
``message MONOTONIC_S WIDTH BYTES`` (WIDTH and BYTES: the PointCloud2's points and data size,
or an OccupancyGrid's width and cells).
SIGINT or SIGTERM ends it. Like a user who follows the README for RViz, it uses the package's
large-data Fast DDS profile unless one is chosen in the environment.

    .venv/bin/python -m convbki_ros.tools.topic_listener --topic /semantic_map --qos latched --depth 1
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import time
from collections.abc import Sequence


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="topic_listener", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--topic", required=True, help="topic to subscribe, e.g. /semantic_map")
    p.add_argument("--qos", choices=("latched", "volatile"), default="volatile",
                   help="durability: latched = transient local, volatile (default: %(default)s); always reliable")
    p.add_argument("--depth", type=int, default=1, help="keep-last history depth (default: %(default)s)")
    p.add_argument("--type", default="sensor_msgs/msg/PointCloud2",
                   help="message type as package/msg/Name (default: %(default)s)")
    return p


def _message_class(name: str):
    package, kind, cls = name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), cls)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from convbki_ros.dds import use_large_data_profile

    use_large_data_profile()
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    message_class = _message_class(args.type)
    rclpy.init()
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    node = rclpy.create_node(f"topic_listener_{args.topic.strip('/').replace('/', '_')}")
    durability = DurabilityPolicy.TRANSIENT_LOCAL if args.qos == "latched" else DurabilityPolicy.VOLATILE
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.depth, reliability=ReliabilityPolicy.RELIABLE,
                     durability=durability)

    def received(msg) -> None:
        # A cloud's points, or a grid's cells (OccupancyGrid keeps its width in info).
        width = msg.width if hasattr(msg, "width") else getattr(getattr(msg, "info", None), "width", 0)
        print(f"message {time.monotonic():.3f} {width} {len(getattr(msg, 'data', b''))}", flush=True)

    node.create_subscription(message_class, args.topic, received, qos)
    print(f"listener ready: {args.topic} ({args.qos}, depth {args.depth})", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())

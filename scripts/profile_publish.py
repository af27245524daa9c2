"""Where a map publish spends its time: copy, statistics + packing, message, send.

Maps a drive (``--dataset``, default the benchmark's drive in out/bench/drive) with the
node's mapper object, then times, for the whole map and for one publish cycle after one
scan (updates + view), each stage the node runs: the copy taken under the map lock, the
statistics packed into point records, the PointCloud2 around them, and rclpy's
``publish()`` with one subscriber in another process (``topic_listener``). Medians of
``--repeat`` runs; also how long ``publish()`` holds the interpreter (the GIL), measured
as the stall of a thread that ticks every millisecond meanwhile.

    .venv/bin/python scripts/profile_publish.py --scans 300 [--dataset ROOT --sequence SS]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.outputs.records import RECORD, change_records, packed_palette, records_from_alpha, view_records
from convbki_core.paths import kernel_path
from convbki_ros.dds import publish_asynchronously, use_large_data_profile
from convbki_ros.outputs.cloud_encoding import records_cloud


def timed(function, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeat):
        started = time.perf_counter()
        result = function()
        times.append(1e3 * (time.perf_counter() - started))
    return statistics.median(times), result


class GilProbe:
    """A thread that wakes every millisecond; its longest late wake-up is how long the
    interpreter was held by someone else."""

    def __init__(self):
        self.worst = 0.0
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while self.running:
            before = time.perf_counter()
            time.sleep(0.001)
            self.worst = max(self.worst, time.perf_counter() - before - 0.001)

    def stop(self) -> float:
        self.running = False
        self.thread.join()
        return 1e3 * self.worst


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="out/bench/drive")
    parser.add_argument("--sequence", default="00")
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    dataset = SemanticKittiSequence(Path(args.dataset), args.sequence)
    label_map = load_label_map("semantic_kitti")
    palette = packed_palette(label_map.colors)
    mapper = ConvBKIMapper(MapperConfig.paper(device="cpu", ignore_classes=label_map.ignore_classes,
                                              track_changes=True), kernel_path("semantic_kitti_compound"))
    frames = []
    for number, frame in enumerate(dataset):
        if number >= args.scans:
            break
        mapper.integrate(frame.points, frame.input_labels, frame.pose)
        mapper.take_changes()  # as the node's publish cycle does; untaken changes would pile up
        frames.append(frame)
    print(f"map: {len(mapper):,} voxels after {len(frames)} scans ({len(mapper.window.mask.nonzero()[0]):,} in the "
          "window)")

    use_large_data_profile()
    publish_asynchronously()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    listener = subprocess.Popen([sys.executable, "-m", "convbki_ros.tools.topic_listener", "--topic", "/profile_map",
                                 "--qos", "latched", "--depth", "1"], stdout=subprocess.DEVNULL)
    rclpy.init()
    node = rclpy.create_node("profile_publish")
    publisher = node.create_publisher(PointCloud2, "/profile_map", QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    deadline = time.monotonic() + 30
    while not publisher.get_subscription_count() and time.monotonic() < deadline:
        time.sleep(0.1)

    copy_ms, (indices, alpha) = timed(mapper.items, args.repeat)
    records_ms, records = timed(lambda: records_from_alpha(indices, alpha, mapper.resolution, palette), args.repeat)
    message_ms, msg = timed(lambda: records_cloud(0, "map", RECORD, len(records),
                                                  lambda out: np.copyto(out, records)), args.repeat)
    sends, stalls = [], []
    for _ in range(args.repeat):
        probe = GilProbe()
        started = time.perf_counter()
        publisher.publish(msg)
        sends.append(1e3 * (time.perf_counter() - started))
        stalls.append(probe.stop())
    print(f"whole map ({len(records):,} voxels, {len(records) * RECORD.itemsize / 1e6:.0f} MB): copy under the lock "
          f"{copy_ms:.0f} ms, statistics + packing {records_ms:.0f} ms, message {message_ms:.0f} ms, publish() "
          f"{statistics.median(sends):.0f} ms (holding the interpreter up to {statistics.median(stalls):.0f} ms)")

    cycle = []
    for frame in frames[-args.repeat:]:
        mapper.integrate(frame.points, frame.input_labels, frame.pose)
        mapper.take_changes()  # this scan's changes are what the next cycle sends
        mapper.integrate(frame.points, frame.input_labels, frame.pose)
        started = time.perf_counter()
        changes = mapper.take_changes()
        updates = change_records(changes.removed, changes.indices, changes.alpha, mapper.resolution, palette)
        taken = time.perf_counter()
        view = view_records(mapper.window_records(palette), frame.pose[:3, 3], 30.0, 600_000)
        cycle.append((1e3 * (taken - started), 1e3 * (time.perf_counter() - taken), len(updates), len(view)))
    middle = sorted(cycle)[len(cycle) // 2]
    print(f"one cycle after one scan: updates {middle[0]:.0f} ms ({middle[2]:,} voxels, "
          f"{middle[2] * RECORD.itemsize / 1e6:.1f} MB), view {middle[1]:.0f} ms ({middle[3]:,} voxels)")
    node.destroy_node()
    rclpy.shutdown()
    listener.terminate()
    listener.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())

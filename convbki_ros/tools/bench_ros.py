"""The figures of ``bench`` that go through the node's ROS-side code (PointCloud2 encoding and
decoding, the odometry buffer, the node's start). ``bench`` lives in the core, which never
imports convbki_ros, so it runs ``python -m convbki_ros.tools.bench_ros`` in its own
process on the same drive and reports these figures as not measured where that cannot run.
Imports no rclpy at import time: the codec works on plain objects with the PointCloud2
attributes.
"""

from __future__ import annotations

import statistics
import time
from types import SimpleNamespace

import numpy as np

from convbki_core.io.labels import load_label_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.offline import paper_mapper
from convbki_core.tools.bench_figures import median_ms, steady
from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.inputs.pose_buffer import OdometryBuffer
from convbki_ros.outputs.cloud_encoding import map_cloud_fields, pack_fields

# The keys the functions below add to bench's figures.
ENCODE_KEYS = ("encode_ms_per_million", "encoded_voxels")
SCAN_TO_MAP_KEYS = ("scan_to_map_ms",)
SCAN_PERIOD_NS = 100_000_000  # 10 Hz, the KITTI LiDAR


def encode_figures(mapper: ConvBKIMapper, repeat: int) -> dict:
    """Map voxels -> PointCloud2 field bytes (the ``/semantic_map`` point layout): ms per million
    voxels, and the voxels encoded."""
    voxels = mapper.voxels()
    colours = load_label_map().colors
    elapsed = median_ms(lambda: pack_fields(map_cloud_fields(voxels, colours)), repeat)
    return {"encode_ms_per_million": elapsed / (len(voxels) / 1e6), "encoded_voxels": len(voxels)}


def scan_to_map_figures(frames: list, repeat: int) -> dict:
    """The node's whole path for one scan: decode PointCloud2 + pose lookup + update + window move."""
    label_map = load_label_map()
    mapper = paper_mapper()
    poses = OdometryBuffer()
    clouds = []
    for number, frame in enumerate(frames[:repeat]):
        raw = label_map.to_raw(frame.input_labels).astype(np.uint32)
        layout, point_step, data = pack_fields({"x": frame.points[:, 0], "y": frame.points[:, 1],
                                                "z": frame.points[:, 2], "intensity": frame.remission,
                                                "label": raw})
        clouds.append((number, _CloudView(layout, point_step, data.tobytes(), len(frame.points))))
        # Odometry on both sides of the scan's stamp, so the lookup interpolates as the node's does.
        poses.add(number * SCAN_PERIOD_NS, frame.pose, "velo_link")
        poses.add(number * SCAN_PERIOD_NS + SCAN_PERIOD_NS // 2, frame.pose, "velo_link")
    times = []
    for number, cloud in clouds:
        started = time.perf_counter()
        decoded = decode_cloud(cloud, 20)
        pose = poses.lookup(number * SCAN_PERIOD_NS + SCAN_PERIOD_NS // 10).pose
        mapper.integrate(decoded.points, label_map.to_learning(decoded.labels), pose)
        times.append(1e3 * (time.perf_counter() - started))
    return {"scan_to_map_ms": steady(times)}


class _CloudView:
    """Just the PointCloud2 attributes the decoder reads."""

    def __init__(self, layout, point_step, data, count):
        self.fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in layout]
        self.point_step, self.row_step, self.data = point_step, point_step * count, data
        self.width, self.height, self.is_bigendian, self.is_dense = count, 1, False, True
        self.header = SimpleNamespace(frame_id="velo_link", stamp=SimpleNamespace(sec=0, nanosec=0))


# -- start-up: process start to "ready", and the first scans after it ----------------------------
START_KEYS = ("cold_start_s", "warm_start_s", "cold_first_scan_ms", "cold_tenth_scan_ms", "warm_first_scan_ms",
              "warm_tenth_scan_ms")
READY = "mapper ready"


def start_figures(frames: list, scans: int = 10, starts: int = 3) -> dict:
    """The mapper node started as a user starts it (``python -m convbki_ros.main`` with the
    shipped params, in its own process) with an empty compiled-kernel cache (``NUMBA_CACHE_DIR``
    on a new folder: a fresh install) and with the cache set-up leaves: seconds from process
    start to "ready", then the update time the node reports on /diagnostics for its first and
    its tenth scan, published over DDS one at a time (the first ``scans`` of the drive).
    Medians over ``starts`` starts of each kind (one scan's time is noisy)."""
    import tempfile

    figures = {}
    for kind in ("cold", "warm"):
        runs = []
        for _ in range(starts):
            with tempfile.TemporaryDirectory(prefix="convbki_bench_cache_") as empty_cache:
                seconds, update_ms = _time_a_start(frames[:scans], {"NUMBA_CACHE_DIR": empty_cache}
                                                   if kind == "cold" else {})
            runs.append((seconds, update_ms[0], update_ms[-1]))
        for key, values in zip(("start_s", "first_scan_ms", "tenth_scan_ms"), zip(*runs)):
            figures[f"{kind}_{key}"] = statistics.median(values)
    return figures


def _time_a_start(frames: list, env: dict) -> tuple[float, list[float]]:
    import os
    import random
    import signal
    import subprocess
    import sys
    import threading

    from convbki_core.paths import config_dir

    domain = random.randint(101, 200)  # away from the tests' domains (1..100)
    environment = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                   "PYTHONUNBUFFERED": "1", **env}
    started = time.monotonic()
    node = subprocess.Popen([sys.executable, "-m", "convbki_ros.main", "--ros-args", "--params-file",
                             str(config_dir() / "mapper.yaml"), "-p", "device:=cpu", "-p", "diagnostics_period:=0.1",
                             "-p", "map_file:=\"\"", "-r", "cloud_in:=/bench/cloud", "-r", "odom:=/bench/odom"],
                            env=environment, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    ready = threading.Event()
    output: list[str] = []

    def read() -> None:
        for line in node.stdout:
            output.append(line)
            if READY in line:
                ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        while not ready.wait(0.05):
            if node.poll() is not None:
                raise RuntimeError(f"the mapper node stopped before it was ready:\n{''.join(output[-20:])}")
        seconds = time.monotonic() - started
        return seconds, _first_scans(domain, frames)
    finally:
        node.send_signal(signal.SIGINT)
        node.wait(timeout=60)
        reader.join(timeout=10)


def _first_scans(domain: int, frames: list) -> list[float]:
    """Publish each frame (odometry, then its cloud) and wait until the node integrated it; the
    node's own update time of each, from /diagnostics."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from convbki_ros.dds import use_large_data_profile
    from convbki_ros.inputs.transforms import pose_to_odometry
    from convbki_ros.outputs.cloud_encoding import encode_cloud

    use_large_data_profile()
    label_map = load_label_map()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("convbki_bench_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    reports: list = []
    node.create_subscription(DiagnosticArray, "/diagnostics", reports.append, 10)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    clouds = node.create_publisher(PointCloud2, "/bench/cloud", qos)
    odometry = node.create_publisher(Odometry, "/bench/odom", qos)

    def spin_until(done, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                raise RuntimeError("the mapper node did not answer within 120 s")
            executor.spin_once(timeout_sec=0.05)

    def values() -> dict:
        return {item.key: item.value for item in reports[-1].status[0].values} if reports else {}

    try:
        spin_until(lambda: clouds.get_subscription_count() and odometry.get_subscription_count() and reports)
        update_ms = []
        for number, frame in enumerate(frames):
            stamp = (number + 1) * SCAN_PERIOD_NS
            columns = {"x": frame.points[:, 0], "y": frame.points[:, 1], "z": frame.points[:, 2],
                       "label": label_map.to_raw(frame.input_labels).astype(np.uint32)}
            odometry.publish(pose_to_odometry(frame.pose, stamp, "map", "velo_link"))
            clouds.publish(encode_cloud(stamp, "velo_link", columns))
            spin_until(lambda count=number + 1: int(values().get("integrated", 0)) >= count)
            update_ms.append(float(values()["update_ms_last"]))
        return update_ms
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()


def main(argv: list[str] | None = None) -> int:
    """Entry point: the ROS-side figures on bench's drive, written as JSON; ``bench`` runs it."""
    import argparse
    import json
    import sys
    from pathlib import Path

    from convbki_core.io.atomic import atomic_write_bytes
    from convbki_core.synth.cached_drive import ensure_drive
    from convbki_core.tools.bench_figures import drive_figures

    parser = argparse.ArgumentParser(prog="bench_ros", description="bench's figures that run the node's ROS-side "
                                     "code (PointCloud2 encoding and decoding, odometry lookup, the node's start)")
    parser.add_argument("--drive-dir", default="out/bench/drive", help="bench's synthetic drive (written if missing)")
    parser.add_argument("--scans", type=int, default=500, help="scans of the drive to map (as bench)")
    parser.add_argument("--repeat", type=int, default=30, help="repetitions of each timing (as bench)")
    parser.add_argument("--seed", type=int, default=5, help="seed of the drive (as bench)")
    parser.add_argument("--skip-start", action="store_true", help="leave out the node's start figures")
    parser.add_argument("--map", default=None, help="the map bench made of the drive (a map file); without it the "
                        "drive is mapped here")
    parser.add_argument("--json", required=True, help="file the figures are written to")
    args = parser.parse_args(argv)
    try:
        dataset = ensure_drive(Path(args.drive_dir), args.scans, args.seed)
    except ValueError as error:
        print(f"bench_ros: error: {error}", file=sys.stderr)
        return 2
    if args.map:
        mapper = paper_mapper()
        mapper.load(args.map)
        # The frames bench times its other figures on: from the second half of the drive.
        first = args.scans // 2
        frames = [dataset[position] for position in range(first, min(args.scans, first + args.repeat))]
    else:
        _, mapper, frames = drive_figures(dataset, args.scans, args.repeat)
    figures = encode_figures(mapper, max(3, args.repeat // 5))
    del mapper
    figures.update(scan_to_map_figures(frames, args.repeat))
    if not args.skip_start:
        figures.update(start_figures(frames))
        for kind in ("cold", "warm"):
            figures[f"{kind}_first_scan_ratio"] = (figures[f"{kind}_first_scan_ms"]
                                                   / max(figures[f"{kind}_tenth_scan_ms"], 1e-6))
    atomic_write_bytes(Path(args.json), (json.dumps(figures, indent=2) + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

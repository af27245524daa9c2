"""What a SLAM's re-sent Path costs the node when it moves nothing (docs/slam.md).

LIO-SAM re-sends its whole path after every scan, each pose nudged by the graph's latest
factor. The node's look at such a Path (``CorrectionRunner.on_path``: the pose count, the
decoding, the checks, and whether it moves any logged scan by ``correction_min_move``) is
timed here against a scan log as long as KITTI 00 (4,500 scans, ten a second, a keyframe a
second), with the Path as it was applied and with every keyframe nudged by 2 cm. The scans'
points do not matter to the look (it reads stamps and poses), so each holds ten. Prints the
median and the largest of ``--repeats`` looks.

    .venv/bin/python scripts/path_check_study.py --scans 4500 --repeats 200
"""

from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.serialization import serialize_message

from convbki_core.correction.scan_log import LoggedScan, ScanLog
from convbki_core.geometry.poses import pose_to_translation_quaternion
from convbki_ros.mapping.corrections import CorrectionRunner

EPOCH_NS = 1_700_000_000 * 10**9


def drive_log(scans: int, segment: int = 100) -> ScanLog:
    """A log of ``scans`` scans 0.1 s apart along a gentle curve, segments of ``segment`` scans."""
    log = ScanLog()
    points = np.random.default_rng(0).uniform(-1, 1, (10, 3)).astype(np.float32)
    for number in range(scans):
        pose = np.eye(4)
        yaw = number * 0.001
        pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        pose[:3, 3] = [number * 1.0, 0.1 * number, 0.0]
        log.append(LoggedScan.of(points, np.zeros(10, np.int64), pose, EPOCH_NS + number * 100_000_000))
        if number % segment == segment - 1:
            log.begin_segment(None, None)
    return log


def path_bytes(stamps: np.ndarray, poses: np.ndarray) -> bytes:
    path = Path()
    path.header.frame_id = "map"
    for stamp, pose in zip(stamps, poses):
        stamped = PoseStamped()
        stamped.header.stamp.sec, stamped.header.stamp.nanosec = divmod(int(stamp), 10**9)
        translation, quaternion = pose_to_translation_quaternion(pose)
        p, q = stamped.pose.position, stamped.pose.orientation
        p.x, p.y, p.z = (float(v) for v in translation)
        q.x, q.y, q.z, q.w = (float(v) for v in quaternion)
        path.poses.append(stamped)
    return serialize_message(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=4500)
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    log = drive_log(args.scans)
    table = log.table()
    mapper = SimpleNamespace(scan_log=log, resolution=0.2, correction_reach=lambda: 25.6)
    params = {"correction_min_move": -1.0, "max_path_poses": 100_000}
    node = SimpleNamespace(param=params.get, resolve_topic_name=lambda name: "/" + name)
    runner = CorrectionRunner(SimpleNamespace(mapper=mapper, frame="map"), node, warnings=None)
    keyframes = np.arange(0, args.scans, 10)
    rng = np.random.default_rng(1)
    for label, nudge in (("as applied", 0.0), ("every keyframe nudged 2 cm", 0.02)):
        poses = table.poses[keyframes].copy()
        poses[:, :3, 3] += rng.normal(0.0, nudge, (len(keyframes), 3)) if nudge else 0.0
        raw = path_bytes(table.stamps_ns[keyframes], poses)
        looks = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            runner.on_path(raw)
            looks.append((time.perf_counter() - started) * 1e3)
        print(f"{label}: {args.scans} logged scans, {len(keyframes)} keyframes: look median "
              f"{statistics.median(looks):.2f} ms, largest {max(looks):.2f} ms; moved nothing "
              f"{runner.counts.unchanged} of {runner.counts.received} so far")


if __name__ == "__main__":
    main()

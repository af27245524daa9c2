"""A long drive's scan log on disk and its corrections (docs/slam.md): memory, disk, reach, cost.

A drive of ``--scans`` 64-beam scans at 10 Hz is mapped with the shipped defaults and the scan
log in a folder, as the node keeps it. Its scans are those of a short ``synth`` drive
(``--source``), cycled; its poses are those of a long drive at 10 m/s on a gentle curve, the
odometry drifting (8 degrees per 100 m, 1 % scale). At each ``--closures SCAN:SECONDS`` a SLAM
closes a loop there that reaches SECONDS back: every pose from the revisited scan on moves by
the drift accumulated since (the map's poses after it follow the corrected frame). Measured:
the process's peak RSS, the log's memory and disk, its bytes per point, each correction's
seconds against integrating the scans it moved (the live scans' median), where that time goes
(reading the scans back, integrating), the save's seconds and the map file's size, and the
labels equal to the map mapped from scratch at the last poses.

    .venv/bin/python scripts/long_drive_study.py --source out/synth60 --scans 1500 \
        --closures 900:60 1499:145 --out out/long
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import time
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.mapper import ConvBKIMapper

STEP_M, CURVE_RAD = 1.0, 0.0004  # per scan: 10 m/s at 10 Hz, a gentle left curve
DRIFT_RAD_PER_M, SCALE = np.radians(8.0) / 100.0, 1.01


def yaw_pose(x: float, y: float, yaw: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:2, 3] = x, y
    return pose


def drive_poses(count: int) -> tuple[np.ndarray, np.ndarray]:
    """(true poses, drifted odometry poses), (count, 4, 4) each."""
    true, odometry = [np.eye(4)], [np.eye(4)]
    for _ in range(1, count):
        step = yaw_pose(STEP_M, 0.0, CURVE_RAD)
        drifted = yaw_pose(STEP_M * SCALE, 0.0, CURVE_RAD + DRIFT_RAD_PER_M * STEP_M)
        true.append(true[-1] @ step)
        odometry.append(odometry[-1] @ drifted)
    return np.stack(true), np.stack(odometry)


def labels_equal(mapper, other) -> float:
    """The fraction of the voxels of either map whose expected class is the same in both (a voxel
    one map lacks counts as different), in voxel order, without a per-voxel Python object."""
    def keyed(m):
        indices, alpha = m.items()
        order = np.lexsort(indices.T[::-1])
        return indices[order], np.argmax(alpha[order], axis=1)

    (a, la), (b, lb) = keyed(mapper), keyed(other)
    both = np.concatenate([a, b])
    unique, inverse = np.unique(both, axis=0, return_inverse=True)
    labels = np.full((2, len(unique)), -1)
    labels[0, inverse[:len(a)]] = la
    labels[1, inverse[len(a):]] = lb
    return round(float(np.mean(labels[0] == labels[1])), 5)


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1e3
    return 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True, help="a synth dataset root (sequence 00)")
    parser.add_argument("--scans", type=int, default=1500)
    parser.add_argument("--closures", nargs="+", default=["900:60", "1499:145"], help="SCAN:SECONDS_BACK")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-scratch", action="store_true", help="skip the from-scratch map")
    args = parser.parse_args()
    closures = {int(item.split(":")[0]): int(float(item.split(":")[1]) * 10) for item in args.closures}
    source = SemanticKittiSequence(args.source, "00")
    frames = [source[k] for k in range(len(source))]
    true, odometry = drive_poses(args.scans)
    stamps = 1_700_000_000 * 10**9 + np.arange(args.scans, dtype=np.int64) * 100_000_000
    shutil.rmtree(args.out / "log", ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    config = MapperConfig().replace(device="cpu")
    mapper = ConvBKIMapper(config)
    mapper.use_log_folder(args.out / "log")
    fix = np.eye(4)  # map <- odometry: the SLAM's frame correction so far
    mapped = np.zeros((args.scans, 4, 4))  # the poses the map holds each scan at
    live_ms, corrections, rss_peak, log_memory_peak = [], [], 0.0, 0
    for k in range(args.scans):
        frame = frames[k % len(frames)]
        mapped[k] = fix @ odometry[k]
        started = time.perf_counter()
        mapper.integrate(frame.points, frame.input_values, mapped[k], frame.input_moving, stamp_ns=int(stamps[k]))
        live_ms.append(1e3 * (time.perf_counter() - started))
        log_memory_peak = max(log_memory_peak, mapper.scan_log.nbytes)
        if k % 50 == 0:
            rss_peak = max(rss_peak, rss_mb())
        if k in closures:
            since = k - closures[k]
            # The revisited scan stays; every pose after it loses the drift accumulated since.
            moved = {j: mapped[since] @ np.linalg.inv(true[since]) @ true[j] for j in range(since + 1, k + 1)}
            reads = time.perf_counter()
            for _, scan in mapper.scan_log.scans(since + 1):
                scan.decoded()
            read_s = time.perf_counter() - reads
            started = time.perf_counter()
            fixed, result = mapper.corrected(moved, tolerance=0.05)
            seconds = time.perf_counter() - started
            rss_peak = max(rss_peak, rss_mb())
            median = statistics.median(live_ms)
            corrections.append({"at_scan": k, "reach_s": closures[k] / 10, "moved": result.scans,
                                "replayed": result.replayed, "seconds": round(seconds, 1),
                                "reading_s": round(read_s, 1),
                                "integrating_moved_s": round(result.scans * median / 1e3, 1),
                                "ratio": round(seconds / (result.scans * median / 1e3), 3)})
            print(corrections[-1], {"log_first": mapper.scan_log.first_index, "frozen_why": mapper.scan_log.frozen_why,
                                    "error": mapper.scan_log.folder.error}, flush=True)
            mapper = fixed
            for j, pose in moved.items():
                mapped[j] = pose
            fix = mapped[k] @ np.linalg.inv(odometry[k])
    log = mapper.scan_log
    log.folder.flush()
    points = sum(scan.count for _, scan in log.scans())
    data = sum(scan.data.size for _, scan in log.scans())
    started = time.perf_counter()
    mapper.save(args.out / "map.npz")
    save_s = time.perf_counter() - started
    summary = {"scans": args.scans, "voxels": len(mapper), "live_ms_median": round(statistics.median(live_ms), 1),
               "rss_peak_mb": round(max(rss_peak, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3), 0),
               "log_memory_peak_mb": round(log_memory_peak / 1e6, 1), "log_scans": len(log),
               "log_reach_s": (log.newest_ns - log.reach_ns) / 1e9, "frozen": log.frozen,
               "log_disk_mb": round(log.disk_bytes / 1e6, 1), "folder_mb": round(log.folder.nbytes / 1e6, 1),
               "bases_disk_mb": round(sum(s.base.disk_bytes for s in log.segments() if s.base) / 1e6, 1),
               "segments": len(log.segments()), "bytes_per_point": round(data / points, 2),
               "write_error": log.folder.error,
               "save_s": round(save_s, 2), "map_file_mb": round((args.out / "map.npz").stat().st_size / 1e6, 1),
               "corrections": corrections}
    (args.out / "study.json").write_text(json.dumps(summary, indent=1))  # before the long from-scratch map
    if not args.no_scratch:
        scratch = ConvBKIMapper(config.replace(scan_log=False))
        for k in range(args.scans):
            frame = frames[k % len(frames)]
            scratch.integrate(frame.points, frame.input_values, mapped[k], frame.input_moving, stamp_ns=int(stamps[k]))
        summary["labels_equal_to_scratch"] = labels_equal(mapper, scratch)
    print(json.dumps(summary, indent=1))
    (args.out / "study.json").write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

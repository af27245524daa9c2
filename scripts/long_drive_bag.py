"""A bag of a long drive with a LIO-SAM-like SLAM beside it (docs/slam.md, the long-drive run).

``--scans`` 64-beam scans at 10 Hz. From a ``synth --drift`` drive at least that long
(``--source``): its scans, route and drifting odometry (a town's density, its streets revisited,
as on KITTI 00). From a shorter one: its scans cycled on the poses of ``long_drive_study`` (10 m/s
on a gentle curve; the odometry drifts 8 degrees per 100 m and 1 % in scale; denser than a real
drive: the cycled scenes do not join up). As LIO-SAM does, the SLAM publishes its whole path on
``/pose_corrections`` (``nav_msgs/Path`` in ``map``, a keyframe a second, each with its scan's
stamp) five times a second, every keyframe's position nudged by a centimetre or two afresh each
second (an iSAM2 graph at each new factor), and ``map -> odom`` on /tf. At each ``--closures
SCAN:SECONDS`` it closes a loop reaching SECONDS back: every pose after the revisited scan loses
the drift accumulated since, and ``map -> odom`` follows. Written with the topics and frames of
``kitti_to_bag``'s drift bags, so the node runs on it with ``map_frame:=map``.

    .venv/bin/python -m convbki_core.tools.synth --out out/long/data --frames 4500 --seed 7 --movers 40 \
        --drift 8 --drift-scale 0.01
    .venv/bin/python scripts/long_drive_bag.py --source out/long/data --scans 4500 \
        --closures 1500:145 4499:444 --out out/long/bag
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from long_drive_study import drive_poses

from convbki_core.datasets.drift import read_loop_closure
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_ros.tools.kitti_to_bag import (
    CLOUD_TOPIC,
    CORRECTIONS_TOPIC,
    EPOCH_NS,
    MAP_FRAME,
    ODOM_FRAME,
    ODOM_TOPIC,
    SENSOR_FRAME,
    TF_TOPIC,
    add_connections,
    cloud_fields,
)

PATH_EVERY, KEYFRAME_EVERY, NUDGE_EVERY, NUDGE_M = 2, 10, 10, 0.01


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True)
    parser.add_argument("--scans", type=int, default=4500)
    parser.add_argument("--closures", nargs="+", default=["1500:145", "4499:444"])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from convbki_ros.inputs.transforms import (
        message_types,
        pose_to_odometry,
        pose_to_transform_stamped,
        poses_to_path,
    )
    from convbki_ros.outputs.cloud_encoding import encode_cloud

    closures = {int(item.split(":")[0]): int(float(item.split(":")[1]) * 10) for item in args.closures}
    source = SemanticKittiSequence(args.source, "00")
    closure = read_loop_closure(source)
    if len(source) >= args.scans and closure is not None:
        # A drive as long as the bag (``synth --drift``): its own route, revisits and drifting odometry.
        true, odometry = source.poses[:args.scans], closure.odometry[:args.scans]
        fields = None
    else:
        true, odometry = drive_poses(args.scans)
        fields = [cloud_fields(source[k], False) for k in range(len(source))]  # cycled
    stamps = EPOCH_NS + np.arange(args.scans, dtype=np.int64) * 100_000_000
    estimate = odometry.copy()  # map <- lidar as the SLAM has it now
    map_from_odom = np.eye(4)
    rng = np.random.default_rng(0)
    nudge = np.zeros((args.scans, 3))
    typestore = get_typestore(Stores.ROS2_JAZZY)
    types = message_types(typestore)
    shutil.rmtree(args.out, ignore_errors=True)
    paths = 0
    with Writer(args.out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = add_connections(writer, typestore, {
            TF_TOPIC: "tf2_msgs/msg/TFMessage", ODOM_TOPIC: "nav_msgs/msg/Odometry",
            CLOUD_TOPIC: "sensor_msgs/msg/PointCloud2", CORRECTIONS_TOPIC: "nav_msgs/msg/Path"})
        tf_conn, odom_conn, cloud_conn, path_conn = connections.values()
        for k in range(args.scans):
            stamp = int(stamps[k])
            estimate[k] = map_from_odom @ odometry[k]
            if k in closures:
                since = k - closures[k]
                estimate[since + 1:k + 1] = estimate[since] @ np.linalg.inv(true[since]) @ true[since + 1:k + 1]
                map_from_odom = estimate[k] @ np.linalg.inv(odometry[k])
            if k % NUDGE_EVERY == 0:
                nudge = rng.normal(0.0, NUDGE_M, (args.scans, 3))
            if (k % PATH_EVERY == 0 or k in closures) and k >= KEYFRAME_EVERY:  # a closure is sent at once
                keys = np.arange(0, k + 1, KEYFRAME_EVERY)
                poses = estimate[keys].copy()
                poses[:, :3, 3] += nudge[keys]
                path = poses_to_path(poses, stamps[keys], MAP_FRAME, stamp, types)
                writer.write(path_conn, stamp, typestore.serialize_cdr(path, path.__msgtype__))
                paths += 1
            transforms = [pose_to_transform_stamped(map_from_odom, stamp, MAP_FRAME, ODOM_FRAME, types)]
            tf_msg = types("tf2_msgs/msg/TFMessage")(transforms=transforms)
            odom = pose_to_odometry(odometry[k], stamp, ODOM_FRAME, SENSOR_FRAME, types)
            frame_fields = cloud_fields(source[k], False) if fields is None else fields[k % len(fields)]
            cloud = encode_cloud(stamp, SENSOR_FRAME, frame_fields, types=types)
            writer.write(tf_conn, stamp, typestore.serialize_cdr(tf_msg, tf_msg.__msgtype__))
            writer.write(odom_conn, stamp, typestore.serialize_cdr(odom, odom.__msgtype__))
            writer.write(cloud_conn, stamp, typestore.serialize_cdr(cloud, cloud.__msgtype__))
    np.save(args.out.parent / "final_poses.npy", estimate)  # where the last Path puts every scan
    print(f"wrote {args.scans} scans and {paths} Paths to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

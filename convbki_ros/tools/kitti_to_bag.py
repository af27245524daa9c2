"""``kitti_to_bag``: a SemanticKITTI-format sequence -> rosbag2 (mcap or sqlite3).

Topics: /kitti/velo/pointcloud (PointCloud2, frame velo_link, fields x, y, z, intensity
and label or prob_i), /kitti/odom (nav_msgs/Odometry of velo_link in map), and TF as a
recorded robot has it: /tf_static holds the LiDAR's mount on the vehicle once (the pose of
velo_link in camera_gray_left, KITTI's left grey camera, from calib.txt's Tr; recorded
transient local), /tf the vehicle's pose (camera_gray_left in map, poses.txt). Per frame,
/tf and /kitti/odom are written just before the cloud, all at the cloud's stamp
(EPOCH + times.txt). The bag is written into a hidden folder next to BAG and renamed into
place at the end, so an interrupted run leaves nothing half-written.

A drift drive (``synth --drift``: a sequence with ``loop_closure.yaml``) is written as a robot
with a SLAM records it, unless ``--true-poses``: /kitti/odom is the drifting odometry in frame
odom, /tf holds odom -> camera_gray_left from it and map -> odom, the identity until the SLAM
closes the loop and its correction from then on, and /pose_corrections (nav_msgs/Path in map)
the corrected keyframe poses of velo_link, once, just before the closure's cloud (when the
frames written hold the closure and scans before it).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from convbki_core.io.atomic import remove_stale_staging_folders, staging_prefix
from convbki_core.tools.cli import NewOutputs, UserError, frames_arg, progress, run, say_notices, sequence_arg

PROG = "kitti_to_bag"

EPOCH_NS = 1_700_000_000 * 1_000_000_000  # stamps = this + times.txt seconds (deterministic replays)
CLOUD_TOPIC = "/kitti/velo/pointcloud"
ODOM_TOPIC = "/kitti/odom"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
VEHICLE_FRAME = "camera_gray_left"  # the frame poses.txt gives (KITTI's camera 0), as kitti2bag names it
MAP_FRAME = "map"
ODOM_FRAME = "odom"  # a drift drive's odometry frame: map -> odom is the SLAM's correction
CORRECTIONS_TOPIC = "/pose_corrections"
SENSOR_FRAME = "velo_link"
DEFAULT_PREDICTIONS_DIR = "predictions"


def build_parser() -> argparse.ArgumentParser:
    """Command-line parser."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Write a SemanticKITTI-format sequence (scans, input segmentation, "
        "poses) to a rosbag2: /kitti/velo/pointcloud, /kitti/odom, /tf and /tf_static. Ground truth "
        "stays in the dataset folder. Stamps come from times.txt when present, else 0.1 s "
        "apart, counted from a fixed epoch (1700000000 s), so a replay is deterministic.",
    )
    p.add_argument("--dataset", required=True, metavar="ROOT",
                   help="dataset root holding sequences/SS/{velodyne,labels,...}, "
                   "poses.txt and calib.txt")
    p.add_argument("--sequence", required=True, metavar="SS", type=sequence_arg,
                   help="sequence id, e.g. 08")
    p.add_argument("--out", required=True, metavar="BAG",
                   help="output bag directory (must not exist yet, unless --force)")
    p.add_argument("--predictions-dir", default=None, metavar="DIR",
                   help="folder under sequences/SS with the input segmentation "
                   "NNNNNN.label (uint32 raw ids), written as the uint32 `label` field "
                   f"(default: {DEFAULT_PREDICTIONS_DIR}; not read with --probabilities-dir)")
    p.add_argument("--probabilities-dir", default=None, metavar="DIR",
                   help="folder under sequences/SS with per-point class probabilities "
                   "NNNNNN.npy (N x C float16/float32); when given, the cloud carries "
                   "float32 fields prob_0..prob_{C-1} instead of `label`")
    p.add_argument("--frames", default=None, metavar="A:B", type=frames_arg,
                   help="only frames A (inclusive) to B (exclusive); default: all")
    p.add_argument("--true-poses", action="store_true",
                   help="for a drift drive (loop_closure.yaml), write poses.txt's true poses as /kitti/odom in "
                   "map, without the drift, map -> odom or /pose_corrections")
    p.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"),
                   help="rosbag2 storage plugin (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace BAG when it exists (the old bag is removed only once the new one is complete)")
    return p


def data_qos(latched: bool = False):
    """Offered QoS recorded in metadata.yaml: reliable, volatile, keep last 100 (what a driver offers);
    ``latched``: transient local, as tf2's static broadcaster offers /tf_static."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1 if latched else 100, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, deadline=zero,
               lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


def cloud_fields(frame, probabilities: bool) -> dict[str, np.ndarray]:
    """x, y, z, intensity (float32) and label (uint32 raw word) or prob (N, C float32) of a frame."""
    fields = {"x": frame.points[:, 0], "y": frame.points[:, 1], "z": frame.points[:, 2],
              "intensity": frame.remission.astype(np.float32, copy=False)}
    if probabilities:
        fields["prob"] = frame.probabilities.astype(np.float32, copy=False)  # -> prob_0 .. prob_{C-1}
    else:
        fields["label"] = frame.raw_input_labels.astype(np.uint32, copy=False)
    return fields


def add_connections(writer, typestore, types_by_topic: dict[str, str], latched=frozenset()) -> dict:
    """A rosbags ``Writer``'s connection for each topic (``types_by_topic``: topic -> message
    type), offered with ``data_qos`` (``latched``: the topics offered as tf2 offers /tf_static)."""
    return {topic: writer.add_connection(topic, msgtype, typestore=typestore,
                                         offered_qos_profiles=[data_qos(latched=topic in latched)])
            for topic, msgtype in types_by_topic.items()}


def write_bag(sequence, positions: Sequence[int], path: Path, storage: str, probabilities: bool,
              closure=None) -> dict[str, int]:
    """Write the frames at ``positions`` of ``sequence`` into a new bag at ``path``; counts per
    topic. ``closure``: a drift drive's ``LoopClosure`` (odometry in odom, map -> odom and the
    correction Path)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from convbki_ros.inputs.transforms import (
        message_types,
        pose_to_odometry,
        pose_to_transform_stamped,
        poses_to_path,
        seconds_to_ns,
    )
    from convbki_ros.outputs.cloud_encoding import encode_cloud

    typestore = get_typestore(Stores.ROS2_JAZZY)
    types = message_types(typestore)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    counts = {TF_STATIC_TOPIC: 0, TF_TOPIC: 0, ODOM_TOPIC: 0, CLOUD_TOPIC: 0}
    closes = closure is not None and closure.closure_frame in positions[1:]  # the Path only with scans before it
    if closes:
        counts[CORRECTIONS_TOPIC] = 0
    previous = None
    mount = sequence.calibration  # camera_gray_left <- velo_link
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        topics = {TF_STATIC_TOPIC: "tf2_msgs/msg/TFMessage", TF_TOPIC: "tf2_msgs/msg/TFMessage",
                  ODOM_TOPIC: "nav_msgs/msg/Odometry", CLOUD_TOPIC: "sensor_msgs/msg/PointCloud2"}
        if closes:
            topics[CORRECTIONS_TOPIC] = "nav_msgs/msg/Path"
        connections = add_connections(writer, typestore, topics, latched={TF_STATIC_TOPIC})
        static_conn, tf_conn, odom_conn, cloud_conn = (connections[topic] for topic in list(topics)[:4])
        path_conn = connections.get(CORRECTIONS_TOPIC)
        for position in progress(positions, total=len(positions), description=PROG):
            frame = sequence[position]
            stamp = EPOCH_NS + seconds_to_ns(frame.stamp)
            if previous is not None and stamp <= previous:
                raise UserError(f"{sequence.folder / 'times.txt'}: time of frame {frame.name} "
                                f"({frame.stamp} s) is not after the previous frame's")
            if previous is None:
                static = pose_to_transform_stamped(mount, stamp, VEHICLE_FRAME, SENSOR_FRAME, types)
                static_msg = types("tf2_msgs/msg/TFMessage")(transforms=[static])
                writer.write(static_conn, stamp, typestore.serialize_cdr(static_msg, static_msg.__msgtype__))
                counts[TF_STATIC_TOPIC] += 1
            previous = stamp
            if closure is None:
                vehicle = frame.pose @ np.linalg.inv(mount)  # map <- camera_gray_left
                transforms = [pose_to_transform_stamped(vehicle, stamp, MAP_FRAME, VEHICLE_FRAME, types)]
                odom = pose_to_odometry(frame.pose, stamp, MAP_FRAME, SENSOR_FRAME, types)
            else:
                drifted = closure.odometry[position]  # odom <- velo_link, as the odometry says
                if closes and position == closure.closure_frame:  # the SLAM publishes its optimised keyframes
                    keyframes = closure.keyframes[np.isin(closure.keyframes, positions)]
                    path = poses_to_path(closure.truth[keyframes],
                                         [EPOCH_NS + seconds_to_ns(sequence.times[k]) for k in keyframes],
                                         MAP_FRAME, stamp, types)
                    writer.write(path_conn, stamp, typestore.serialize_cdr(path, path.__msgtype__))
                    counts[CORRECTIONS_TOPIC] += 1
                transforms = [pose_to_transform_stamped(closure.correction_at(position), stamp, MAP_FRAME,
                                                        ODOM_FRAME, types),
                              pose_to_transform_stamped(drifted @ np.linalg.inv(mount), stamp, ODOM_FRAME,
                                                        VEHICLE_FRAME, types)]
                odom = pose_to_odometry(drifted, stamp, ODOM_FRAME, SENSOR_FRAME, types)
            tf_msg = types("tf2_msgs/msg/TFMessage")(transforms=transforms)
            cloud = encode_cloud(stamp, SENSOR_FRAME, cloud_fields(frame, probabilities), types=types)
            writer.write(tf_conn, stamp, typestore.serialize_cdr(tf_msg, tf_msg.__msgtype__))
            writer.write(odom_conn, stamp, typestore.serialize_cdr(odom, odom.__msgtype__))
            writer.write(cloud_conn, stamp, typestore.serialize_cdr(cloud, cloud.__msgtype__))
            for topic in (TF_TOPIC, ODOM_TOPIC, CLOUD_TOPIC):
                counts[topic] += 1
    return counts


def _folder_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size


def _replace(new: Path, out: Path, force: bool) -> None:
    """Move the finished bag ``new`` to ``out`` (replacing an old ``out`` only with ``force``)."""
    if not (out.exists() or out.is_symlink()):
        os.rename(new, out)
        return
    if not force:
        raise UserError(f"{out} exists (use --force to replace it)")
    trash = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
    os.rename(out, trash / out.name)
    os.rename(new, out)
    shutil.rmtree(trash, ignore_errors=True)


def convert(args: argparse.Namespace) -> int:
    """The command's body: read the sequence, write the bag, print a summary."""
    from convbki_core.datasets import parse_frames
    from convbki_core.datasets.drift import read_loop_closure
    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence

    out = Path(args.out)
    if (out.exists() or out.is_symlink()) and not args.force:
        raise UserError(f"{out} exists (use --force to replace it)")
    probabilities = args.probabilities_dir is not None
    predictions = args.predictions_dir or (None if probabilities else DEFAULT_PREDICTIONS_DIR)
    sequence = SemanticKittiSequence(args.dataset, args.sequence, predictions_dir=predictions,
                                     probabilities_dir=args.probabilities_dir)
    say_notices(PROG, sequence.notices)
    try:
        positions = parse_frames(args.frames, len(sequence))
    except ValueError as error:
        raise UserError(str(error)) from None
    sequence.check_files(positions)  # a broken scan found now, not after half the bag is written
    closure = None if args.true_poses else read_loop_closure(sequence)

    if out.parent.exists() and not out.parent.is_dir():
        raise UserError(f"{out.parent}: not a folder (for {out})")
    parents = NewOutputs()  # folders made for --out are removed again if the bag cannot be written
    parents.folder(out.parent)
    remove_stale_staging_folders(out)  # a bag half-written by a killed run
    staging = Path(tempfile.mkdtemp(dir=out.parent, prefix=staging_prefix(out)))
    try:
        counts = write_bag(sequence, positions, staging / out.name, args.storage, probabilities, closure)
        _replace(staging / out.name, out, args.force)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        parents.discard()
        raise
    shutil.rmtree(staging, ignore_errors=True)

    first, last = sequence.times[positions[0]], sequence.times[positions[-1]]
    size = _folder_size(out)
    print(f"{PROG}: wrote {out} ({args.storage}, {len(positions)} frames of sequence {sequence.sequence}, "
          f"{last - first:.3f} s, {size / 1e6:.1f} MB)")
    if closure is not None:
        closing = (f"map -> odom corrected and the keyframes on {CORRECTIONS_TOPIC} at frame {closure.closure_frame}"
                   if CORRECTIONS_TOPIC in counts else f"the loop closes at frame {closure.closure_frame}, not written")
        print(f"  a drift drive: odometry in '{ODOM_FRAME}' as it drifts; {closing}")
    for topic, count in counts.items():
        print(f"  {topic:<26} {count:6d} messages")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    return run(PROG, convert, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""kitti_to_bag on real files: a SemanticKITTI sequence turned into a bag and read back with
rosbags (messages, stamps, order, metadata), partial sequences, probabilities, frames, and the
errors that leave nothing behind. The ``dataset`` fixture is test/ros/conftest.py's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_fixture import EPOCH_NS, TIMES, convert
from ros_helpers import odometry_to_pose

from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.inputs.transforms import stamp_to_ns, transform_to_pose

REPO = Path(__file__).resolve().parents[2]
TOPICS = {"/kitti/velo/pointcloud": "sensor_msgs/msg/PointCloud2", "/kitti/odom": "nav_msgs/msg/Odometry",
          "/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage"}


def read_bag(path: Path):
    """{topic: [(timestamp, message)]} and the connections, read with rosbags."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    messages: dict[str, list] = {}
    with Reader(path) as reader:
        connections = {c.topic: c for c in reader.connections}
        order = []
        for connection, timestamp, data in reader.messages():
            messages.setdefault(connection.topic, []).append(
                (timestamp, store.deserialize_cdr(data, connection.msgtype)))
            order.append((timestamp, connection.topic))
    return messages, connections, order


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_kitti_to_bag_round_trip(dataset, tmp_path: Path, storage: str, capsys) -> None:
    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence

    root, frames, _ = dataset
    out = tmp_path / "nested" / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", out, "--storage", storage) == 0
    summary = capsys.readouterr().out
    assert f"{out}" in summary and "4 frames" in summary and "/kitti/velo/pointcloud" in summary
    assert sorted(p.name for p in out.parent.iterdir()) == ["bag"]  # no staging folder left behind

    messages, connections, order = read_bag(out)
    assert {topic: c.msgtype for topic, c in connections.items()} == TOPICS
    assert {topic: len(m) for topic, m in messages.items()} == {**dict.fromkeys(TOPICS, 4), "/tf_static": 1}
    expected_stamps = [EPOCH_NS + round(t * 1e9) for t in TIMES]
    # the mount once, first; per frame: /tf, then odometry, then the cloud, all at the frame's stamp
    assert [topic for _, topic in order] == ["/tf_static", *["/tf", "/kitti/odom", "/kitti/velo/pointcloud"] * 4]
    assert [t for t, _ in order] == [expected_stamps[0], *[s for s in expected_stamps for _ in range(3)]]

    sequence = SemanticKittiSequence(root, "08")
    _, static_message = messages["/tf_static"][0]
    (mount,) = static_message.transforms
    assert (mount.header.frame_id, mount.child_frame_id) == ("camera_gray_left", "velo_link")
    assert np.allclose(transform_to_pose(mount), sequence.calibration, atol=1e-12)  # calib.txt's Tr
    for number, (points, _, predicted) in enumerate(frames):
        timestamp, cloud = messages["/kitti/velo/pointcloud"][number]
        assert timestamp == expected_stamps[number] == stamp_to_ns(cloud.header.stamp)
        assert cloud.header.frame_id == "velo_link" and cloud.height == 1 and cloud.is_dense
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity", "label"]
        decoded = decode_cloud(cloud)
        assert decoded.points.tobytes() == points.tobytes()
        assert np.array_equal(decoded.labels, predicted.astype(np.int64))  # raw words, instance bits kept
        assert decoded.raw_label_dtype == np.uint32
        assert np.array_equal(decoded.intensity, np.full(len(points), 0.5, np.float32))

        timestamp, odom = messages["/kitti/odom"][number]
        assert timestamp == stamp_to_ns(odom.header.stamp)
        assert (odom.header.frame_id, odom.child_frame_id) == ("map", "velo_link")
        assert np.allclose(odometry_to_pose(odom), sequence[number].pose, atol=1e-12)
        _, tf_message = messages["/tf"][number]
        (transform,) = tf_message.transforms
        assert (transform.header.frame_id, transform.child_frame_id) == ("map", "camera_gray_left")
        assert stamp_to_ns(transform.header.stamp) == timestamp
        # the vehicle's pose times the mount is the LiDAR's pose, as the odometry has it
        assert np.allclose(transform_to_pose(transform) @ transform_to_pose(mount), sequence[number].pose,
                           atol=1e-9)

    metadata = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["version"] == 9
    assert metadata["storage_identifier"] == storage
    assert metadata["message_count"] == 13
    assert metadata["starting_time"]["nanoseconds_since_epoch"] == expected_stamps[0]
    assert metadata["duration"]["nanoseconds"] == expected_stamps[-1] - expected_stamps[0]
    assert all((out / name).is_file() for name in metadata["relative_file_paths"])
    topics = {t["topic_metadata"]["name"]: t for t in metadata["topics_with_message_count"]}
    assert {name: t["topic_metadata"]["type"] for name, t in topics.items()} == TOPICS
    for name, entry in topics.items():
        assert entry["message_count"] == (1 if name == "/tf_static" else 4)
        assert entry["topic_metadata"]["serialization_format"] == "cdr"
        assert entry["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
        (qos,) = entry["topic_metadata"]["offered_qos_profiles"]
        durability = "transient_local" if name == "/tf_static" else "volatile"
        assert (qos["reliability"], qos["durability"], qos["history"]) == ("reliable", durability, "keep_last")


def test_kitti_to_bag_of_a_partial_sequence_uses_pose_k_for_scan_k(dataset, tmp_path: Path, capsys) -> None:
    """Scans 1 and 2 of the 4 beside the whole poses.txt and times.txt: the bag carries their own
    poses and stamps, and one line says how many poses were not used."""
    import shutil

    from convbki_core.datasets.semantic_kitti import SemanticKittiSequence

    root, frames, _ = dataset
    partial = tmp_path / "partial"
    shutil.copytree(root / "sequences" / "08", partial / "sequences" / "08")
    for sub in ("velodyne", "labels", "predictions", "probabilities"):
        for path in (partial / "sequences" / "08" / sub).iterdir():
            if int(path.stem) not in (1, 2):
                path.unlink()
    out = tmp_path / "bag"
    assert convert("--dataset", partial, "--sequence", "08", "--out", out) == 0
    assert f"kitti_to_bag: note: {partial / 'sequences' / '08' / 'poses.txt'}: 4 poses for 2 numbered scans: row k " \
        "used for scan k, 2 not used" in capsys.readouterr().err
    messages, _, _ = read_bag(out)
    whole = SemanticKittiSequence(root, "08")
    odometry = messages["/kitti/odom"]
    assert [timestamp for timestamp, _ in odometry] == [EPOCH_NS + round(TIMES[k] * 1e9) for k in (1, 2)]
    for (_, odom), number in zip(odometry, (1, 2), strict=True):
        assert np.allclose(odometry_to_pose(odom), whole[number].pose, atol=1e-12)
    clouds = [decode_cloud(cloud).points for _, cloud in messages["/kitti/velo/pointcloud"]]
    assert [points.tobytes() for points in clouds] == [frames[k][0].tobytes() for k in (1, 2)]


def test_kitti_to_bag_probabilities_and_frames(dataset, tmp_path: Path) -> None:
    root, frames, probabilities = dataset
    out = tmp_path / "probs"
    assert convert("--dataset", root, "--sequence", "08", "--out", out, "--probabilities-dir", "probabilities",
                   "--frames", "1:3") == 0
    messages, _, _ = read_bag(out)
    clouds = messages["/kitti/velo/pointcloud"]
    assert [t for t, _ in clouds] == [EPOCH_NS + round(t * 1e9) for t in TIMES[1:3]]
    for (_, cloud), number in zip(clouds, [1, 2]):
        names = [f.name for f in cloud.fields]
        assert names == ["x", "y", "z", "intensity"] + [f"prob_{k}" for k in range(20)]
        decoded = decode_cloud(cloud, 20)
        assert decoded.points.tobytes() == frames[number][0].tobytes()
        # the dataset stores float16; the bag carries exactly their float32 values
        assert np.array_equal(decoded.probabilities, probabilities[number].astype(np.float16).astype(np.float32))
        assert decoded.labels is None


def test_kitti_to_bag_errors(dataset, tmp_path: Path, capsys) -> None:
    root, _, _ = dataset
    assert convert("--dataset", tmp_path / "missing", "--sequence", "8", "--out", tmp_path / "a") == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("kitti_to_bag: error:") and "missing" in error[0]
    assert not (tmp_path / "a").exists()

    assert convert("--dataset", root, "--sequence", "8", "--out", tmp_path / "b", "--predictions-dir", "nope") == 2
    assert "nope" in capsys.readouterr().err

    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    assert convert("--dataset", root, "--sequence", "8", "--out", existing) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == [f"kitti_to_bag: error: {existing} exists (use --force to replace it)"]
    assert (existing / "keep.txt").read_text() == "mine"
    assert convert("--dataset", root, "--sequence", "8", "--out", existing, "--force", "--frames", "0:2") == 0
    assert not (existing / "keep.txt").exists() and (existing / "metadata.yaml").is_file()
    assert yaml.safe_load((existing / "metadata.yaml").read_text())["rosbag2_bagfile_information"][
        "message_count"] == 7  # 2 frames of 3 messages, and the mount once on /tf_static
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing"]  # no staging or old-bag folders left


def test_kitti_to_bag_failure_midway_leaves_nothing(dataset, tmp_path: Path, capsys) -> None:
    """A frame that cannot be read after others were written: exit 2, no bag, no partial folder."""
    import shutil

    root = tmp_path / "broken"
    shutil.copytree(dataset[0], root)
    (root / "sequences" / "08" / "predictions" / "000002.label").write_bytes(b"\0" * 8)  # 2 labels for 280 points
    assert convert("--dataset", root, "--sequence", "8", "--out", tmp_path / "bag") == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("kitti_to_bag: error:") and "000002.label" in error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken"]


def test_kitti_to_bag_module_entry_point(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "convbki_ros.tools.kitti_to_bag",
                             "--dataset", str(tmp_path / "none"), "--sequence", "0", "--out", str(tmp_path / "bag")],
                            capture_output=True, text=True, cwd=REPO, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1

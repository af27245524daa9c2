"""kitti_to_bag and play_bag on real files and real DDS: bags read back with rosbags, replays
received by an rclpy subscriber in this process while play_bag runs as a subprocess."""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from kitti_fixture import pose_about_z, write_sequence
from ros_helpers import Probe, domain_id, odometry_to_pose

from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.inputs.transforms import stamp_to_ns, transform_to_pose
from convbki_ros.tools import kitti_to_bag, play_bag

REPO = Path(__file__).resolve().parents[2]
EPOCH_NS = 1_700_000_000_000_000_000
TIMES = [0.0, 0.1037, 0.2071, 0.3109]
FRAME_SIZES = [300, 301, 280, 333]
TOPICS = {"/kitti/velo/pointcloud": "sensor_msgs/msg/PointCloud2", "/kitti/odom": "nav_msgs/msg/Odometry",
          "/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage"}
@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    """A 4-frame sequence 08: first pose not identity, raw ids with instance bits, probabilities."""
    root = tmp_path_factory.mktemp("kitti")
    rng = np.random.default_rng(8)
    frames, poses, probabilities = [], [], []
    for number, size in enumerate(FRAME_SIZES):
        points = rng.normal(scale=8.0, size=(size, 3)).astype(np.float32)
        truth = rng.choice([10, 40, 50, 70], size).astype(np.uint32)
        predicted = rng.choice([10, 40, 48, 50, 252], size).astype(np.uint32) | (rng.integers(0, 9, size) << 16).astype(
            np.uint32)
        frames.append((points, truth, predicted))
        poses.append(pose_about_z(0.3 + 0.05 * number, [5.0 + number, -2.0 + 0.5 * number, 0.25]))
        p = rng.random((size, 20))
        probabilities.append(p / p.sum(axis=1, keepdims=True))
    write_sequence(root, "08", frames, poses, times=TIMES, probabilities=probabilities)
    return root, frames, probabilities


def convert(*argv: str) -> int:
    return kitti_to_bag.main([str(a) for a in argv])


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


def test_to_rclpy_equals_rclpy_deserialisation(dataset, tmp_path: Path) -> None:
    """The generic rosbags -> rclpy converter gives what rclpy itself decodes from the same bytes."""
    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    root, _, _ = dataset
    out = tmp_path / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", out, "--frames", "0:1") == 0
    store = get_typestore(Stores.ROS2_JAZZY)
    checked = set()
    with Reader(out) as reader:
        for connection, _, data in reader.messages():
            if connection.msgtype.startswith("tf2_msgs/"):
                continue  # no rclpy package for it in the PyPI wheels
            cls = play_bag.rclpy_message_class(connection.msgtype)
            converted = play_bag.to_rclpy(store.deserialize_cdr(data, connection.msgtype), cls)
            assert converted == deserialize_message(bytes(data), cls)
            # (bytes may differ in CDR alignment padding, which rosbags leaves uninitialised)
            assert deserialize_message(serialize_message(converted), cls) == converted
            checked.add(connection.msgtype)
    assert checked == {"sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry"}


# ----------------------------------------------------------------------------- play_bag over DDS


class Listener:
    """An rclpy subscriber node in its own context (this process), on one ROS domain."""

    def __init__(self, domain: int, cloud_topic: str, odom_topic: str):
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import PointCloud2

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("bag_listener", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.clouds, self.odoms, self.clocks = [], [], []
        self.node.create_subscription(PointCloud2, cloud_topic, self.clouds.append, qos)
        self.node.create_subscription(Odometry, odom_topic, self.odoms.append, qos)
        self.node.create_subscription(Clock, "/clock", lambda m: self.clocks.append(stamp_to_ns(m.clock)), qos)
        self.tf, self.tf_static = [], []
        try:
            from rclpy.qos import DurabilityPolicy
            from tf2_msgs.msg import TFMessage
        except ImportError:  # no TF where tf2_msgs is not built
            return
        latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(TFMessage, "/tf", self.tf.append, qos)
        self.node.create_subscription(TFMessage, "/tf_static", self.tf_static.append, latched)

    def spin_until(self, done, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not done():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def _play(bag: Path, domain: int, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "convbki_ros.tools.play_bag", str(bag), *args], cwd=REPO, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@contextlib.contextmanager
def _playing(bag: Path, domain: int, *args: str):
    """``_play``, and a player still running when the block ends (a failed test) is killed."""
    process = _play(bag, domain, *args)
    try:
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()


@pytest.mark.parametrize("mode", ["raw", "deserialize"])
def test_play_bag_publishes_everything_in_order(dataset, tmp_path: Path, monkeypatch, mode: str) -> None:
    root, frames, _ = dataset
    bag = tmp_path / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", bag) == 0
    domain = domain_id()
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if mode == "raw":
        cloud_topic, odom_topic = "/kitti/velo/pointcloud", "/kitti/odom"
        extra = ["--clock", "--rate", "4"]
    else:  # converted messages, our --remap and a ROS remap rule
        cloud_topic, odom_topic = "/cloud_in", "/odom"
        extra = ["--clock", "--rate", "4", "--deserialize", "--remap", "/kitti/odom:=/odom",
                 "--ros-args", "-r", "/kitti/velo/pointcloud:=/cloud_in"]
    listener = Listener(domain, cloud_topic, odom_topic)
    try:
        with _playing(bag, domain, "--wait-subscribers", "20", *extra) as process:
            listener.spin_until(lambda: len(listener.clouds) == 4 and len(listener.odoms) == 4
                                and len(listener.clocks) >= 4 and len(listener.tf) == 4, timeout=40)
            _, stderr = process.communicate(timeout=30)
    finally:
        listener.close()
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr and "skipping" not in stderr
    stamps = [EPOCH_NS + round(t * 1e9) for t in TIMES]
    assert [stamp_to_ns(m.transforms[0].header.stamp) for m in listener.tf] == stamps
    assert [(m.transforms[0].header.frame_id, m.transforms[0].child_frame_id) for m in listener.tf_static] == [
        ("camera_gray_left", "velo_link")]
    assert [stamp_to_ns(m.header.stamp) for m in listener.clouds] == stamps
    assert [stamp_to_ns(m.header.stamp) for m in listener.odoms] == stamps
    assert listener.clocks == stamps  # one /clock per bag timestamp, in order
    for cloud, (points, _, predicted) in zip(listener.clouds, frames):
        decoded = decode_cloud(cloud)
        assert decoded.points.tobytes() == points.tobytes()
        assert np.array_equal(decoded.labels, predicted.astype(np.int64))


def test_play_bag_paces_by_stamps_and_stops_on_ctrl_c(dataset, tmp_path: Path) -> None:
    import signal

    root, _, _ = dataset
    bag = tmp_path / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", bag) == 0
    # rate 0.01: the 4 frames would take ~31 s; SIGINT once the first cloud has arrived must end
    # it with 0, before the next stamp is due.
    from sensor_msgs.msg import PointCloud2

    domain = domain_id()
    probe = Probe(domain)
    clouds = probe.subscribe(PointCloud2, "/kitti/velo/pointcloud")
    try:
        with _playing(bag, domain, "--rate", "0.01", "--wait-subscribers", "30") as process:
            assert probe.spin_until(lambda: bool(clouds), 60), "the first cloud never arrived"
            process.send_signal(signal.SIGINT)
            _, stderr = process.communicate(timeout=30)  # a bound for a hung player, not a measurement
    finally:
        probe.close()
    assert process.returncode == 0
    # Only the first timestamp's messages (/tf_static, /tf, odometry, cloud) were due: pacing by the
    # stamps. Ctrl-C may land while that stamp's messages are still going out (the cloud can arrive
    # before its publish call returns), so the count is at most 4; without pacing all 13 would be
    # out by then.
    assert "Traceback" not in stderr
    sent = int(re.search(r"interrupted after (\d+) messages", stderr).group(1))
    assert sent <= 4, stderr


def test_play_bag_bad_input_is_one_line(tmp_path: Path) -> None:
    assert play_bag.main([str(tmp_path / "nothing")]) == 2
    not_a_bag = tmp_path / "folder"
    not_a_bag.mkdir()
    result = subprocess.run([sys.executable, "-m", "convbki_ros.tools.play_bag", str(not_a_bag)], capture_output=True,
                            text=True, cwd=REPO, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"play_bag: error: {not_a_bag}: no such bag (a rosbag2 folder with metadata.yaml, or a .mcap/.db3 file)"]


def test_play_bag_says_so_when_a_subscriber_goes_away(dataset, tmp_path: Path) -> None:
    """A subscriber that leaves during the replay did not get the rest: exit 1, the topic and the count."""
    root, _, _ = dataset
    bag = tmp_path / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", bag) == 0
    domain = domain_id()
    listener = Listener(domain, "/kitti/velo/pointcloud", "/kitti/odom")
    try:
        # rate 0.1: the 4 stamps are 1 s apart, time enough to see the subscription go.
        with _playing(bag, domain, "--rate", "0.1", "--wait-subscribers", "20") as process:
            listener.spin_until(lambda: len(listener.clouds) >= 1, timeout=40)
            assert listener.clouds, "the first cloud never arrived"
            for subscription in list(listener.node.subscriptions):
                if subscription.topic_name == "/kitti/velo/pointcloud":
                    listener.node.destroy_subscription(subscription)
            _, stderr = process.communicate(timeout=60)
    finally:
        listener.close()
    assert process.returncode == play_bag.NOT_DELIVERED, stderr
    assert "Traceback" not in stderr
    gone = re.search(r"play_bag: error: /kitti/velo/pointcloud: 1 subscriber\(s\) went away after message (\d) "
                     r"of 4: what they had not acknowledged was not delivered", stderr)
    assert gone and 1 <= int(gone.group(1)) <= 2, stderr
    assert "/kitti/odom: " not in stderr.split("published", 1)[1]  # the odometry's subscriber stayed


def test_a_paced_replay_and_a_paused_player_lose_nothing(dataset, tmp_path: Path) -> None:
    """The mapper node, then play_bag --wait-for-node at full speed, then play_bag stopped (SIGSTOP)
    for longer than Fast DDS's default participant lease (20 s) and resumed: every cloud integrated,
    and the player never lost sight of the node."""
    import signal

    from mapper_rig import Rig

    root, _, _ = dataset
    bag = tmp_path / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", bag) == 0
    remaps = ["--remap", "/kitti/velo/pointcloud:=/cloud_in", "--remap", "/kitti/odom:=/odom"]
    rig = Rig(tmp_path, "-p", "pose_wait_timeout:=0.0", "-p", "save_on_shutdown:=false",
              "-p", "stamp_backwards_tolerance:=1000000.0", watch_map=False)
    try:
        with _playing(bag, rig.domain, "--wait-for-node", *remaps) as process:
            _, stderr = process.communicate(timeout=120)
        assert process.returncode == 0, stderr
        assert "play_bag: /convbki_mapper received 4 of 4 clouds, integrated 4, dropped 0 in " in stderr, stderr
        assert rig.wait_stats(lambda s: s.integrated == 4).dropped == 0

        # The same bag again (its stamps are taken as a second pass, not as time going back),
        # paced by the node's progress too, stopped after its first cloud for 21 s.
        with _playing(bag, rig.domain, "--rate", "0.1", "--wait-for-node", *remaps) as process:
            rig.wait_stats(lambda s: s.scans_in >= 5)
            process.send_signal(signal.SIGSTOP)
            stopped = time.monotonic()
            rig.probe.spin_until(lambda: False, 21.0)  # the pause under test, not a synchronisation
            assert time.monotonic() - stopped >= 21.0
            process.send_signal(signal.SIGCONT)
            _, stderr = process.communicate(timeout=90)
        assert re.search(r"resumed 1 time\(s\) after falling behind the bag's pace .* the longest 2\d\.\d s", stderr)
        # The player's participants did not expire the node's on resuming (the node's profile
        # announces a lease longer than the stop), so nothing was sent to no one.
        assert "DDS had forgotten" not in stderr, stderr
        assert process.returncode == 0, stderr
        assert "play_bag: /convbki_mapper received 4 of 4 clouds, integrated 4, dropped 0 in " in stderr, stderr
        assert rig.wait_stats(lambda s: s.integrated == 8).dropped == 0
    finally:
        rig.close()


def test_the_pacer_gives_up_clouds_the_node_never_received_and_says_how_many(monkeypatch):
    """--wait-for-node: clouds that DDS lost are not waited for forever; after LOST_AFTER_S of
    no progress they count as missing (and play_bag exits 1 on them). The pacer as play_bag
    builds it, on a node of its own, hears a stand-in mapper's /diagnostics over DDS; only the
    clock is the test's, so that LOST_AFTER_S passes in a few spins."""
    import threading

    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    class Clock:  # each reading a quarter of a second after the one before
        now = 100.0

        def monotonic(self):
            self.now += 0.25
            return self.now

    domain = domain_id()
    player, mapper = Probe(domain, "play_bag"), Probe(domain, "convbki_mapper")
    reports = mapper.node.create_publisher(DiagnosticArray, "/diagnostics", 10)

    def report(scans: int) -> None:  # what the mapper's counters say: it received and integrated ``scans``
        values = {"scans_in": scans, "integrated": scans, "dropped": 0, "queue": 0, "queue_limit": 100}
        reports.publish(DiagnosticArray(status=[DiagnosticStatus(
            name="/convbki_mapper: mapping", values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]))

    stop = threading.Event()
    # Once the pacer waits for the rest: the node got 1 of the 4, and keeps reporting the same counts.
    keep_reporting = threading.Thread(target=lambda: [report(11) for _ in iter(lambda: stop.wait(0.05), True)])
    try:
        pacer = play_bag.NodePacer(player.node, "/convbki_mapper")
        assert player.spin_until(lambda: reports.get_subscription_count() > 0, 20)
        report(10)
        assert pacer.wait_for_node(20.0, lambda: True) and pacer.baseline.scans_in == 10
        clock = Clock()
        monkeypatch.setattr(play_bag, "time", clock)
        pacer.sent(4)
        keep_reporting.start()
        started = clock.now
        line = pacer.finish(lambda: True)
    finally:
        stop.set()
        if keep_reporting.is_alive():
            keep_reporting.join()
        player.close()
        mapper.close()
    assert pacer.lost == 3 and pacer.missing == 3 and clock.now - started >= play_bag.LOST_AFTER_S
    assert line.startswith("/convbki_mapper received 1 of 4 clouds, integrated 1, dropped 0")

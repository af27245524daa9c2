"""play_bag on real DDS: bags made by kitti_to_bag replayed while an rclpy subscriber in this
process receives them (order, stamps, /clock, remaps, converted messages, pacing by stamps,
Ctrl-C, a subscriber that goes away), paced to the mapper node's progress and stopped and
resumed, the pacer's count of clouds DDS lost, and the rosbags -> rclpy converter that the
replay falls back on. The ``dataset`` fixture is test/ros/conftest.py's; most replays of the
selected tests run side by side (``replays``), each on a ROS domain of its own; the paced and
paused one starts with the test run."""

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
from bag_fixture import EPOCH_NS, TIMES, convert, write_dataset
from ros_helpers import Probe, domain_id, selected_tests

from convbki_ros.inputs.cloud_decoding import decode_cloud
from convbki_ros.inputs.transforms import stamp_to_ns
from convbki_ros.tools import node_pacing, play_bag
from convbki_ros.tools.bag_reading import rclpy_message_class, to_rclpy

REPO = Path(__file__).resolve().parents[2]


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
            cls = rclpy_message_class(connection.msgtype)
            converted = to_rclpy(store.deserialize_cdr(data, connection.msgtype), cls)
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


# The replays below mostly wait (a player's start and DDS discovery, the acknowledgements it
# waits for at the end): each runs on a ROS domain of its own, and the ``replays`` fixture runs
# those of the selected tests side by side, each test then checking its own. The paced and paused
# one, with its 21 s stop, starts with the test run (``early_start``, test/conftest.py).


def _in_order(bag: Path, mode: str) -> tuple[subprocess.Popen, str, Listener]:
    """play_bag at 4x with /clock to a listener: raw, or (``deserialize``) converted messages under
    our --remap and a ROS remap rule. The player, its stderr, and what the listener received."""
    domain = domain_id()
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
    return process, stderr, listener


def _interrupted(bag: Path) -> tuple[subprocess.Popen, str]:
    """play_bag at rate 0.01 (the 4 frames would take ~31 s), SIGINT once the first cloud has arrived."""
    import signal

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
    return process, stderr


def _subscriber_leaves(bag: Path) -> tuple[subprocess.Popen, str]:
    """play_bag at rate 0.1 (the 4 stamps 10 s apart: time to see the subscription go) to a listener
    whose cloud subscription is destroyed once the first cloud has arrived."""
    domain = domain_id()
    listener = Listener(domain, "/kitti/velo/pointcloud", "/kitti/odom")
    try:
        with _playing(bag, domain, "--rate", "0.1", "--wait-subscribers", "20") as process:
            listener.spin_until(lambda: len(listener.clouds) >= 1, timeout=40)
            assert listener.clouds, "the first cloud never arrived"
            for subscription in list(listener.node.subscriptions):
                if subscription.topic_name == "/kitti/velo/pointcloud":
                    listener.node.destroy_subscription(subscription)
            _, stderr = process.communicate(timeout=60)
    finally:
        listener.close()
    return process, stderr


def _paced_and_paused(bag: Path, folder: Path) -> None:
    """The checks of test_a_paced_replay_and_a_paused_player_lose_nothing, in the order they happen."""
    import signal

    from mapper_rig import Rig

    remaps = ["--remap", "/kitti/velo/pointcloud:=/cloud_in", "--remap", "/kitti/odom:=/odom"]
    # /diagnostics every 0.05 s: what the pacer and the test read the node's progress from.
    rig = Rig(folder, "-p", "pose_wait_timeout:=0.0", "-p", "save_on_shutdown:=false",
              "-p", "stamp_backwards_tolerance:=1000000.0", watch_map=False, diagnostics_period=0.05, wait=False)
    try:
        # The player starts while the node does: --wait-for-node waits until the node reports.
        with _playing(bag, rig.domain, "--wait-for-node", *remaps) as process:
            rig.wait_ready()
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


def _paced_and_paused_from_the_start(tmp_path_factory) -> None:
    """``_paced_and_paused`` on a bag of its own: it starts with the test run (``early_start``),
    its 21 s stop beside the tests before it."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # for the rig's probe
    root, _, _ = write_dataset(tmp_path_factory.mktemp("kitti_paused"))
    _paced_and_paused(_bag_of(root, tmp_path_factory), tmp_path_factory.mktemp("replay"))


REPLAYS = {  # test: its replay, given the bag and a folder of its own
    "test_play_bag_publishes_everything_in_order[raw]": lambda bag, _: _in_order(bag, "raw"),
    "test_play_bag_publishes_everything_in_order[deserialize]": lambda bag, _: _in_order(bag, "deserialize"),
    "test_play_bag_paces_by_stamps_and_stops_on_ctrl_c": lambda bag, _: _interrupted(bag),
    "test_play_bag_says_so_when_a_subscriber_goes_away": lambda bag, _: _subscriber_leaves(bag),
}


def _bag_of(root: Path, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bag") / "bag"
    assert convert("--dataset", root, "--sequence", "8", "--out", path) == 0
    return path


@pytest.fixture(scope="module")
def bag(dataset, tmp_path_factory) -> Path:
    """The 4-frame sequence as a bag, which the replays only read."""
    return _bag_of(dataset[0], tmp_path_factory)


@pytest.fixture(scope="module")
def replays(request, bag, tmp_path_factory):
    """``replays(test name)``: what that test's replay returned (its failure raised), once it is done.
    The replays of every selected test of this module start together, each in a thread; one not
    started yet starts when asked for."""
    from concurrent.futures import ThreadPoolExecutor

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # for the listeners' contexts
    pool = ThreadPoolExecutor(max_workers=len(REPLAYS))
    running = {}

    def replay(test: str):
        if test not in running:
            running[test] = pool.submit(REPLAYS[test], bag, tmp_path_factory.mktemp("replay"))
        return running[test].result()

    for test in REPLAYS.keys() & selected_tests(request):
        running[test] = pool.submit(REPLAYS[test], bag, tmp_path_factory.mktemp("replay"))
    yield replay
    pool.shutdown(wait=True, cancel_futures=True)


@pytest.mark.parametrize("mode", ["raw", "deserialize"])
def test_play_bag_publishes_everything_in_order(dataset, replays, request, mode: str) -> None:
    _, frames, _ = dataset
    process, stderr, listener = replays(request.node.name)
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


def test_play_bag_paces_by_stamps_and_stops_on_ctrl_c(replays, request) -> None:
    # SIGINT once the first cloud has arrived must end it with 0, before the next stamp is due.
    process, stderr = replays(request.node.name)
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


def test_play_bag_says_so_when_a_subscriber_goes_away(replays, request) -> None:
    """A subscriber that leaves during the replay did not get the rest: exit 1, the topic and the count."""
    process, stderr = replays(request.node.name)
    assert process.returncode == play_bag.NOT_DELIVERED, stderr
    assert "Traceback" not in stderr
    gone = re.search(r"play_bag: error: /kitti/velo/pointcloud: 1 subscriber\(s\) went away after message (\d) "
                     r"of 4: what they had not acknowledged was not delivered", stderr)
    # play_bag counts the subscribers before its first message and after each stamp's messages:
    # the listener leaves once the first cloud arrived, so the departure is seen after the first
    # or, where the player looked just before the listener left, the second.
    assert gone and 1 <= int(gone.group(1)) <= 2, stderr
    assert "/kitti/odom: " not in stderr.split("published", 1)[1]  # the odometry's subscriber stayed


@pytest.mark.early_start.with_args(_paced_and_paused_from_the_start)
def test_a_paced_replay_and_a_paused_player_lose_nothing(early_result) -> None:
    """The mapper node, then play_bag --wait-for-node at full speed, then play_bag stopped (SIGSTOP)
    for longer than Fast DDS's default participant lease (20 s) and resumed: every cloud integrated,
    and the player never lost sight of the node. (The checks are in ``_paced_and_paused``, which
    starts with the test run: most of its time is the stop.)"""


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
        pacer = node_pacing.NodePacer(player.node, "/convbki_mapper")
        assert player.spin_until(lambda: reports.get_subscription_count() > 0, 20)
        report(10)
        assert pacer.wait_for_node(20.0, lambda: True) and pacer.baseline.scans_in == 10
        clock = Clock()
        monkeypatch.setattr(node_pacing, "time", clock)
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
    assert pacer.lost == 3 and pacer.missing == 3 and clock.now - started >= node_pacing.LOST_AFTER_S
    assert line.startswith("/convbki_mapper received 1 of 4 clouds, integrated 1, dropped 0")

"""The node's correction thread against the update thread's timing, in one process (no DDS): a
Path that waits for clouds queued before its newest keyframe lets no logged scan fall out of a
bounded log meanwhile, so the log it corrects still holds every scan it moves; a Path that
overtook the clouds it reaches waits for them, and for the one the update thread is integrating;
a Path's bytes become keyframes."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2

from convbki_core.config import MapperConfig
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.mapper import ConvBKIMapper
from convbki_ros.inputs.sync import CloudQueue
from convbki_ros.mapping.corrections import CorrectionRunner, Keyframes

NUM_CLASSES = 4
BOUND = 6  # scans the log keeps
STAMP_0 = 1_000_000_000  # ns, scan 0's stamp; scan k is stamped STAMP_0 + k


def wait_for(condition, timeout: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


class Rig:
    """A mapper with a log of ``BOUND`` scans holding ``BOUND`` scans (stamps 1 s + scan number
    ns), the real cloud queue, and the correction thread's ``_apply`` on a Path whose newest
    keyframe is stamped as scan ``BOUND``, run in a thread; ``corrected_logs``: the log copies
    it went on to correct with."""

    def __init__(self):
        self.rng = np.random.default_rng(5)
        self.mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu",
                                                       scan_log_scans=BOUND),
                                    ConvBKIKernel("single", NUM_CLASSES, 5, 0.2, ell=[0.4]))
        self.queue = CloudQueue(max_pose_jump=10.0)
        self.core = SimpleNamespace(map_lock=threading.Lock(), mapper=self.mapper, lineage=0, queue=self.queue)
        for number in range(BOUND):
            self.integrate(number)
        assert self.mapper.scan_log.frozen == 0 and len(self.mapper.scan_log) == BOUND
        self.keyframes = Keyframes(np.array([STAMP_0, STAMP_0 + BOUND]), np.stack([np.eye(4)] * 2), 0.0)
        self.runner = CorrectionRunner(self.core, SimpleNamespace(param=lambda name: 0.0), warnings=None)
        self.corrected_logs = []
        self.runner._correct = lambda keyframes, live, lineage, log, started: \
            self.corrected_logs.append(log)
        self.thread = threading.Thread(target=self.runner._apply, args=(self.keyframes,))

    def integrate(self, number: int) -> None:
        """Scan ``number`` mapped as the update thread maps it."""
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * number, 0.0, 0.0]
        with self.core.map_lock:
            self.mapper.integrate(self.rng.uniform(-2, 2, (150, 3)).astype(np.float32),
                                  self.rng.integers(0, NUM_CLASSES, 150), pose, stamp_ns=STAMP_0 + number)
        with self.queue.changed:
            self.queue.changed.notify_all()


def cloud_stamped(number: int) -> PointCloud2:
    cloud = PointCloud2()
    cloud.header.stamp.sec, cloud.header.stamp.nanosec = 1, number
    return cloud


def test_a_path_waiting_for_queued_clouds_lets_no_logged_scan_fall_out():
    rig = Rig()
    mapper, queue, thread, corrected_logs = rig.mapper, rig.queue, rig.thread, rig.corrected_logs
    integrate = rig.integrate
    # A cloud of the keyframes' time still queued (its odometry has not come) when the Path arrives.
    queue.push(cloud_stamped(BOUND), limit=10)
    thread.start()
    try:
        # While it waits, the update thread maps newer clouds, past the log's bound.
        assert wait_for(lambda: mapper.scan_log.held_from is not None), "the log is not held while the Path waits"
        for number in range(BOUND, 2 * BOUND):
            integrate(number)
        assert mapper.scan_log.frozen == 0 and len(mapper.scan_log) == 2 * BOUND
        assert thread.is_alive() and not corrected_logs  # still waiting for the queued cloud
        with queue.changed:  # the queued cloud is taken
            queue.clouds.clear()
            queue.changed.notify_all()
    finally:
        thread.join(timeout=30)
    assert not thread.is_alive()
    # The correction's copy reaches back to the first scan; the live log keeps its bound again.
    (log,) = corrected_logs
    assert log.frozen == 0 and [index for index, _ in log.scans()] == list(range(2 * BOUND))
    assert mapper.scan_log.held_from is None
    integrate(2 * BOUND)
    assert mapper.scan_log.frozen > 0 and len(mapper.scan_log) <= BOUND


def test_a_path_that_overtook_the_clouds_it_reaches_waits_for_them():
    # The Path arrives when the newest cloud received is older than its newest keyframe: the
    # keyframe's cloud is still on its way (a larger message, another topic).
    rig = Rig()
    rig.thread.start()
    try:
        assert wait_for(lambda: rig.mapper.scan_log.held_from is not None or rig.corrected_logs)
        assert not rig.corrected_logs, "it went on without the keyframe's scan"  # it waits for it
        rig.integrate(BOUND)  # the keyframe's cloud arrives and is mapped
    finally:
        rig.thread.join(timeout=30)
    assert not rig.thread.is_alive()
    (log,) = rig.corrected_logs
    assert [index for index, _ in log.scans()] == list(range(BOUND + 1))


def test_a_path_waits_for_the_cloud_the_update_thread_is_integrating():
    # The keyframe's cloud has arrived, and so has a newer one, but the update thread has taken the
    # keyframe's and not logged it yet: neither queued nor logged, it is still on its way into the map.
    rig = Rig()
    queue = rig.queue
    with queue.changed:
        queue.in_flight = STAMP_0 + BOUND  # what CloudQueue.next marks for the cloud it hands out
    queue.push(cloud_stamped(BOUND + 1), limit=10)
    rig.thread.start()
    try:
        assert wait_for(lambda: rig.mapper.scan_log.held_from is not None or rig.corrected_logs)
        assert not rig.corrected_logs, "it went on without the scan being integrated"  # it waits for it
        rig.integrate(BOUND)  # the update thread logs it, then says it is done
        queue.finished()
    finally:
        rig.thread.join(timeout=30)
    assert not rig.thread.is_alive()
    (log,) = rig.corrected_logs
    assert [index for index, _ in log.scans()] == list(range(BOUND + 1))


def serialized_path(frame: str, stamps: list[int], positions, quaternions, pose_frames=None) -> bytes:
    """A nav_msgs/Path as rclpy serializes it (what the node's raw subscription receives)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    from rclpy.serialization import serialize_message

    path = Path()
    path.header.frame_id = frame
    for number, (stamp, position, quaternion) in enumerate(zip(stamps, positions, quaternions, strict=True)):
        stamped = PoseStamped()
        stamped.header.frame_id = (pose_frames or [""] * len(stamps))[number]
        stamped.header.stamp.sec, stamped.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        p, q = stamped.pose.position, stamped.pose.orientation
        p.x, p.y, p.z = (float(v) for v in position)
        q.x, q.y, q.z, q.w = (float(v) for v in quaternion)
        path.poses.append(stamped)
    return serialize_message(path)


def test_a_path_becomes_keyframes_from_its_bytes_and_what_cannot_be_used_is_named():
    """path_keyframes over the raw bytes' decoding: each keyframe the pose its translation and
    (normalised) quaternion make, stamps in ns; a Path in another frame, empty, with a pose in
    another frame, a quaternion that is not a rotation, or stamps out of order is refused naming
    which pose."""
    from convbki_core.geometry.poses import pose_from_translation_quaternion
    from convbki_ros.inputs.path_decoding import decode_path
    from convbki_ros.mapping.corrections import path_keyframes

    rng = np.random.default_rng(3)
    quaternions = rng.normal(size=(5, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    quaternions[2] *= 1.005  # within the tolerance: normalised
    positions = rng.uniform(-50, 50, (5, 3))
    stamps = [7 * 10**9 + 10**8 * k + 3 for k in range(5)]

    def keyframes(*args, **kwargs):
        return path_keyframes(decode_path(serialized_path(*args, **kwargs), 100), "map")

    got = keyframes("map", stamps, positions, quaternions, pose_frames=["", "map", "", "map", ""])
    np.testing.assert_array_equal(got.stamps_ns, stamps)
    for number in range(5):
        want = pose_from_translation_quaternion(positions[number], quaternions[number] / np.linalg.norm(
            quaternions[number]))
        np.testing.assert_allclose(got.poses[number], want, atol=1e-12)
    assert keyframes("odom", stamps, positions, quaternions) == "its frame is 'odom', not the map's 'map'"
    assert keyframes("map", [], [], []) == "it holds no pose"
    assert keyframes("map", stamps, positions, quaternions, pose_frames=["", "", "", "odom", ""]) == \
        "pose 3 is in frame 'odom', not the map's 'map'"
    bad = quaternions.copy()
    bad[4] = [0.0, 0.0, 0.0, 0.0]
    assert keyframes("map", stamps, positions, bad).startswith("pose 4: orientation quaternion")
    nan = positions.copy()
    nan[1, 2] = np.nan
    assert keyframes("map", stamps, nan, quaternions).startswith("pose 1: position")
    assert keyframes("map", stamps[::-1], positions, quaternions).startswith(
        "its stamps are not in ascending order (pose 1 at 7.300 s after 7.400 s)")


class Logger:
    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(text)

    warning = error = info


def drive_with_paths():
    """A mapper whose log holds 16 scans (segments of 10), its scans, and two keyframe Paths
    that move them differently: A turns and shifts the drive from scan 0 on; B is A up to scan
    7's keyframe and shifts on from there (``agreeing``), or moves every scan otherwise."""
    rng = np.random.default_rng(11)
    config = MapperConfig.paper(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu", scan_log_scans=20)
    mapper = ConvBKIMapper(config, ConvBKIKernel("single", NUM_CLASSES, 5, 0.2, ell=[0.4]))
    scans = []
    for number in range(16):
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * number, 0.0, 0.0]
        scan = (rng.uniform(-2, 2, (150, 3)).astype(np.float32), rng.integers(0, NUM_CLASSES, 150), pose,
                STAMP_0 + number)
        scans.append(scan)
        mapper.integrate(*scan[:3], stamp_ns=scan[3])

    def moved(yaw: float, shift: float) -> np.ndarray:
        change = np.eye(4)
        change[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        change[1, 3] = shift
        return change

    a_last = moved(0.05, 0.6) @ scans[15][2]
    path_a = Keyframes(np.array([STAMP_0, STAMP_0 + 15]), np.stack([scans[0][2], a_last]), 0.0)
    return mapper, scans, path_a, moved


@pytest.mark.parametrize("newer", ["agreeing", "disagreeing"])
def test_a_newer_path_takes_over_a_running_correction_or_restarts_it(newer):
    """A Path that comes while a correction runs stops it before its next scan. Where it puts the
    scans already mapped again where the running one did, the correction goes on with its poses
    for the rest; otherwise it begins again from the first scan it moves. Either way the map in
    the end is the one mapped from scratch with the poses each scan was mapped again at."""
    from convbki_core.correction.replay import keyframe_corrections

    mapper, scans, path_a, moved = drive_with_paths()
    logged = mapper.scan_log.scans()
    poses_a = keyframe_corrections(logged, path_a.stamps_ns, path_a.poses)
    if newer == "agreeing":  # A's poses up to scan 7 (a keyframe there), more of a shift after it
        seventh = poses_a[7]
        path_b = Keyframes(np.array([STAMP_0, STAMP_0 + 7, STAMP_0 + 15]),
                           np.stack([scans[0][2], seventh, moved(0.0, 0.3) @ path_a.poses[1]]), 0.0)
    else:
        path_b = Keyframes(path_a.stamps_ns, np.stack([scans[0][2], moved(-0.04, -0.5) @ scans[15][2]]), 0.0)
    poses_b = keyframe_corrections(logged, path_b.stamps_ns, path_b.poses)
    switch = 8  # the scan before which B comes (A and B agree up to scan 7)

    core = SimpleNamespace(map_lock=threading.Lock(), mapper=mapper, lineage=0, queue=CloudQueue(max_pose_jump=10.0))
    core.replace_mapper = lambda new: setattr(core, "mapper", new)
    logger = Logger()
    node = SimpleNamespace(param={"correction_tolerance": 1e-6, "correction_min_move": 0.0}.get,
                           get_logger=lambda: logger, outputs=SimpleNamespace(map_replaced=lambda: None))
    runner = CorrectionRunner(core, node, warnings=None)
    plain_between = runner._between

    def between(since, live):
        check = plain_between(since, live)

        def look(index):
            if index == switch and runner.counts.retargeted + runner.counts.restarted == 0:
                with runner._changed:
                    runner._waiting = path_b  # what on_path does with a Path that moves something
            return check(index)
        return look

    runner._between = between
    runner._apply(path_a)
    assert core.mapper is not mapper and runner.counts.done == 1
    assert (runner.counts.retargeted, runner.counts.restarted) == ((1, 0) if newer == "agreeing" else (0, 1))
    assert "1 newer Paths took over" in logger.lines[-1]

    # From scratch: each scan at the pose it was mapped again at.
    fresh = ConvBKIMapper(mapper.config, mapper.kernel)
    for number, (points, labels, pose, stamp) in enumerate(scans):
        wanted = poses_a if newer == "agreeing" and number < switch else poses_b
        fresh.integrate(points, labels, wanted.get(number, pose), stamp_ns=stamp)
    got_indices, got_alpha = core.mapper.items()
    want_indices, want_alpha = fresh.items()
    got, want = np.lexsort(got_indices.T[::-1]), np.lexsort(want_indices.T[::-1])
    np.testing.assert_array_equal(got_indices[got], want_indices[want])
    np.testing.assert_array_equal(got_alpha[got], want_alpha[want])
    assert core.mapper.scan_log.pending is None


def test_a_newer_path_that_moves_nothing_ends_the_running_correction_and_its_pending_path():
    """A newer Path that puts every scan where the map has it: the running correction stops, the
    map in service stays, and its log keeps no Path to apply (a save would otherwise carry the
    stale one to map_tool correct)."""
    mapper, scans, path_a, _ = drive_with_paths()
    as_mapped = Keyframes(path_a.stamps_ns, np.stack([scans[0][2], scans[15][2]]), 0.0)
    core = SimpleNamespace(map_lock=threading.Lock(), mapper=mapper, lineage=0, queue=CloudQueue(max_pose_jump=10.0))
    node = SimpleNamespace(param={"correction_tolerance": 1e-6, "correction_min_move": 0.0}.get,
                           get_logger=lambda: Logger())
    runner = CorrectionRunner(core, node, warnings=None)
    plain_between = runner._between

    def between(since, live):
        check = plain_between(since, live)

        def look(index):
            if index == 5:
                assert mapper.scan_log.pending is not None  # A's, while it runs
                with runner._changed:
                    runner._waiting = as_mapped
            return check(index)
        return look

    runner._between = between
    runner._apply(path_a)
    assert core.mapper is mapper and runner.counts.done == 0 and runner.counts.unchanged == 1
    assert mapper.scan_log.pending is None

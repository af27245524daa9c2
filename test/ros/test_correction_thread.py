"""The node's correction thread against the update thread's timing, in one process (no DDS): a
Path that waits for clouds queued before its newest keyframe lets no logged scan fall out of a
bounded log meanwhile, so the log it corrects still holds every scan it moves; a Path that
overtook the clouds it reaches waits for them."""

import threading
import time
from types import SimpleNamespace

import numpy as np
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
        self.runner._correct = lambda keyframes, live, lineage, log, tolerance, started: \
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

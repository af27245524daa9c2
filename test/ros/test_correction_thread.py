"""The node's correction thread against the update thread's timing, in one process (no DDS):
a Path that waits for clouds queued before its newest keyframe lets no logged scan fall out of
a bounded log meanwhile, so the log it corrects still holds every scan it moves."""

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


def wait_for(condition, timeout: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_path_waiting_for_queued_clouds_lets_no_logged_scan_fall_out():
    rng = np.random.default_rng(5)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu",
                                              scan_log_scans=BOUND),
                           ConvBKIKernel("single", NUM_CLASSES, 5, 0.2, ell=[0.4]))

    def integrate(number: int) -> None:
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * number, 0.0, 0.0]
        with core.map_lock:  # as the update thread does
            mapper.integrate(rng.uniform(-2, 2, (150, 3)).astype(np.float32), rng.integers(0, NUM_CLASSES, 150),
                             pose, stamp_ns=1_000_000_000 + number)

    queue = CloudQueue(max_pose_jump=10.0)
    core = SimpleNamespace(map_lock=threading.Lock(), mapper=mapper, lineage=0, queue=queue)
    for number in range(BOUND):
        integrate(number)
    assert mapper.scan_log.frozen == 0 and len(mapper.scan_log) == BOUND
    # A cloud of the keyframes' time still queued (its odometry has not come) when the Path arrives.
    cloud = PointCloud2()
    cloud.header.stamp.sec, cloud.header.stamp.nanosec = 1, BOUND
    queue.push(cloud, limit=10)
    keyframes = Keyframes(np.array([1_000_000_000, 1_000_000_000 + BOUND]), np.stack([np.eye(4)] * 2), 0.0)

    runner = CorrectionRunner(core, SimpleNamespace(param=lambda name: 0.0), warnings=None)
    corrected_logs = []
    runner._correct = lambda keyframes, live, lineage, log, tolerance, started: corrected_logs.append(log)
    thread = threading.Thread(target=runner._apply, args=(keyframes,))
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

"""The queue of clouds waiting for their pose: bounded by count and bytes, not by the wall clock."""

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2

from convbki_ros.inputs.sync import CloudQueue, Verdict

SECOND = 1_000_000_000


def cloud(stamp_ns, size=1000):
    msg = PointCloud2()
    msg.header.stamp = Time(sec=stamp_ns // SECOND, nanosec=stamp_ns % SECOND)
    msg.data = bytes(size)
    return msg


def test_a_cloud_waits_for_its_odometry_as_long_as_the_queue_has_room():
    queue = CloudQueue(max_pose_jump=10.0)
    for number in range(5):
        assert not queue.push(cloud(number * SECOND), limit=10)
    assert queue.bytes == 5000
    clock = [0]
    # No time limit: however long the node's clock runs, nothing is decided without odometry.
    clock[0] = 3600 * SECOND
    assert queue._decide(0.0, lambda: clock[0]) is None and len(queue) == 5
    # Odometry covering the first two stamps comes at last: they are placed, the rest still wait.
    queue.add_odometry(0, np.eye(4), "velo_link")
    queue.add_odometry(int(1.5 * SECOND), np.eye(4), "velo_link")
    decided = [queue.next(0.0, lambda: clock[0]) for _ in range(2)]
    assert [d.verdict for d in decided] == [Verdict.PLACE, Verdict.PLACE]
    assert len(queue) == 3 and queue.waiting_for_pose() == 3 and queue.bytes == 3000


def test_a_full_queue_pushes_out_the_oldest_and_says_whether_it_was_waiting_for_a_pose():
    queue = CloudQueue(max_pose_jump=10.0)
    queue.add_odometry(0, np.eye(4), "velo_link")
    queue.add_odometry(2 * SECOND, np.eye(4), "velo_link")
    queue.push(cloud(SECOND), limit=3)  # its pose is known
    queue.push(cloud(5 * SECOND), limit=3)
    queue.push(cloud(6 * SECOND), limit=3)
    evicted = queue.push(cloud(7 * SECOND), limit=3)
    assert (evicted.ready, evicted.waiting_for_pose) == (1, 0)
    evicted = queue.push(cloud(8 * SECOND), limit=3)
    assert (evicted.ready, evicted.waiting_for_pose) == (0, 1)
    # Bytes bound it too: a cloud of 2500 bytes in a 3000-byte queue leaves room for itself only.
    evicted = queue.push(cloud(9 * SECOND, size=2500), limit=100, byte_limit=3000)
    assert evicted.waiting_for_pose == 3 and len(queue) == 1 and queue.bytes == 2500
    # One cloud larger than the limit is still taken (an empty queue always takes one).
    assert not CloudQueue(10.0).push(cloud(0, size=5000), limit=10, byte_limit=3000)


def test_a_time_limit_runs_in_the_nodes_clock():
    queue = CloudQueue(max_pose_jump=10.0)
    clock = [100 * SECOND]
    queue.push(cloud(SECOND), limit=10, clock_ns=clock[0])
    assert queue._decide(2.0, lambda: clock[0]) is None
    clock[0] += int(1.9 * SECOND)  # a paused bag stops the clock of a node on use_sim_time
    assert queue._decide(2.0, lambda: clock[0]) is None
    clock[0] += int(0.1 * SECOND)
    decision = queue._decide(2.0, lambda: clock[0])
    assert decision.verdict is Verdict.NO_POSE and len(queue) == 0 and queue.bytes == 0


def test_a_correction_lets_the_live_map_take_its_clouds_first_and_never_makes_it_drop_one():
    import threading

    from convbki_ros.mapping.correction_waits import let_live_scans_first

    queue = CloudQueue(max_pose_jump=10.0)
    queue.add_odometry(0, np.eye(4), "velo_link")
    queue.add_odometry(20 * SECOND, np.eye(4), "velo_link")
    for number in range(6):
        queue.push(cloud(number * SECOND), limit=100)
    assert queue.ready() == 6
    # More than `backlog` clouds wait: the correction waits whatever its time share (`longest`).
    waiting = threading.Thread(target=let_live_scans_first, args=(queue, lambda: False, 0.0, 4))
    waiting.start()
    waiting.join(0.5)
    assert waiting.is_alive()
    for _ in range(2):  # the update thread takes two: four are left, and the share is spent
        assert queue.next(0.0).verdict is Verdict.PLACE
    waiting.join(10.0)
    assert not waiting.is_alive() and queue.ready() == 4
    # A short queue: the correction waits for it to empty, `longest` seconds at most.
    started = threading.Event()

    def wait_long():
        started.set()
        let_live_scans_first(queue, lambda: False, 60.0, 4)

    waiting = threading.Thread(target=wait_long)
    waiting.start()
    started.wait(10.0)
    waiting.join(0.5)
    assert waiting.is_alive()
    while queue.ready():
        queue.next(0.0)
    waiting.join(10.0)
    assert not waiting.is_alive()
    # The node stopping ends any wait.
    for number in range(6, 12):
        queue.push(cloud(number * SECOND), limit=100)
    let_live_scans_first(queue, lambda: True, 0.0, 4)

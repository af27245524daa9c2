"""Odometry interpolation at a cloud's stamp."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from convbki_core.geometry.poses import pose_from_translation_quaternion
from convbki_ros.inputs.pose_buffer import MAX_POSES, OUTAGE_MIN_S, OdometryBuffer, PoseStatus, pose_problem


def yaw_pose(yaw, x):
    return pose_from_translation_quaternion(np.array([x, 2.0 * x, 0.5]),
                                            np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]))


def test_exact_and_interpolated_stamps():
    buffer = OdometryBuffer(tolerance_ns=0)
    buffer.add(100, yaw_pose(0.0, 0.0), "velo_link")
    buffer.add(300, yaw_pose(1.0, 2.0), "velo_link")
    exact = buffer.lookup(300)
    assert exact.status is PoseStatus.FOUND and exact.child_frame_id == "velo_link"
    np.testing.assert_allclose(exact.pose, yaw_pose(1.0, 2.0))
    middle = buffer.lookup(150)  # a quarter of the way
    np.testing.assert_allclose(middle.pose, yaw_pose(0.25, 0.5), atol=1e-12)
    assert buffer.lookup(50).status is PoseStatus.TOO_OLD
    assert buffer.lookup(301).status is PoseStatus.WAIT
    assert OdometryBuffer().lookup(5).status is PoseStatus.EMPTY


def test_out_of_order_insertion_and_history_limit():
    buffer = OdometryBuffer(history_ns=1000, tolerance_ns=0)
    for stamp in (500, 100, 300, 1400):
        buffer.add(stamp, yaw_pose(stamp * 1e-3, stamp * 1e-3))
    assert len(buffer) == 2 and buffer.latest_stamp == 1400  # 100 and 300 fell out of the last 1000 ns
    np.testing.assert_allclose(buffer.lookup(950).pose, yaw_pose(0.95, 0.95), atol=1e-12)


def test_the_history_is_bounded_by_count_too():
    """Odometry stamped a nanosecond apart stays within the history's time but not its count: the
    newest MAX_POSES are kept, and the newest still interpolate."""
    buffer = OdometryBuffer(tolerance_ns=0)
    pose = yaw_pose(0.0, 1.0)
    for stamp in range(MAX_POSES + 500):
        buffer.add(stamp, pose)
    assert len(buffer) == MAX_POSES and buffer.lookup(499).status is PoseStatus.TOO_OLD
    np.testing.assert_allclose(buffer.lookup(MAX_POSES + 400).pose, pose)


@given(st.floats(0.0, 1.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_interpolated_rotation_stays_a_rotation(fraction, yaw0, yaw1):
    buffer = OdometryBuffer(tolerance_ns=0)
    buffer.add(0, yaw_pose(yaw0, 0.0))
    buffer.add(10**9, yaw_pose(yaw1, 1.0))
    pose = buffer.lookup(int(fraction * 1e9)).pose
    rotation = pose[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
    assert abs(np.linalg.det(rotation) - 1.0) < 1e-9
    # A turn about z stays a turn about z, and its yaw lies between the inputs' on the shorter
    # arc (through +-pi when that is shorter), as far along it as the stamp is between theirs.
    np.testing.assert_allclose(rotation[2], [0.0, 0.0, 1.0], atol=1e-9)
    yaw = np.arctan2(rotation[1, 0], rotation[0, 0])
    arc = _wrapped(yaw1 - yaw0)
    np.testing.assert_allclose(abs(_wrapped(yaw - yaw0)) + abs(_wrapped(yaw1 - yaw)), abs(arc), atol=1e-9)
    travelled, expected = _wrapped(yaw - yaw0), int(fraction * 1e9) * 1e-9 * arc
    if np.pi - abs(arc) < 1e-6:  # a half turn: either way round is as short
        travelled, expected = abs(travelled), abs(expected)
    np.testing.assert_allclose(travelled, expected, atol=1e-9)


def _wrapped(angle):
    """``angle`` in [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def test_pose_problem_names_non_finite_and_non_unit_poses():
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    assert pose_problem([1.0, 2.0, 3.0], identity) is None
    assert pose_problem([0.0, 0.0, 0.0], identity * (1 + 1e-6)) is None  # float round-off is fine
    assert "position (nan, 0, 0) is not finite" in pose_problem([np.nan, 0.0, 0.0], identity)
    assert "is not finite" in pose_problem([0.0, 0.0, 0.0], [0.0, np.inf, 0.0, 1.0])
    assert "has norm 2, not 1" in pose_problem([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0])
    assert "has norm 0, not 1" in pose_problem([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0])


def test_no_interpolation_across_a_jump():
    buffer = OdometryBuffer(tolerance_ns=0, max_jump=5.0)
    assert buffer.add(0, yaw_pose(0.0, 0.0)) is None
    assert buffer.add(100, yaw_pose(0.0, 1.0)) is None  # 2.2 m: an ordinary step
    jump = buffer.add(200, yaw_pose(0.0, 21.0))  # (1, 2) -> (21, 42): 44.7 m
    assert jump is not None and abs(jump.distance - np.hypot(20.0, 40.0)) < 1e-9 and not jump.outage
    assert buffer.lookup(50).status is PoseStatus.FOUND
    assert buffer.lookup(150).status is PoseStatus.JUMP
    for exact in (100, 200):  # the poses themselves stay usable
        assert buffer.lookup(exact).status is PoseStatus.FOUND
    # A pose inserted inside the gap moves the jump to whichever side is still far.
    assert buffer.add(190, yaw_pose(0.0, 20.5)) is not None
    assert buffer.lookup(150).status is PoseStatus.JUMP
    assert buffer.lookup(195).status is PoseStatus.FOUND
    # Dropping the poses before the jump leaves an ordinary buffer that starts after it.
    buffer.drop_before(190)
    assert len(buffer) == 2 and buffer.lookup(150).status is PoseStatus.TOO_OLD
    assert buffer.lookup(195).status is PoseStatus.FOUND


def test_max_jump_zero_never_reports_a_jump():
    buffer = OdometryBuffer(tolerance_ns=0)
    buffer.add(0, yaw_pose(0.0, 0.0))
    assert buffer.add(100, yaw_pose(0.0, 1000.0)) is None
    assert buffer.lookup(50).status is PoseStatus.FOUND


SECOND = 1_000_000_000
PERIOD = SECOND // 10  # a 10 Hz odometry


def odometry_at_10_hz(buffer, seconds, speed=15.0, start=0.0):
    """Poses of a car at ``speed`` m/s along the diagonal, one every 0.1 s for ``seconds``."""
    for step in range(int(seconds * 10)):
        stamp = int(start * SECOND) + step * PERIOD
        buffer.add(stamp, yaw_pose(0.0, speed * stamp / SECOND / np.sqrt(5.0)))
    return buffer.latest_stamp


def test_an_outage_then_a_far_pose_is_an_outage_not_a_jump():
    buffer = OdometryBuffer(history_ns=60 * SECOND, tolerance_ns=0, max_jump=10.0)
    last = odometry_at_10_hz(buffer, 5.0)
    # No odometry for 10 s while the car goes on at 15 m/s: 150 m further on.
    resumed = last + 10 * SECOND
    found = buffer.add(resumed, yaw_pose(0.0, 15.0 * resumed / SECOND / np.sqrt(5.0)))
    assert found is not None and found.outage
    assert abs(found.gap_s - 10.0) < 1e-9 and abs(found.distance - 150.0) < 1e-6
    assert buffer.lookup(last + 5 * SECOND).status is PoseStatus.OUTAGE
    # The odometry goes on at its rate after the outage, and so does the mapping.
    assert buffer.add(resumed + PERIOD, yaw_pose(0.0, 15.0 * (resumed + PERIOD) / SECOND / np.sqrt(5.0))) is None
    assert buffer.lookup(resumed + PERIOD // 2).status is PoseStatus.FOUND


def test_a_jump_within_continuous_odometry_is_a_jump():
    buffer = OdometryBuffer(history_ns=60 * SECOND, tolerance_ns=0, max_jump=10.0)
    last = odometry_at_10_hz(buffer, 5.0)
    found = buffer.add(last + PERIOD, yaw_pose(0.0, 100.0))  # the next message, ~150 m away
    assert found is not None and not found.outage and abs(found.gap_s - 0.1) < 1e-9
    assert buffer.lookup(last + PERIOD // 2).status is PoseStatus.JUMP
    # A few lost messages are not an outage either: the gap is short against the odometry's rate.
    buffer = OdometryBuffer(history_ns=60 * SECOND, tolerance_ns=0, max_jump=10.0)
    last = odometry_at_10_hz(buffer, 5.0)
    found = buffer.add(last + 5 * PERIOD, yaw_pose(0.0, 100.0))
    assert found is not None and not found.outage


def test_the_outage_gap_follows_the_odometry_rate():
    slow = OdometryBuffer(history_ns=600 * SECOND, tolerance_ns=0, max_jump=10.0)
    for step in range(20):  # 1 Hz odometry (a GPS): a 5 s gap is five missed fixes, not an outage
        slow.add(step * SECOND, yaw_pose(0.0, 0.0))
    assert slow.outage_gap_ns() == 10 * SECOND
    assert not slow.add(24 * SECOND, yaw_pose(0.0, 100.0)).outage
    assert OdometryBuffer().outage_gap_ns() == OUTAGE_MIN_S * SECOND  # too few poses to know a rate

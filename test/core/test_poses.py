"""Poses and quaternions (``convbki_core.geometry.poses``): conversions both ways, slerp, interpolation."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from convbki_core.geometry import poses


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of (x, y, z, w) quaternions (rotation b, then a): the reference."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


unit_quaternions = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1).map(lambda q: np.array(q) / np.linalg.norm(q))


@given(unit_quaternions)
def test_quaternion_matrix_round_trip(q) -> None:
    rotation = poses.quaternion_to_matrix(q)
    assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(rotation), 1.0)
    back = poses.matrix_to_quaternion(rotation)
    assert back[3] >= 0
    # q and -q are the same rotation: back is one of them, the one with w >= 0 unless w is ~0
    # (then round-off decides the sign, and either is right).
    assert np.allclose(back, q, atol=1e-9) or np.allclose(back, -q, atol=1e-9), (back, q)
    if abs(q[3]) > 1e-9:
        assert np.allclose(back, np.sign(q[3]) * q, atol=1e-9), (back, q)
    assert np.allclose(poses.quaternion_to_matrix(back), rotation, atol=1e-12)


def test_quaternion_known_values_and_batches() -> None:
    quarter = poses.matrix_to_quaternion(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float))
    assert np.allclose(quarter, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    half_x = poses.matrix_to_quaternion(np.diag([1.0, -1.0, -1.0]))  # trace -1: a non-w pivot
    assert np.allclose(np.abs(half_x), [1, 0, 0, 0])
    rng = np.random.default_rng(0)
    qs = rng.normal(size=(7, 5, 4))
    qs /= np.linalg.norm(qs, axis=-1, keepdims=True)
    assert np.allclose(poses.quaternion_to_matrix(poses.matrix_to_quaternion(poses.quaternion_to_matrix(qs))),
                       poses.quaternion_to_matrix(qs), atol=1e-12)
    a, b = qs[0, 0], qs[0, 1]
    assert np.allclose(poses.quaternion_to_matrix(quaternion_multiply(a, b)),
                       poses.quaternion_to_matrix(a) @ poses.quaternion_to_matrix(b), atol=1e-12)


def _angle(a, b) -> float:
    return 2 * np.arccos(np.clip(abs(np.dot(a, b)), -1, 1))


@given(unit_quaternions, unit_quaternions, st.floats(0, 1))
def test_slerp_properties(q0, q1, t) -> None:
    assert np.allclose(poses.quaternion_to_matrix(poses.slerp(q0, q1, 0.0)), poses.quaternion_to_matrix(q0), atol=1e-9)
    assert np.allclose(poses.quaternion_to_matrix(poses.slerp(q0, q1, 1.0)), poses.quaternion_to_matrix(q1), atol=1e-9)
    q = poses.slerp(q0, q1, t)
    assert np.isclose(np.linalg.norm(q), 1.0)
    total = _angle(q0, q1)
    assume(total > 1e-4)
    assert total <= np.pi + 1e-9  # the shortest way round
    assert np.isclose(_angle(q0, q), t * total, atol=1e-6)  # constant angular speed
    assert np.isclose(_angle(q, q1), (1 - t) * total, atol=1e-6)


def test_interpolate_pose_midway() -> None:
    p0 = poses.pose_from_translation_quaternion([0, 0, 0], [0, 0, 0, 1])
    p1 = poses.pose_from_translation_quaternion([2, 4, 6], [0, 0, 1, 0])  # 180 deg about z
    mid = poses.interpolate_pose(p0, p1, 0.5)
    assert np.allclose(mid[:3, 3], [1, 2, 3])
    assert np.allclose(mid[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12) or np.allclose(
        mid[:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)

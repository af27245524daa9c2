"""Poses and quaternions: pure numpy, shared by the method (a SLAM's corrections move logged
scans between keyframes) and the ROS side (TF, odometry, bags).

Conventions: quaternions are ``(x, y, z, w)`` as in geometry_msgs; a pose is a 4x4
homogeneous matrix ``parent <- child`` (e.g. ``map <- velo_link``).
"""

from __future__ import annotations

import numpy as np

# ----------------------------------------------------------------------------- quaternions


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> unit quaternions ``(..., 4)`` (x, y, z, w), w >= 0.

    Shepperd's method, vectorised: each matrix uses the best-conditioned of four formulas.
    """
    m = np.asarray(rotation, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must have shape (..., 3, 3), got {m.shape}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    # Candidates (each row: x, y, z, w scaled by 4 * component), pick the largest pivot.
    candidates = np.stack([
        np.stack([m21 - m12, m02 - m20, m10 - m01, 1.0 + trace], axis=-1),
        np.stack([1.0 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12], axis=-1),
        np.stack([m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21, m02 - m20], axis=-1),
        np.stack([m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22, m10 - m01], axis=-1),
    ], axis=-2)
    pivots = np.stack([trace, m00, m11, m22], axis=-1)
    choice = np.argmax(pivots, axis=-1)
    quaternion = np.take_along_axis(candidates, choice[..., None, None], axis=-2)[..., 0, :]
    quaternion /= np.linalg.norm(quaternion, axis=-1, keepdims=True)
    return np.where(quaternion[..., 3:4] < 0.0, -quaternion, quaternion)


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` (x, y, z, w; normalised here) -> rotation matrices ``(..., 3, 3)``."""
    q = np.asarray(quaternion, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have shape (..., 4), got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0.0) or not np.all(np.isfinite(norm)):
        raise ValueError("quaternion must be finite and non-zero")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def slerp(q0: np.ndarray, q1: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """Spherical linear interpolation from ``q0`` (t = 0) to ``q1`` (t = 1), shortest arc.

    Inputs are normalised; the result is a unit quaternion (x, y, z, w). ``t`` may be an
    array broadcasting against the quaternions' leading axes.
    """
    a = np.asarray(q0, dtype=np.float64)
    b = np.asarray(q1, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0.0, -b, b)  # same rotation, shorter way round
    dot = np.abs(dot)
    angle = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_angle = np.sin(angle)
    near = sin_angle < 1e-9
    safe = np.where(near, 1.0, sin_angle)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * angle) / safe)
    w1 = np.where(near, t, np.sin(t * angle) / safe)
    result = w0 * a + w1 * b
    return result / np.linalg.norm(result, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- poses


def pose_from_translation_quaternion(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """(x, y, z) and (x, y, z, w) -> 4x4 pose."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(quaternion)
    pose[:3, 3] = translation
    return pose


def pose_to_translation_quaternion(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 pose -> ((3,) translation, (4,) quaternion x, y, z, w with w >= 0)."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be 4x4, got {pose.shape}")
    return pose[:3, 3].copy(), matrix_to_quaternion(pose[:3, :3])


def interpolate_pose(pose0: np.ndarray, pose1: np.ndarray, t: float) -> np.ndarray:
    """Pose at fraction ``t`` from ``pose0`` (0) to ``pose1`` (1): lerp translation, slerp rotation."""
    p0, q0 = pose_to_translation_quaternion(pose0)
    p1, q1 = pose_to_translation_quaternion(pose1)
    return pose_from_translation_quaternion((1.0 - t) * p0 + t * p1, slerp(q0, q1, t))

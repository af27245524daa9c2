"""Poses, quaternions and stamps for the ROS side: pure numpy, no rclpy at import time.

Conventions: quaternions are ``(x, y, z, w)`` as in geometry_msgs; a pose is a 4x4
homogeneous matrix ``parent <- child`` (e.g. ``map <- velo_link``); stamps are integer
nanoseconds since the epoch, or ``(sec, nanosec)`` as in builtin_interfaces/Time.

Message functions are duck-typed: they read any object with the ROS field names, and build
messages from a type resolver (``message_types``): rclpy's message classes by default, or
rosbags' typestore classes (``message_types(typestore)``), so one code path serves the node
and the bag writer.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000

TypeResolver = Callable[[str], type]


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


# ----------------------------------------------------------------------------- stamps


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (``sec``, ``nanosec``), a (sec, nanosec) pair, or int ns -> int ns."""
    if isinstance(stamp, (bool, float, np.floating)):
        raise TypeError(f"a stamp must be int nanoseconds, (sec, nanosec) or a Time, got {stamp!r}")
    if isinstance(stamp, (int, np.integer)):
        return int(stamp)
    if isinstance(stamp, tuple):
        sec, nanosec = stamp
        return int(sec) * NS_PER_S + int(nanosec)
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(nanoseconds: int) -> tuple[int, int]:
    """int ns -> (sec, nanosec) with 0 <= nanosec < 1e9 (sec may be negative)."""
    sec, nanosec = divmod(int(nanoseconds), NS_PER_S)
    return sec, nanosec


def seconds_to_ns(seconds: float) -> int:
    """Float seconds -> int ns, rounded to the nearest nanosecond."""
    return round(float(seconds) * NS_PER_S)


# ----------------------------------------------------------------------------- message types


def message_types(typestore: Any = None) -> TypeResolver:
    """A resolver ``"pkg/msg/Name" -> class``.

    Without ``typestore``: rclpy's generated classes (``importlib``; raises ImportError when a
    package is not installed). With a rosbags typestore: its dataclasses.
    """
    if typestore is not None:
        return lambda name: typestore.types[name]

    def resolve(name: str) -> type:
        package, kind, short = name.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), short)

    return resolve


def make_header(types: TypeResolver, stamp: Any, frame_id: str) -> Any:
    """std_msgs/Header with ``stamp`` (int ns, (sec, nanosec) or a Time) and ``frame_id``."""
    sec, nanosec = ns_to_stamp(stamp_to_ns(stamp))
    time = types("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)
    return types("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)


def _vector3(types: TypeResolver, name: str, values: np.ndarray) -> Any:
    x, y, z = (float(v) for v in values)
    return types(name)(x=x, y=y, z=z)


def _quaternion(types: TypeResolver, values: np.ndarray) -> Any:
    x, y, z, w = (float(v) for v in values)
    return types("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)


def _covariance(types: TypeResolver, values: np.ndarray | None) -> np.ndarray:
    return np.zeros(36, np.float64) if values is None else np.asarray(values, np.float64).reshape(36).copy()


def pose_to_odometry(pose: np.ndarray, stamp: Any, frame_id: str, child_frame_id: str,
                     types: TypeResolver | None = None, pose_covariance: np.ndarray | None = None,
                     linear_velocity: np.ndarray | None = None, angular_velocity: np.ndarray | None = None) -> Any:
    """nav_msgs/Odometry: the pose of ``child_frame_id`` in ``frame_id`` (4x4 ``frame <- child``).

    Velocities (in the child frame, m/s and rad/s) default to zero; covariances are zero
    unless ``pose_covariance`` (6x6, row-major) is given.
    """
    types = types or message_types()
    translation, quaternion = pose_to_translation_quaternion(pose)
    position = types("geometry_msgs/msg/Point")(x=float(translation[0]), y=float(translation[1]),
                                                 z=float(translation[2]))
    pose_msg = types("geometry_msgs/msg/Pose")(position=position, orientation=_quaternion(types, quaternion))
    vector = "geometry_msgs/msg/Vector3"
    twist = types("geometry_msgs/msg/Twist")(
        linear=_vector3(types, vector, np.zeros(3) if linear_velocity is None else linear_velocity),
        angular=_vector3(types, vector, np.zeros(3) if angular_velocity is None else angular_velocity))
    return types("nav_msgs/msg/Odometry")(
        header=make_header(types, stamp, frame_id),
        child_frame_id=child_frame_id,
        pose=types("geometry_msgs/msg/PoseWithCovariance")(pose=pose_msg,
                                                            covariance=_covariance(types, pose_covariance)),
        twist=types("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=_covariance(types, None)),
    )


def pose_to_transform_stamped(pose: np.ndarray, stamp: Any, frame_id: str, child_frame_id: str,
                              types: TypeResolver | None = None) -> Any:
    """geometry_msgs/TransformStamped ``frame_id <- child_frame_id`` from a 4x4 pose."""
    types = types or message_types()
    translation, quaternion = pose_to_translation_quaternion(pose)
    transform = types("geometry_msgs/msg/Transform")(
        translation=_vector3(types, "geometry_msgs/msg/Vector3", translation),
        rotation=_quaternion(types, quaternion))
    return types("geometry_msgs/msg/TransformStamped")(header=make_header(types, stamp, frame_id),
                                                      child_frame_id=child_frame_id, transform=transform)


def poses_to_path(poses: np.ndarray, stamps: Sequence[int], frame_id: str, stamp: Any,
                  types: TypeResolver | None = None) -> Any:
    """nav_msgs/Path in ``frame_id`` stamped ``stamp``: one PoseStamped per 4x4 pose of ``poses``
    at its stamp of ``stamps`` (ns), in ``frame_id`` too (a SLAM's optimised keyframes)."""
    types = types or message_types()
    stamped = []
    for pose, pose_stamp in zip(poses, stamps, strict=True):
        translation, quaternion = pose_to_translation_quaternion(pose)
        position = types("geometry_msgs/msg/Point")(x=float(translation[0]), y=float(translation[1]),
                                                     z=float(translation[2]))
        stamped.append(types("geometry_msgs/msg/PoseStamped")(
            header=make_header(types, int(pose_stamp), frame_id),
            pose=types("geometry_msgs/msg/Pose")(position=position, orientation=_quaternion(types, quaternion))))
    return types("nav_msgs/msg/Path")(header=make_header(types, stamp, frame_id), poses=stamped)


def transform_to_pose(msg: Any) -> np.ndarray:
    """geometry_msgs/TransformStamped (or Transform) -> 4x4 pose."""
    transform = getattr(msg, "transform", msg)
    t, r = transform.translation, transform.rotation
    return pose_from_translation_quaternion(np.array([t.x, t.y, t.z], np.float64),
                                            np.array([r.x, r.y, r.z, r.w], np.float64))

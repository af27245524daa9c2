"""Stamps and pose messages for the ROS side: pure numpy, no rclpy at import time.

Stamps are integer nanoseconds since the epoch, or ``(sec, nanosec)`` as in
builtin_interfaces/Time; poses and quaternions as ``convbki_core.geometry.poses`` holds them (4x4
``parent <- child``, quaternions ``(x, y, z, w)``).

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

from convbki_core.geometry.poses import pose_from_translation_quaternion, pose_to_translation_quaternion

NS_PER_S = 1_000_000_000

TypeResolver = Callable[[str], type]


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

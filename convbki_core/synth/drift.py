"""A drive's odometry with drift, and what a SLAM publishes when it closes the loop.

Wheel and IMU odometry integrate the car's motion with small, steady errors: a heading bias
(a gyro's, or unequal wheel radii: degrees per hundred metres driven) and a scale error (a
wheel radius off by a fraction). Each step between two scans is the true step with its
translation scaled by (1 + scale error) and a turn of the bias times the distance added, so
the odometry drifts further from the truth the longer the drive, and a drive round a closed
route comes back metres and degrees from where it started.

A pose-graph SLAM on top of it (LIO-SAM, RTAB-Map, GLIM) keeps keyframes and publishes ``map
-> odom``: until it recognises the start (the loop closure, at ``frame``) the robot's pose in
``map`` is the odometry's; then it optimises, publishes every keyframe's corrected pose (here
the true ones, every ``keyframe_every`` scans and the last scan before the closure), and from
then on publishes ``map -> odom`` = the correction at the closure, so that the scans after it
land where they belong. ``loop_closure.yaml`` beside ``odometry.txt`` says when and which
keyframes (``datasets.drift`` reads them).
"""

from __future__ import annotations

import math

import numpy as np


def drifted_odometry(truth: np.ndarray, heading_bias_deg_per_100m: float, scale_error: float) -> np.ndarray:
    """(F, 4, 4) odometry poses (map <- lidar) of a drive whose true poses are ``truth``: the
    first is the truth's, each step after it the true step with its translation scaled by
    ``1 + scale_error`` and a yaw of ``heading_bias_deg_per_100m`` per 100 m of it added."""
    poses = np.empty_like(truth)
    poses[0] = truth[0]
    bias = math.radians(heading_bias_deg_per_100m) / 100.0  # rad per metre
    for k in range(1, len(truth)):
        step = np.linalg.inv(truth[k - 1]) @ truth[k]
        distance = float(np.linalg.norm(step[:3, 3]))
        yaw = bias * distance
        turn = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        drifted = np.eye(4)
        drifted[:3, :3] = turn @ step[:3, :3]
        drifted[:3, 3] = step[:3, 3] * (1.0 + scale_error)
        poses[k] = poses[k - 1] @ drifted
    return poses


def first_lap_frame(truth: np.ndarray, lap_length: float) -> int | None:
    """The first frame at which the drive has covered a whole lap of ``lap_length`` m (None: never)."""
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1))])
    after = np.flatnonzero(travelled >= lap_length)
    return int(after[0]) if len(after) else None


def keyframes(closure: int, every: int) -> list[int]:
    """The keyframes a SLAM re-publishes at the closure: every ``every``-th scan before it, and
    the last scan before it."""
    frames = list(range(0, closure, every))
    if frames[-1] != closure - 1:
        frames.append(closure - 1)
    return frames


def record(closure: int, every: int, heading_bias: float, scale_error: float) -> dict:
    """The contents of ``loop_closure.yaml``."""
    return {"closure_frame": int(closure), "keyframe_every": int(every), "keyframes": keyframes(closure, every),
            "heading_bias_deg_per_100m": float(heading_bias), "scale_error": float(scale_error),
            "odometry": "odometry.txt", "corrected_keyframes": "the keyframes' rows of poses.txt (the truth)"}

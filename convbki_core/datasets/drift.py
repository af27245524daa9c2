"""A drive whose odometry drifts and whose SLAM closes the loop (written by ``synth --drift``).

Beside a SemanticKITTI-layout sequence (``poses.txt`` the true poses):

* ``odometry.txt``: the odometry's poses, in ``poses.txt``'s convention (camera frame, 3 x 4
  rows, read with the sequence's calibration);
* ``loop_closure.yaml``: ``closure_frame`` (the SLAM closes the loop just before integrating
  this scan), ``keyframes`` (the frames whose corrected poses it then publishes: their rows of
  ``poses.txt``).

What the robot maps with (``robot_poses``): the odometry's pose until the closure, then the
odometry's pose after the correction the SLAM found at the closure (``map -> odom`` jumps
once). ``corrected_poses``: what a correction of the map makes of the scans before the closure
(the keyframes' corrections interpolated between them, ``correction.keyframe_corrections``),
and the robot's poses after it: the poses a map built from scratch after the correction uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from convbki_core.datasets import DatasetError
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_poses


@dataclass
class LoopClosure:
    closure_frame: int
    keyframes: np.ndarray  # (K,) frames, ascending, all before the closure
    odometry: np.ndarray  # (F, 4, 4) map <- lidar as the odometry says
    truth: np.ndarray  # (F, 4, 4) map <- lidar, poses.txt
    stamps_ns: np.ndarray  # (F,) int64

    def correction_at(self, frame: int) -> np.ndarray:
        """``map -> odom`` as the SLAM publishes it at ``frame``: the identity until the loop
        closes, then the correction that puts the closure's scan at its true pose."""
        if frame < self.closure_frame:
            return np.eye(4)
        return self.truth[self.closure_frame] @ np.linalg.inv(self.odometry[self.closure_frame])

    def robot_poses(self) -> np.ndarray:
        """(F, 4, 4): the odometry's poses, and after the closure those times the correction
        ``map -> odom`` the SLAM publishes from then on."""
        return np.stack([self.correction_at(k) @ self.odometry[k] for k in range(len(self.odometry))])

    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4): the keyframes' corrected poses, as the SLAM publishes them at the closure."""
        return self.truth[self.keyframes]

    def corrected_poses(self) -> np.ndarray:
        """(F, 4, 4): every scan where a correction at the closure puts it (the scans before the
        closure moved by the keyframes' corrections; those after as the robot mapped them)."""
        from convbki_core.correction.replay import keyframe_corrections
        from convbki_core.correction.scan_log import LoggedScan

        robot = self.robot_poses()
        empty = np.zeros((0, 3), np.float32)
        before = [(k, LoggedScan.of(empty, np.zeros(0, np.int64), robot[k], int(self.stamps_ns[k])))
                  for k in range(self.closure_frame)]
        moved = keyframe_corrections(before, self.stamps_ns[self.keyframes], self.keyframe_poses())
        poses = robot.copy()
        for index, pose in moved.items():
            poses[index] = pose
        return poses


def read_loop_closure(dataset: SemanticKittiSequence) -> LoopClosure | None:
    """The sequence's loop closure (``loop_closure.yaml`` and ``odometry.txt``), or None where it
    has none. Raises ``DatasetError`` naming the file and the problem."""
    path = dataset.folder / "loop_closure.yaml"
    if not path.exists():
        return None
    try:
        record = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise DatasetError(f"{path}: cannot read ({str(error).splitlines()[0]})") from None
    if not isinstance(record, dict):
        raise DatasetError(f"{path}: not a mapping")
    frames = len(dataset)
    closure = record.get("closure_frame")
    keyframes = record.get("keyframes")
    if isinstance(closure, bool) or not isinstance(closure, int) or not 1 <= closure < frames:
        raise DatasetError(f"{path}: closure_frame must be a frame 1..{frames - 1}, got {closure!r}")
    if not isinstance(keyframes, list) or not keyframes or any(
            isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < closure for k in keyframes) \
            or sorted(set(keyframes)) != keyframes:
        raise DatasetError(f"{path}: keyframes must be ascending frames before the closure {closure}")
    odometry_path = dataset.folder / str(record.get("odometry", "odometry.txt"))
    odometry = read_poses(Path(odometry_path), dataset.calibration)
    if len(odometry) != frames:
        raise DatasetError(f"{odometry_path}: {len(odometry)} poses for {frames} scans")
    stamps = np.round(np.asarray(dataset.times, np.float64) * 1e9).astype(np.int64)
    return LoopClosure(closure, np.asarray(keyframes, np.int64), odometry, dataset.poses.copy(), stamps)

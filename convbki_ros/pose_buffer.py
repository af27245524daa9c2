"""Odometry history and the pose of a cloud at its own stamp.

A LiDAR cloud and the odometry of its frame rarely share a stamp. The mapper keeps the
recent odometry and interpolates between the two poses around the cloud's stamp
(translation linearly, rotation by slerp). A cloud newer than the latest odometry waits
for more; a cloud older than everything kept cannot be placed and is dropped.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from enum import Enum

import numpy as np

from convbki_ros.transforms import interpolate_pose


class PoseStatus(Enum):
    FOUND = "found"
    WAIT = "wait"  # the stamp is newer than the latest odometry: more may come
    TOO_OLD = "too_old"  # the stamp is older than the oldest odometry kept
    EMPTY = "empty"  # no odometry yet


@dataclass
class PoseLookup:
    status: PoseStatus
    pose: np.ndarray | None = None
    child_frame_id: str = ""


class OdometryBuffer:
    """Poses (map <- child frame) by stamp, covering the last ``history_ns`` nanoseconds.

    ``tolerance_ns``: a cloud up to this much newer than the latest odometry uses the latest
    pose rather than waiting (sensor and odometry clocks are rarely within a nanosecond).
    """

    def __init__(self, history_ns: int = 30_000_000_000, tolerance_ns: int = 1_000_000):
        self.history_ns = int(history_ns)
        self.tolerance_ns = int(tolerance_ns)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._frames: list[str] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def latest_stamp(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()
        self._frames.clear()

    def add(self, stamp_ns: int, pose: np.ndarray, child_frame_id: str = "") -> None:
        """Insert one odometry pose; out-of-order stamps are placed in order, duplicates replace."""
        position = bisect.bisect_left(self._stamps, stamp_ns)
        if position < len(self._stamps) and self._stamps[position] == stamp_ns:
            self._poses[position] = pose
            self._frames[position] = child_frame_id
        else:
            self._stamps.insert(position, stamp_ns)
            self._poses.insert(position, pose)
            self._frames.insert(position, child_frame_id)
        horizon = self._stamps[-1] - self.history_ns
        cut = bisect.bisect_left(self._stamps, horizon)
        if cut:
            del self._stamps[:cut], self._poses[:cut], self._frames[:cut]

    def lookup(self, stamp_ns: int) -> PoseLookup:
        """The pose at ``stamp_ns``: interpolated between its neighbours, or why there is none."""
        if not self._stamps:
            return PoseLookup(PoseStatus.EMPTY)
        if stamp_ns < self._stamps[0]:
            return PoseLookup(PoseStatus.TOO_OLD)
        last = len(self._stamps) - 1
        if stamp_ns > self._stamps[last]:
            if stamp_ns - self._stamps[last] <= self.tolerance_ns:
                return PoseLookup(PoseStatus.FOUND, self._poses[last], self._frames[last])
            return PoseLookup(PoseStatus.WAIT)
        position = bisect.bisect_left(self._stamps, stamp_ns)
        if self._stamps[position] == stamp_ns:
            return PoseLookup(PoseStatus.FOUND, self._poses[position], self._frames[position])
        before, after = self._stamps[position - 1], self._stamps[position]
        fraction = (stamp_ns - before) / (after - before)
        pose = interpolate_pose(self._poses[position - 1], self._poses[position], fraction)
        return PoseLookup(PoseStatus.FOUND, pose, self._frames[position])

"""Odometry history and the pose of a cloud at its own stamp.

A LiDAR cloud and the odometry of its frame rarely share a stamp. The mapper keeps the
recent odometry and interpolates between the two poses around the cloud's stamp
(translation linearly, rotation by slerp). A cloud newer than the latest odometry waits
for more; a cloud older than everything kept cannot be placed and is dropped.

Odometry is checked before it is kept (``pose_problem``): a non-finite position or a
quaternion that is not a rotation would place a whole scan in the wrong spot. Two
consecutive poses further apart than ``max_jump`` metres are a jump (a relocalisation, a
reset odometry): the buffer keeps both, but never interpolates across the gap, since a
pose half way through a jump is a pose the sensor never had.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from enum import Enum

import numpy as np

from convbki_ros.transforms import interpolate_pose

# How far |q| may be from 1. Odometry sources normalise in float32 or float64 (errors near
# 1e-7) and bag conversions keep that; a norm off by a per cent is a broken message (a
# zero or default quaternion, swapped fields), not round-off.
QUATERNION_NORM_TOLERANCE = 1e-2


class PoseStatus(Enum):
    FOUND = "found"
    WAIT = "wait"  # the stamp is newer than the latest odometry: more may come
    TOO_OLD = "too_old"  # the stamp is older than the oldest odometry kept
    EMPTY = "empty"  # no odometry yet
    JUMP = "jump"  # the stamp falls between two poses that are a jump apart


@dataclass
class PoseLookup:
    status: PoseStatus
    pose: np.ndarray | None = None
    child_frame_id: str = ""


def _numbers(values: np.ndarray) -> str:
    return ", ".join(f"{v:.6g}" for v in values)


def pose_problem(position: np.ndarray, orientation: np.ndarray,
                 tolerance: float = QUATERNION_NORM_TOLERANCE) -> str | None:
    """What is wrong with an odometry pose, in words, or None when it is usable.

    ``position`` (x, y, z) in metres, ``orientation`` a quaternion (x, y, z, w) that must
    be finite with a norm within ``tolerance`` of 1.
    """
    position = np.asarray(position, dtype=np.float64)
    orientation = np.asarray(orientation, dtype=np.float64)
    if not np.isfinite(position).all():
        return f"position ({_numbers(position)}) is not finite"
    if not np.isfinite(orientation).all():
        return f"orientation quaternion ({_numbers(orientation)}) is not finite"
    norm = float(np.linalg.norm(orientation))
    if abs(norm - 1.0) > tolerance:
        return f"orientation quaternion ({_numbers(orientation)}) has norm {norm:.6g}, not 1"
    return None


class OdometryBuffer:
    """Poses (map <- child frame) by stamp, covering the last ``history_ns`` nanoseconds.

    ``tolerance_ns``: a cloud up to this much newer than the latest odometry uses the latest
    pose rather than waiting (sensor and odometry clocks are rarely within a nanosecond).
    ``max_jump``: metres between two consecutive poses beyond which they are a jump and
    stamps between them get ``PoseStatus.JUMP``; 0 = never.
    """

    def __init__(self, history_ns: int = 30_000_000_000, tolerance_ns: int = 1_000_000, max_jump: float = 0.0):
        self.history_ns = int(history_ns)
        self.tolerance_ns = int(tolerance_ns)
        self.max_jump = float(max_jump)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._frames: list[str] = []
        self._jump_before: list[bool] = []  # True: entry i is a jump away from entry i - 1

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def latest_stamp(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()
        self._frames.clear()
        self._jump_before.clear()

    def _distance(self, first: int, second: int) -> float:
        return float(np.linalg.norm(self._poses[second][:3, 3] - self._poses[first][:3, 3]))

    def _is_jump(self, position: int) -> bool:
        return position > 0 and self.max_jump > 0 and self._distance(position - 1, position) > self.max_jump

    def add(self, stamp_ns: int, pose: np.ndarray, child_frame_id: str = "") -> float | None:
        """Insert one odometry pose; out-of-order stamps are placed in order, duplicates replace.

        Returns the distance (m) from the pose before it when that is a jump (see
        ``max_jump``), else None.
        """
        position = bisect.bisect_left(self._stamps, stamp_ns)
        if position < len(self._stamps) and self._stamps[position] == stamp_ns:
            self._poses[position] = pose
            self._frames[position] = child_frame_id
        else:
            self._stamps.insert(position, stamp_ns)
            self._poses.insert(position, pose)
            self._frames.insert(position, child_frame_id)
            self._jump_before.insert(position, False)
        # The new pose changes the gaps on both of its sides.
        for gap in (position, position + 1):
            if gap < len(self._stamps):
                self._jump_before[gap] = self._is_jump(gap)
        jump = self._distance(position - 1, position) if self._jump_before[position] else None
        self.drop_before(self._stamps[-1] - self.history_ns)
        return jump

    def drop_before(self, stamp_ns: int) -> None:
        """Forget the poses stamped before ``stamp_ns``."""
        cut = bisect.bisect_left(self._stamps, stamp_ns)
        if cut:
            del self._stamps[:cut], self._poses[:cut], self._frames[:cut], self._jump_before[:cut]
            if self._jump_before:
                self._jump_before[0] = False  # nothing before it any more

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
        if self._jump_before[position]:
            return PoseLookup(PoseStatus.JUMP)
        before, after = self._stamps[position - 1], self._stamps[position]
        fraction = (stamp_ns - before) / (after - before)
        pose = interpolate_pose(self._poses[position - 1], self._poses[position], fraction)
        return PoseLookup(PoseStatus.FOUND, pose, self._frames[position])

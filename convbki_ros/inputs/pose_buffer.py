"""Odometry history and the pose of a cloud at its own stamp.

A LiDAR cloud and the odometry of its frame rarely share a stamp. The mapper keeps the
recent odometry and interpolates between the two poses around the cloud's stamp
(translation linearly, rotation by slerp). A cloud newer than the latest odometry waits
for more; a cloud older than everything kept cannot be placed and is dropped.

Odometry is checked before it is kept (``pose_problem``): a non-finite position or a
quaternion that is not a rotation would place a whole scan in the wrong spot. Two
consecutive poses further apart than ``max_jump`` metres are a break: the buffer keeps both,
but never interpolates across it, since a pose half way through is a pose the sensor never
had. A break is one of two things, and the user must be told which:

* an outage: the two poses are far apart in time as well (no odometry came for a while, the
  robot moved on meanwhile); the stamps between them are ``PoseStatus.OUTAGE``;
* a jump: consecutive odometry that moved further than the robot can (a relocalisation, an
  odometry that restarted at its origin); ``PoseStatus.JUMP``.

The gap that makes an outage is measured against the odometry's own rate: more than
``OUTAGE_PERIODS`` of its usual periods, and at least ``OUTAGE_MIN_S``.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from enum import Enum

import numpy as np

from convbki_core.geometry.poses import interpolate_pose

# How far |q| may be from 1. Odometry sources normalise in float32 or float64 (errors near
# 1e-7) and bag conversions keep that; a norm off by a per cent is a broken message (a
# zero or default quaternion, swapped fields), not round-off.
QUATERNION_NORM_TOLERANCE = 1e-2
# A gap in the stamps longer than this many of the odometry's usual periods (the median of the
# recent ones), and than OUTAGE_MIN_S, is an outage rather than a step: a 10 Hz odometry that
# skips a message or two is still continuous, one silent for a second is not.
OUTAGE_PERIODS = 10
OUTAGE_MIN_S = 1.0
RATE_HISTORY = 50  # recent stamp gaps the usual period is taken from
# Poses kept at most, beside the time they cover: a source sending odometry stamped a nanosecond
# apart (anyone on the domain can) must not grow the history without bound. 1 kHz over the
# history's 30 s fits.
MAX_POSES = 50_000


class PoseStatus(Enum):
    FOUND = "found"
    WAIT = "wait"  # the stamp is newer than the latest odometry: more may come
    TOO_OLD = "too_old"  # the stamp is older than the oldest odometry kept
    EMPTY = "empty"  # no odometry yet
    JUMP = "jump"  # the stamp falls between two poses that are a jump apart
    OUTAGE = "outage"  # the stamp falls in an outage of the odometry that ended far away


@dataclass
class PoseBreak:
    """Two consecutive poses too far apart to interpolate between (see the module's docstring)."""

    distance: float  # metres between them
    gap_s: float  # seconds between their stamps
    outage: bool  # the gap is an outage of the odometry, not a step of continuous odometry


@dataclass
class PoseLookup:
    status: PoseStatus
    pose: np.ndarray | None = None
    child_frame_id: str = ""
    reason: str = ""  # why not found, where the status alone does not say it (TF as the pose source)


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
    """Poses (map <- child frame) by stamp, covering the last ``history_ns`` nanoseconds (at most
    ``MAX_POSES`` of them, the newest).

    ``tolerance_ns``: a cloud up to this much newer than the latest odometry uses the latest
    pose rather than waiting (sensor and odometry clocks are rarely within a nanosecond).
    ``max_jump``: metres between two consecutive poses beyond which they are a jump and
    stamps between them get ``PoseStatus.JUMP`` or ``PoseStatus.OUTAGE``; 0 = never.
    """

    def __init__(self, history_ns: int = 30_000_000_000, tolerance_ns: int = 1_000_000, max_jump: float = 0.0):
        self.history_ns = int(history_ns)
        self.tolerance_ns = int(tolerance_ns)
        self.max_jump = float(max_jump)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._frames: list[str] = []
        self._jump_before: list[bool] = []  # True: entry i is a break away from entry i - 1

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

    def usual_period_ns(self) -> int | None:
        """The median gap between the recent stamps, None with fewer than three poses."""
        stamps = self._stamps[-RATE_HISTORY - 1:]
        if len(stamps) < 3:
            return None
        return int(np.median(np.diff(stamps)))

    def outage_gap_ns(self) -> int:
        """A stamp gap longer than this is an outage (see the module's docstring)."""
        period = self.usual_period_ns() or 0
        return max(int(OUTAGE_MIN_S * 1e9), OUTAGE_PERIODS * period)

    def _is_outage(self, position: int) -> bool:
        return self._stamps[position] - self._stamps[position - 1] > self.outage_gap_ns()

    def add(self, stamp_ns: int, pose: np.ndarray, child_frame_id: str = "") -> PoseBreak | None:
        """Insert one odometry pose; out-of-order stamps are placed in order, duplicates replace.

        Returns the break between it and the pose before it when they are further apart than
        ``max_jump`` (an outage or a jump), else None.
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
        found = None
        if self._jump_before[position]:
            gap = self._stamps[position] - self._stamps[position - 1]
            found = PoseBreak(self._distance(position - 1, position), gap / 1e9, self._is_outage(position))
        self.drop_before(self._stamps[-1] - self.history_ns)
        if len(self._stamps) > MAX_POSES:
            self.drop_before(self._stamps[len(self._stamps) - MAX_POSES])
        return found

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
            return PoseLookup(PoseStatus.OUTAGE if self._is_outage(position) else PoseStatus.JUMP)
        before, after = self._stamps[position - 1], self._stamps[position]
        fraction = (stamp_ns - before) / (after - before)
        pose = interpolate_pose(self._poses[position - 1], self._poses[position], fraction)
        return PoseLookup(PoseStatus.FOUND, pose, self._frames[position])

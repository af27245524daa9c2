"""Moving integrated scans where a SLAM now says they were, exactly.

A pose-graph SLAM that closes a loop moves the poses of scans the map integrated long ago.
ConvBKI's update is a sum (Eq. 4), so the class evidence of a scan could be taken out and
put back at its new pose; but free space, clamping and the movers' rules read the map's state
at each scan (a voxel takes free evidence only once it holds some, clamping scales it the
first time rays contradict it, a reset forgets), and taking a scan out is not the inverse of
putting it in: measured on a drift drive, the class evidence moved alone left 16 % of the
occupied voxels read otherwise than in the map built from scratch with the corrected poses.

So a correction maps the scans again. The scan log (``scan_log``) keeps every integrated scan
bit for bit, and the map as it was when each segment of the log began. A correction starts a
new mapper from the base of the segment that holds the first moved scan and integrates every
logged scan from there on, in the order they came, each at its corrected pose (the others at
the poses they were integrated with): what mapping from scratch with the corrected poses
gives, bit for bit, for every rule. The map it replaces is untouched while this runs (the
node maps live scans into it meanwhile, and the new mapper catches up with them before it
takes the old one's place: ``continue_correction``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from convbki_core.correction.scan_log import LoggedScan, ScanLog
from convbki_core.geometry.poses import interpolate_pose


@dataclass
class CorrectionResult:
    """What one correction did."""

    scans: int = 0  # scans moved
    largest_move: float = 0.0  # m: the largest displacement of a moved scan's sensor
    seconds: float = 0.0  # mapping the logged scans again
    replayed: int = 0  # scans mapped again (the moved ones and those after them, or in their segment)
    skipped: int = 0  # scans whose poses changed less than the tolerance


def continue_correction(mapper, log: ScanLog, moves: dict[int, np.ndarray], since: int,
                        until: int | None = None) -> int:
    """Integrate into ``mapper`` the scans of ``log`` from index ``since`` on (up to ``until``,
    exclusive), each at its pose in ``moves`` or else the one it was integrated with; returns how
    many. A correction calls it once from its base, and again for the scans logged meanwhile."""
    count = 0
    for index, scan in log.scans(since):
        if until is not None and index >= until:
            break
        if index != since + count:  # never a map with a scan missing: the caller holds the log
            raise ValueError(f"scan {since + count} is no longer logged: the correction cannot go on")
        pose = moves.get(index, scan.pose)
        mapper.integrate(scan.points(), scan.values(), pose, stamp_ns=scan.stamp_ns, mount=scan.mount,
                         logged=scan.at(pose) if index in moves else scan)
        count += 1
    return count


def pose_displacement(old: np.ndarray, new: np.ndarray, reach: float) -> float:
    """How far a point ``reach`` metres from the sensor moves from ``old`` to ``new`` (m), at most:
    the translation plus the rotation's arc at that range."""
    change = new @ np.linalg.inv(old)
    cosine = (np.trace(change[:3, :3]) - 1.0) / 2.0
    angle = math.acos(min(1.0, max(-1.0, cosine)))
    return float(np.linalg.norm(new[:3, 3] - old[:3, 3]) + angle * reach)


# -- corrected poses from a SLAM's keyframes ---------------------------------------------------
def _pose_at(stamps: np.ndarray, poses: np.ndarray, stamp: int) -> np.ndarray | None:
    """The pose at ``stamp`` interpolated between the two of ``poses`` (by ``stamps``, ascending)
    around it; None outside them."""
    if not len(stamps) or stamp < stamps[0] or stamp > stamps[-1]:
        return None
    after = int(np.searchsorted(stamps, stamp, side="left"))
    if stamps[after] == stamp:
        return poses[after]
    before = after - 1
    fraction = (stamp - stamps[before]) / (stamps[after] - stamps[before])
    return interpolate_pose(poses[before], poses[after], float(fraction))


@dataclass
class KeyframeCorrection:
    """A SLAM's correction as changes of the map at its keyframes' stamps: ``changes`` (K, 4, 4)
    is each keyframe's new pose times the inverse of its pose as the map had it (``stamps_ns``
    (K,) ascending)."""

    stamps_ns: np.ndarray
    changes: np.ndarray
    first_stamp_ns: int  # the Path's first keyframe: scans logged from here on are its to move

    def poses_for(self, scans: list[tuple[int, LoggedScan]]) -> dict[int, np.ndarray]:
        """The corrected sensor poses of ``scans`` ((index, scan)) stamped within the keyframes'
        span: the change interpolated between the two keyframes around the scan's stamp, applied
        on the left to the pose it was integrated with. A scan before the first keyframe the log
        reaches but after the Path's first (whose own scans fell out of the log) takes that
        keyframe's change. Returns the new poses by scan index."""
        moved = {}
        for index, scan in scans:
            change = _pose_at(self.stamps_ns, self.changes, scan.stamp_ns)
            if change is None and self.first_stamp_ns <= scan.stamp_ns < self.stamps_ns[0]:
                change = self.changes[0]
            if change is not None:
                moved[index] = change @ scan.pose
        return moved


def keyframe_correction(scans: list[tuple[int, LoggedScan]], keyframe_stamps: np.ndarray,
                        keyframe_poses: np.ndarray) -> KeyframeCorrection | None:
    """The correction a SLAM's keyframes make of the logged ``scans`` ((the drive's scan index,
    scan), oldest first, as ``ScanLog.scans`` gives them): keyframe stamps (ns, ascending) and
    their new poses (K, 4, 4) of the body (map <- body, the body whose pose the scans' mounts
    give the sensor's on). Each keyframe's pose as the map had it is the logged bodies' poses
    interpolated at its stamp; keyframes outside the log's span are not used. None when no
    keyframe lies within the log's span."""
    if not scans:
        return None
    stamps = np.array([scan.stamp_ns for _, scan in scans], np.int64)
    bodies = np.stack([scan.pose @ np.linalg.inv(scan.mount) for _, scan in scans])
    order = np.argsort(stamps, kind="stable")
    stamps_sorted, bodies_sorted = stamps[order], bodies[order]
    corrections = []
    for stamp, pose in zip(keyframe_stamps, keyframe_poses):
        before = _pose_at(stamps_sorted, bodies_sorted, int(stamp))
        if before is not None:
            corrections.append((int(stamp), np.asarray(pose, np.float64) @ np.linalg.inv(before)))
    if not corrections:
        return None
    return KeyframeCorrection(np.array([stamp for stamp, _ in corrections], np.int64),
                              np.stack([change for _, change in corrections]), int(np.min(keyframe_stamps)))


def keyframe_corrections(scans: list[tuple[int, LoggedScan]], keyframe_stamps: np.ndarray,
                         keyframe_poses: np.ndarray) -> dict[int, np.ndarray]:
    """The corrected sensor poses of the logged ``scans`` (``keyframe_correction``): a scan
    between two keyframes takes the change interpolated between theirs by time, applied on the
    left to the pose it was integrated with; scans outside the keyframes' span are not moved
    (they came after the optimisation, with the SLAM's newer frame). Returns the new poses by
    the drive's scan index."""
    correction = keyframe_correction(scans, keyframe_stamps, keyframe_poses)
    return {} if correction is None else correction.poses_for(scans)

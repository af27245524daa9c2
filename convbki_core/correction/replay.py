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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from convbki_core.correction.scan_log import LogTable, ScanLog
from convbki_core.geometry.poses import matrix_to_quaternion, quaternion_to_matrix, slerp


@dataclass
class CorrectionResult:
    """What one correction did."""

    scans: int = 0  # scans moved
    largest_move: float = 0.0  # m: the largest displacement of a moved scan's sensor
    seconds: float = 0.0  # mapping the logged scans again
    replayed: int = 0  # scans mapped again (the moved ones and those after them, or in their segment)
    skipped: int = 0  # scans whose poses changed less than the tolerance


def continue_correction(mapper, log: ScanLog, moves: dict[int, np.ndarray], since: int,
                        until: int | None = None, between: Callable[[int], bool] | None = None) -> int:
    """Integrate into ``mapper`` the scans of ``log`` from index ``since`` on (up to ``until``,
    exclusive), each at its pose in ``moves`` or else the one it was integrated with; returns how
    many. A correction calls it once from its base, and again for the scans logged meanwhile.
    ``between``: asked before each scan with its index; False stops there (a newer Path, a
    shutdown), and the mapper is the map up to the scans integrated so far."""
    count = 0
    for index, scan in log.scans(since):
        if until is not None and index >= until:
            break
        if index != since + count:  # never a map with a scan missing: the caller holds the log
            raise ValueError(f"scan {since + count} is no longer logged: the correction cannot go on")
        if between is not None and not between(index):
            break
        pose = moves.get(index, scan.pose)
        points, values = scan.decoded()  # one read where the log's folder holds the scan
        mapper.integrate(points, values, pose, stamp_ns=scan.stamp_ns, mount=scan.mount,
                         logged=scan.at(pose) if index in moves else scan)
        count += 1
    return count


def pose_displacements(old: np.ndarray, new: np.ndarray, reach: float) -> np.ndarray:
    """How far a point ``reach`` metres from the sensor moves from each of ``old`` to the same
    of ``new`` ((n, 4, 4) each), at most: the translation plus the rotation's arc at that
    range; (n,) metres."""
    if not len(old):
        return np.zeros(0)
    # The rotation between them: new R times old R transposed (rotations: the inverse is the transpose).
    turn = np.einsum("nij,nkj->nik", new[:, :3, :3], old[:, :3, :3])
    cosine = (np.trace(turn, axis1=1, axis2=2) - 1.0) / 2.0
    angle = np.arccos(np.clip(cosine, -1.0, 1.0))
    return np.linalg.norm(new[:, :3, 3] - old[:, :3, 3], axis=1) + angle * reach


# -- corrected poses from a SLAM's keyframes ---------------------------------------------------
def poses_at(stamps: np.ndarray, poses: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses at the stamps ``at`` (M,), each interpolated between the two of ``poses`` (by
    ``stamps``, ascending) around it (``interpolate_pose``: translation lerped, rotation
    slerped). Returns ((M, 4, 4) poses, (M,) whether each stamp lies within ``stamps``; the
    poses of those outside are zero)."""
    at = np.asarray(at, np.int64)
    result = np.zeros((len(at), 4, 4))
    if not len(stamps):
        return result, np.zeros(len(at), bool)
    inside = (at >= stamps[0]) & (at <= stamps[-1])
    wanted = at[inside]
    after = np.searchsorted(stamps, wanted, side="left")
    exact = stamps[after] == wanted
    before = np.maximum(after - 1, 0)
    span = np.where(exact, 1, stamps[after] - stamps[before])
    fraction = np.where(exact, 0.0, (wanted - stamps[before]) / span)
    start, end = poses[before], poses[after]
    rotation = quaternion_to_matrix(slerp(matrix_to_quaternion(start[:, :3, :3]), matrix_to_quaternion(end[:, :3, :3]),
                                          fraction))
    between = np.zeros((len(wanted), 4, 4))
    between[:, :3, :3] = rotation
    between[:, :3, 3] = (1.0 - fraction)[:, None] * start[:, :3, 3] + fraction[:, None] * end[:, :3, 3]
    between[:, 3, 3] = 1.0
    between[exact] = end[exact]
    result[inside] = between
    return result, inside


def _rigid_inverse(poses: np.ndarray) -> np.ndarray:
    """The inverses of rigid transforms (n, 4, 4): the rotation transposed, the translation turned back."""
    inverse = np.zeros_like(poses)
    inverse[:, :3, :3] = np.swapaxes(poses[:, :3, :3], 1, 2)
    inverse[:, :3, 3] = -np.einsum("nij,nj->ni", inverse[:, :3, :3], poses[:, :3, 3])
    inverse[:, 3, 3] = 1.0
    return inverse


@dataclass
class KeyframeCorrection:
    """A SLAM's correction as changes of the map at its keyframes' stamps: ``changes`` (K, 4, 4)
    is each keyframe's new pose times the inverse of its pose as the map had it (``stamps_ns``
    (K,) ascending)."""

    stamps_ns: np.ndarray
    changes: np.ndarray
    first_stamp_ns: int  # the Path's first keyframe: scans logged from here on are its to move

    def poses_for(self, scans) -> dict[int, np.ndarray]:
        """The corrected sensor poses of ``scans`` ((index, scan) pairs or a ``LogTable``) stamped
        within the keyframes' span: the change interpolated between the two keyframes around the
        scan's stamp, applied on the left to the pose it was integrated with. A scan before the
        first keyframe the log reaches but after the Path's first (whose own scans fell out of
        the log) takes that keyframe's change. Returns the new poses by scan index."""
        table = scans if isinstance(scans, LogTable) else LogTable.of(scans)
        poses, reached = self.pose_array(table)
        return {int(index): pose for index, pose in zip(table.indices[reached], poses[reached])}

    def pose_array(self, table: LogTable) -> tuple[np.ndarray, np.ndarray]:
        """``poses_for`` as arrays: ((n, 4, 4) the corrected poses, (n,) whether each scan is
        reached; the others keep the pose they were integrated with)."""
        changes, reached = poses_at(self.stamps_ns, self.changes, table.stamps_ns)
        early = ~reached & (table.stamps_ns >= self.first_stamp_ns) & (table.stamps_ns < self.stamps_ns[0])
        changes[early] = self.changes[0]
        reached = reached | early
        poses = table.poses.copy()
        poses[reached] = changes[reached] @ table.poses[reached]
        return poses, reached


def correction_moves(correction: KeyframeCorrection, table: LogTable, reach: float) -> np.ndarray:
    """How far ``correction`` moves each scan of ``table`` it reaches from its logged pose
    (``pose_displacements`` at ``reach`` m; 0 for those it does not reach), worked out on the
    changes' translations and quaternions without building a pose: what tells a Path that moves
    nothing in a few milliseconds on a log of thousands of scans. The rotation between two
    keyframes' changes is interpolated linearly and normalised, not slerped as the correction
    does: for the small turns between neighbouring keyframes that moves a point tens of metres
    away by a fraction of a millimetre."""
    stamps, keys = table.stamps_ns, correction.stamps_ns
    translations = correction.changes[:, :3, 3]
    quaternions = matrix_to_quaternion(correction.changes[:, :3, :3])
    after = np.clip(np.searchsorted(keys, stamps, side="left"), 1, max(len(keys) - 1, 1))
    before = after - 1 if len(keys) > 1 else np.zeros_like(after)
    after = np.minimum(after, len(keys) - 1)
    span = np.maximum(keys[after] - keys[before], 1)
    fraction = np.clip((stamps - keys[before]) / span, 0.0, 1.0)[:, None]
    start, end = quaternions[before], quaternions[after]
    end = np.where((start * end).sum(axis=1, keepdims=True) < 0.0, -end, end)
    quaternion = (1.0 - fraction) * start + fraction * end
    quaternion /= np.sqrt((quaternion * quaternion).sum(axis=1, keepdims=True))
    translation = (1.0 - fraction) * translations[before] + fraction * translations[after]
    # The scan's sensor turned about the map's origin and shifted: (R - I) p + t, R from the quaternion.
    position = table.poses[:, :3, 3]
    x, y, z, w = quaternion.T
    px, py, pz = position.T
    cx, cy, cz = 2.0 * (y * pz - z * py), 2.0 * (z * px - x * pz), 2.0 * (x * py - y * px)  # 2 u x p
    shift = np.stack([w * cx + (y * cz - z * cy), w * cy + (z * cx - x * cz), w * cz + (x * cy - y * cx)], axis=1)
    angle = 2.0 * np.arccos(np.minimum(np.abs(w), 1.0))
    moves = np.sqrt(((shift + translation) ** 2).sum(axis=1)) + angle * reach
    reached = (stamps >= correction.first_stamp_ns) & (stamps <= keys[-1])  # (those before keys[0]: its first change)
    return np.where(reached, moves, 0.0)


def keyframe_correction(scans, keyframe_stamps: np.ndarray, keyframe_poses: np.ndarray) -> KeyframeCorrection | None:
    """The correction a SLAM's keyframes make of the logged ``scans`` ((the drive's scan index,
    scan) pairs, oldest first, as ``ScanLog.scans`` gives them, or their ``LogTable``): keyframe
    stamps (ns, ascending) and their new poses (K, 4, 4) of the body (map <- body, the body whose
    pose the scans' mounts give the sensor's on). Each keyframe's pose as the map had it is the
    logged bodies' poses interpolated at its stamp; keyframes outside the log's span are not
    used. None when no keyframe lies within the log's span."""
    table = scans if isinstance(scans, LogTable) else LogTable.of(scans)
    if not len(table):
        return None
    keyframe_stamps = np.asarray(keyframe_stamps, np.int64)
    ascending = bool((np.diff(table.stamps_ns) >= 0).all())  # as logged, nearly always
    order = None if ascending else np.argsort(table.stamps_ns, kind="stable")
    stamps = table.stamps_ns if ascending else table.stamps_ns[order]
    # Only the logged bodies around a keyframe are read: those poses alone are worked out, and
    # interpolated between as the whole log would be (each keyframe's two neighbours stay neighbours).
    within = keyframe_stamps[(keyframe_stamps >= stamps[0]) & (keyframe_stamps <= stamps[-1])]
    if not len(within):
        return None
    after = np.searchsorted(stamps, within, side="left")
    needed = np.unique(np.concatenate([after, np.maximum(after - 1, 0)]))
    rows = needed if ascending else order[needed]
    bodies = table.poses[rows] @ _rigid_inverse(table.mounts[rows])
    before, inside = poses_at(stamps[needed], bodies, keyframe_stamps)
    changes = np.asarray(keyframe_poses, np.float64)[inside] @ _rigid_inverse(before[inside])
    return KeyframeCorrection(keyframe_stamps[inside], changes, int(np.min(keyframe_stamps)))


def keyframe_corrections(scans, keyframe_stamps: np.ndarray, keyframe_poses: np.ndarray) -> dict[int, np.ndarray]:
    """The corrected sensor poses of the logged ``scans`` (``keyframe_correction``): a scan
    between two keyframes takes the change interpolated between theirs by time, applied on the
    left to the pose it was integrated with; scans outside the keyframes' span are not moved
    (they came after the optimisation, with the SLAM's newer frame). Returns the new poses by
    the drive's scan index."""
    correction = keyframe_correction(scans, keyframe_stamps, keyframe_poses)
    return {} if correction is None else correction.poses_for(scans)

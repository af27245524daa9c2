"""The mapper's side of a SLAM's corrections: the scan log's segments and the corrected map.

``MapCorrections`` is a mixin of ``convbki_core.mapper.ConvBKIMapper``: its methods read and
write the mapper's own state (its store, window, scan log and change bookkeeping) as the
mapper's other methods do, so they stay methods of the mapper (the node and the tools call
them on it) rather than functions handed a mapper. It never imports the mapper (the stages
below it do not know it): a corrected map is a new mapper of the same class (``type(self)``).
What the replay is and why it is exact: ``replay``.
"""

from __future__ import annotations

import time
from typing import Self

import numpy as np

from convbki_core.correction.log_folder import SegmentBase
from convbki_core.correction.replay import CorrectionResult, continue_correction, pose_displacements
from convbki_core.correction.scan_log import ScanLog, Segment
from convbki_core.geometry.grid import check_poses


class MapCorrections:
    """The scan log and corrections (a SLAM moved poses): a log segment's base, the map
    restarted where the map changed other than by a scan, which scans a correction moves,
    the corrected map, and a new mapper started from a segment."""

    def use_log_folder(self, path, keep_named_by=()) -> None:
        """Keep the scan log's scans and bases in the folder ``path`` too (made when missing; its
        bound: the configuration's ``disk_gigabytes``), so that memory holds only its newest part
        and a correction reaches back over the drive (``scan_log``). ``keep_named_by``: map files
        saved before, whose logs' files there are never deleted. OSError where it cannot be made."""
        from convbki_core.correction.log_folder import LogFolder

        if self.scan_log is not None:
            folder = LogFolder(path, int(self.config.scan_log.disk_gigabytes * 1e9))
            folder.keep_named_by(keep_named_by)
            self.scan_log.use_folder(folder)

    def segment_base(self) -> SegmentBase:
        """The map as it is now (a log segment's base): a copy of the global store (its chunks
        shared) and the window's voxels, gathered; the base writes them into the copy when it is
        built (``SegmentBase.build``: the log's writer thread, else at once)."""
        return SegmentBase(self.store.copy(), window=self.window.items())

    def _begin_log_segment(self) -> None:
        self.scan_log.refresh_base_bytes(self.store)  # the bound counts what the older bases own by now
        self.scan_log.begin_segment(self.segment_base(), self.sensor_position)

    def _restart_log(self, why: str) -> None:
        """The map changed other than by a scan (a load, a forgotten box): a correction can
        reach back to here only, from the map as it is now; ``why`` the scans before cannot move."""
        if self.scan_log is not None:
            self.scan_log.restart(self.segment_base(), self.sensor_position, self.scans_integrated, why)

    def plan_correction(self, poses: dict[int, np.ndarray], tolerance: float = 0.0, reach: float | None = None,
                        log: ScanLog | None = None) -> tuple[dict[int, np.ndarray], int, float]:
        """Which logged scans a correction moves: of ``poses`` (corrected map <- sensor poses by
        the drive's scan index), those still in the log whose points within ``reach`` m (default:
        the window's half extent) move by ``tolerance`` m or more; ``log``: a copy of this
        mapper's log taken earlier (default: the log). Returns (moves, scans left alone, the
        largest displacement of a sensor in m)."""
        log = self.scan_log if log is None else log
        if log is None:
            raise ValueError("this mapper keeps no scan log: nothing can be moved")
        reach = self.correction_reach() if reach is None else reach
        table = log.table()
        where = {int(index): row for row, index in enumerate(table.indices)}
        wanted = [(index, where[index], pose) for index, pose in poses.items() if index in where]
        if not wanted:
            return {}, 0, 0.0
        new = check_poses(np.stack([pose for _, _, pose in wanted]))
        old = table.poses[[row for _, row, _ in wanted]]
        moving = pose_displacements(old, new, reach) >= tolerance
        moves = {index: pose for (index, _, _), pose, move in zip(wanted, new, moving) if move}
        skipped = int((~moving).sum())
        largest = float(np.linalg.norm(new[moving, :3, 3] - old[moving, :3, 3], axis=1).max()) if moving.any() else 0.0
        return moves, skipped, largest

    def correction_reach(self) -> float:
        """How far from the sensor a correction measures a scan's move (m): the window's edge."""
        return float(np.max(np.abs(self.geometry.bounds_max)))

    def corrected(self, poses: dict[int, np.ndarray], tolerance: float = 0.0, until: int | None = None,
                  reuse: Self | None = None, log: ScanLog | None = None, between=None
                  ) -> tuple[Self, CorrectionResult]:
        """This map as it would be had the logged scans been integrated at corrected poses
        (``poses``: map <- sensor by the drive's scan index; scans no longer logged, or moved by
        less than ``tolerance`` m, are left alone), and what that took. The map is not changed:
        a new mapper maps every logged scan again, in the order they came, from the base of the
        log's segment that holds the first moved one (``correction``), up to scan ``until``
        (exclusive; default: every logged scan). ``reuse``: a mapper of the same set-up to map
        into instead of a new one (the one a correction replaced: its window is already in
        memory, where a new window's pages cost more than the scans). ``log``: a copy of this
        mapper's log (``ScanLog.copy``) to read instead of the log, so that this mapper may go
        on mapping meanwhile (the node's live scans). ``between``: asked before each scan mapped
        again (``continue_correction``); False stops the replay there. Returns (the new mapper, or this one when
        nothing moves; the result).

        The new mapper has this one's configuration, so its map is held to the same memory budget
        (``memory_state``; its counts go on from the segment's base). The replay is exact only while
        neither map reached its budget: a full map drops voxels by the order it met new ground in,
        and the corrected drive meets it in another, so a corrected full map differs from this one
        mapped at the corrected poses (and from scratch) where either dropped voxels."""
        started = time.perf_counter()
        log = self.scan_log if log is None else log
        moves, skipped, largest = self.plan_correction(poses, tolerance, log=log)
        result = CorrectionResult(scans=len(moves), largest_move=largest, skipped=skipped)
        if not moves:
            result.seconds = time.perf_counter() - started
            return self, result
        segment = log.segment_for(min(moves))
        new = reuse if reuse is not None and reuse is not self else type(self)(self.config, self.layer.kernel)
        new.frame_id = self.frame_id
        new.start_from(segment, log)
        replayed = continue_correction(new, log, moves, segment.first_index, until, between)
        result.replayed = replayed
        result.seconds = time.perf_counter() - started
        return new, result

    def start_from(self, segment, log: ScanLog) -> None:
        """Make this (new) mapper the map as it was when ``segment`` of ``log`` began: its base,
        and the log's segments before it (a correction maps the scans from there again)."""
        if self.scans_integrated or len(self) or self.sensor_position is not None:
            self._clear()  # a fresh mapper is already empty: its window is not filled twice
        if segment.base is not None:
            store = segment.base_store()  # a store read from the log's folder is this mapper's own already
            self.store = store.copy() if segment.base.in_memory else store
            self.window.store = self.store
            self._bound_store()  # the corrected map is held to this mapper's budget, full at once if over it
        self.scans_integrated = segment.first_index
        if segment.base_position is not None:
            self.sensor_position = np.asarray(segment.base_position, np.float64).copy()
            self.window.move_to(self.geometry.origin_for(self.sensor_position))
        self._everything_changed = True
        self._removed = []
        self._replaced_keys = None
        if self.scan_log is not None:
            older = [s for s in log.segments() if s.first_index < segment.first_index]
            self.scan_log.frozen, self.scan_log.frozen_stamp_ns = log.frozen, log.frozen_stamp_ns
            self.scan_log.frozen_why = log.frozen_why
            self.scan_log.calibration = log.calibration
            self.scan_log.use_folder(log.folder)  # the corrected log's new bases go where the scans are
            self.scan_log.replace_from(0, [*older, Segment(segment.first_index, segment.base, segment.base_position)])


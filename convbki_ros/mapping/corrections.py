"""A SLAM's corrections: ``pose_corrections`` (nav_msgs/Path) moves the scans the map holds.

A pose-graph SLAM (LIO-SAM, RTAB-Map, GLIM, KISS-SLAM) re-publishes its keyframes' optimised
poses as one whole Path after each optimisation. Only the newest counts: a Path that arrives
while a correction runs replaces the one waiting, and is applied after it.

A correction runs on its own thread, beside the update thread:

1. the clouds stamped up to the newest keyframe received and integrated (no logged scan falls
   out of the log meanwhile), then under the map lock a copy of the scan log (its lists only:
   the scans do not change);
2. without the lock, each logged scan's corrected pose (``keyframe_corrections``), the scans
   that move by ``correction_tolerance`` or more, and a new map mapped again from the log
   (``ConvBKIMapper.corrected``), while live scans go on into the map in service;
3. the new map catches up with those live scans, again without the lock, until at most one
   is left;
4. under the lock, that last one and the swap: the update thread waits at most one scan's
   update. Then every voxel of the new map goes out on ``semantic_map/updates`` with the
   replaced map's voxels that the new one does not have as removed, so a subscriber's copy
   becomes the new map; the view and the costmap are published anew.

A reset, a load or a forgotten box while a correction runs abandons it (its map would bring
back what they removed): the SLAM's next Path corrects the map as it is then.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from convbki_core.correction.replay import CorrectionResult, continue_correction, keyframe_correction
from convbki_core.geometry.poses import quaternion_to_matrix
from convbki_ros.inputs.path_decoding import DecodedPath, PathError, decode_path, path_pose_count
from convbki_ros.inputs.pose_buffer import QUATERNION_NORM_TOLERANCE, pose_problem
from convbki_ros.inputs.transforms import stamp_to_ns
from convbki_ros.outputs.status import problem_key


@dataclass
class Keyframes:
    """A Path's keyframes, checked: stamps (K,) ns ascending, poses (K, 4, 4) map <- body."""

    stamps_ns: np.ndarray
    poses: np.ndarray
    received: float  # time.monotonic() on arrival


def path_keyframes(path: DecodedPath, map_frame: str) -> Keyframes | str:
    """The keyframes of a decoded ``nav_msgs/Path``, or why it cannot be used (one line)."""
    if path.frame_id != map_frame:
        return f"its frame is '{path.frame_id}', not the map's '{map_frame}'"
    if not len(path):
        return "it holds no pose"
    outside = path.first_pose_outside(("", map_frame))
    if outside is not None:
        return f"pose {outside} is in frame '{path.frame_ids[outside]}', not the map's '{map_frame}'"
    positions, orientations = path.positions, path.orientations
    norms = np.linalg.norm(orientations, axis=1)
    usable = (np.isfinite(positions).all(axis=1) & np.isfinite(norms)
              & (np.abs(norms - 1.0) <= QUATERNION_NORM_TOLERANCE))
    if not usable.all():
        number = int(np.flatnonzero(~usable)[0])
        return f"pose {number}: {pose_problem(positions[number], orientations[number])}"
    stamps = path.stamps_ns
    if (np.diff(stamps) <= 0).any():
        number = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
        return (f"its stamps are not in ascending order (pose {number} at {stamps[number] / 1e9:.3f} s after "
                f"{stamps[number - 1] / 1e9:.3f} s)")
    poses = np.zeros((len(path), 4, 4))
    poses[:, :3, :3] = quaternion_to_matrix(orientations / norms[:, None])
    poses[:, :3, 3] = positions
    poses[:, 3, 3] = 1.0
    return Keyframes(stamps.copy(), poses, time.monotonic())


@dataclass
class CorrectionCounts:
    """What the correction thread has done, for ``/diagnostics``."""

    received: int = 0  # Paths that passed their checks
    refused: int = 0  # Paths that did not (bad input, nothing in the log to move)
    pending: int = 0  # 1 while a Path waits or is being applied
    done: int = 0  # corrections applied (the map replaced)
    unchanged: int = 0  # Paths that moved no scan by the tolerance or more
    abandoned: int = 0  # corrections a reset, a load or a forgotten box overtook
    last: CorrectionResult | None = None
    last_received_to_applied_s: float = 0.0


class CorrectionRunner:
    """The correction thread of ``MappingCore``: takes Paths, replaces the map with corrected ones."""

    def __init__(self, core, node, warnings):
        self.core, self.node, self.warnings = core, node, warnings
        self.counts = CorrectionCounts()
        self._waiting: Keyframes | None = None
        self._busy = False
        self._stopping = False
        self._changed = threading.Condition()
        self._spare = None  # the map the last correction replaced: its window is reused by the next
        self.thread = threading.Thread(target=self._run, name="convbki_correction", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        with self._changed:
            self._stopping = True
            self._changed.notify_all()

    # -- input (executor thread) ---------------------------------------------------------------
    def on_path(self, raw: bytes) -> None:
        """A Path as its serialized bytes (a raw subscription): its pose count is read and checked
        against max_path_poses before anything is decoded, and the poses are then read with numpy,
        not as hundreds of thousands of Python objects."""
        topic = self.node.resolve_topic_name("pose_corrections")
        limit = int(self.node.param("max_path_poses"))
        try:
            count = path_pose_count(raw)
            if count > limit:
                self._refuse(f"ignoring the Path on {topic}: its {count} poses are more than max_path_poses = "
                             f"{limit} (refused before decoding); the map is unchanged")
                return
            keyframes = path_keyframes(decode_path(raw, limit), self.core.frame)
        except PathError as error:
            keyframes = f"it cannot be read: {error}"
        if isinstance(keyframes, str):
            self._refuse(f"ignoring the Path on {topic}: {keyframes}; the map is unchanged")
            return
        if self.core.mapper.scan_log is None:
            self._refuse("ignoring the Path on pose_corrections: scan_log is false, so no integrated scan can move; "
                         "the map is unchanged")
            return
        with self._changed:
            replaced = self._waiting is not None
            self._waiting = keyframes
            self.counts.received += 1
            self.counts.pending = 1
            self._changed.notify_all()
        if replaced:
            self.node.get_logger().info("a newer Path on pose_corrections replaces the one still waiting")

    def _refuse(self, text: str) -> None:
        with self._changed:
            self.counts.refused += 1
        self.warnings.warn("correction " + problem_key(text), text)

    def idle(self) -> bool:
        """No Path waits and none is being applied."""
        with self._changed:
            return self._waiting is None and not self._busy

    # -- the thread ------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._changed:
                while self._waiting is None and not self._stopping:
                    self._changed.wait()
                if self._stopping:
                    return
                keyframes, self._waiting = self._waiting, None
                self._busy = True
            try:
                self._apply(keyframes)
            except Exception as error:  # never let one correction stop the thread; the map is untouched
                self.node.get_logger().error(f"correction not applied: {error.__class__.__name__}: {error}")
            finally:
                with self._changed:
                    self._busy = False
                    self.counts.pending = int(self._waiting is not None)

    def _apply(self, keyframes: Keyframes) -> None:
        core, started = self.core, time.monotonic()
        tolerance = float(self.node.param("correction_tolerance"))
        # While the clouds up to the newest keyframe come and are integrated, a log at its bounds
        # would freeze the oldest scans, which this Path moves: none falls out until the copy.
        with core.map_lock:
            waited_on = core.mapper.scan_log
            waited_on.hold(waited_on.first_index)
        live = None
        try:
            self._wait_for_scans_up_to(int(keyframes.stamps_ns[-1]))
            with core.map_lock:
                live, lineage = core.mapper, core.lineage
                log = live.scan_log.copy()
                # The scans the live map takes from now on stay logged until the new map has them.
                live.scan_log.hold(log.next_index)
        finally:
            if live is None or waited_on is not live.scan_log:  # (a load meanwhile gave the map another log)
                waited_on.hold(None)
        try:
            self._correct(keyframes, live, lineage, log, tolerance, started)
        finally:
            live.scan_log.hold(None)

    def _correct(self, keyframes: Keyframes, live, lineage: int, log, tolerance: float, started: float) -> None:
        core = self.core
        scans = log.scans()
        correction = keyframe_correction(scans, keyframes.stamps_ns, keyframes.poses)
        if correction is None:
            self._refuse(self._outside_log(keyframes, log))
            return
        moved = correction.poses_for(scans)
        frozen_note = ""
        if log.frozen and scans and keyframes.stamps_ns[0] < scans[0][1].stamp_ns:
            frozen_note = (f"; its keyframes reach back before the oldest logged scan: the {log.frozen} scans before "
                           f"it stayed where they were ({log.frozen_why or 'frozen into the map'})")
        moves, skipped, _ = live.plan_correction(moved, tolerance, log=log)
        if not moves:
            with self._changed:
                self.counts.unchanged += 1
            self.node.get_logger().info(f"pose_corrections: none of the {len(moved)} scans it reaches moves by "
                                        f"correction_tolerance = {tolerance:g} m or more; the map is unchanged")
            return
        new, result = live.corrected(moves, log=log, reuse=self._spare)
        result.skipped = skipped
        self._spare = None
        # Catch up with the live scans without the lock, until one at most is left for the swap.
        while True:
            with core.map_lock:
                if core.lineage != lineage or core.mapper is not live:
                    self._abandon()
                    return
                behind = live.scans_integrated - new.scans_integrated
                if behind <= 1:
                    self._extend(moves, correction, live, live.scan_log, new.scans_integrated, tolerance, result)
                    result.replayed += continue_correction(new, live.scan_log, moves, new.scans_integrated)
                    new.frame_id = live.frame_id
                    core.replace_mapper(new)
                    break
                log = live.scan_log.copy()
            self._extend(moves, correction, live, log, new.scans_integrated, tolerance, result)
            result.replayed += continue_correction(new, log, moves, new.scans_integrated)
        result.seconds = time.monotonic() - started
        previous = live.items()[0]  # the replaced map changes no more: read without the lock
        with core.map_lock:
            if core.mapper is new:
                new.announce_replacement(previous)
        self.node.outputs.map_replaced()
        live.retire()  # its window is kept for the next correction; its voxels and log are freed
        self._spare = live
        with self._changed:
            self.counts.done += 1
            self.counts.last = result
        self.node.get_logger().info(
            f"pose_corrections applied: {result.scans} scans moved (largest move {result.largest_move:.2f} m, "
            f"{result.skipped} within correction_tolerance left alone), {result.replayed} mapped again, "
            f"in {result.seconds:.2f} s{frozen_note}")

    def _wait_for_scans_up_to(self, stamp: int, longest: float = 5.0) -> None:
        """Let the clouds stamped up to ``stamp`` (the newest keyframe's) arrive and the update
        thread integrate them first, for ``longest`` seconds at most: the Path moves them too.
        Arrived means a cloud stamped at or after ``stamp`` is queued or logged: a Path, a small
        message on a topic of its own, can overtake the clouds it reaches, which would then be
        mapped after the correction at their uncorrected poses; the cloud the update thread has
        taken and not yet logged counts as queued. Keyframes more than ``longest``
        seconds newer than the newest cloud are not waited for (no cloud is that late), nor any
        when no cloud is logged or queued."""
        core, queue = self.core, self.core.queue
        deadline = time.monotonic() + longest
        with queue.changed:
            while not queue.stopping and time.monotonic() < deadline:
                # The cloud the update thread is integrating counts as queued: it is not logged yet.
                queued = [stamp_to_ns(p.msg.header.stamp) for p in queue.clouds] + \
                    ([] if queue.in_flight is None else [queue.in_flight])
                logged = core.mapper.scan_log.newest_ns
                newest = max(queued + ([] if logged is None else [logged]), default=None)
                # (Nothing logged nor queued: no stream to wait for, e.g. a map loaded without a log.)
                arrived = newest is None or newest >= stamp or stamp - newest > longest * 1e9
                if arrived and (not queued or min(queued) > stamp):
                    return
                queue.changed.wait(0.05)

    @staticmethod
    def _extend(moves, correction, live, log, since: int, tolerance: float, result: CorrectionResult) -> None:
        """Scans logged since the correction began that the keyframes reach (clouds stamped before
        the newest keyframe that came late) move with the others."""
        late = [(index, scan) for index, scan in log.scans(since) if index not in moves]
        more, skipped, largest = live.plan_correction(correction.poses_for(late), tolerance, log=log)
        moves.update(more)
        result.scans += len(more)
        result.skipped += skipped
        result.largest_move = max(result.largest_move, largest)

    def _abandon(self) -> None:
        with self._changed:
            self.counts.abandoned += 1
        self.node.get_logger().warning("a correction was abandoned: the map was reset, loaded or had a box forgotten "
                                       "while it ran; the next Path on pose_corrections corrects the map as it is")

    def _outside_log(self, keyframes: Keyframes, log) -> str:
        """Why no logged scan lies between two keyframes (one line)."""
        first, last = keyframes.stamps_ns[0] / 1e9, keyframes.stamps_ns[-1] / 1e9
        scans = log.scans()
        if not scans:
            held = "the scan log holds no scan"
        else:
            held = (f"the scan log holds {len(scans)} scans stamped {scans[0][1].stamp_ns / 1e9:.3f} .. "
                    f"{scans[-1][1].stamp_ns / 1e9:.3f} s")
        if log.frozen:
            held += f"; the {log.frozen} scans before cannot move: {log.frozen_why or 'they are frozen into the map'}"
        return (f"ignoring the Path on pose_corrections: its {len(keyframes.stamps_ns)} keyframes stamped {first:.3f} "
                f".. {last:.3f} s bracket no logged scan ({held}); the map is unchanged")

    # -- reports -----------------------------------------------------------------------------------
    def diagnostic_values(self) -> list[tuple[str, str]]:
        """The correction's and the scan log's key-value pairs for ``/diagnostics``."""
        with self._changed:
            counts = CorrectionCounts(**vars(self.counts))
        values = [("corrections_pending", counts.pending), ("corrections_done", counts.done),
                  ("corrections_refused", counts.refused), ("corrections_unchanged", counts.unchanged),
                  ("corrections_abandoned", counts.abandoned)]
        if counts.last is not None:
            values += [("correction_last_scans", counts.last.scans),
                       ("correction_last_largest_move_m", f"{counts.last.largest_move:.3f}"),
                       ("correction_last_s", f"{counts.last.seconds:.3f}"),
                       ("correction_last_replayed", counts.last.replayed)]
        log = self.core.mapper.scan_log
        if log is not None:
            reach = log.reach_ns
            values += [("scan_log_scans", len(log)), ("scan_log_megabytes", f"{log.nbytes / 1e6:.1f}"),
                       ("scan_log_frozen", log.frozen),
                       ("scan_log_reach_stamp", "" if reach is None else f"{reach / 1e9:.3f}")]
        return [(key, str(value)) for key, value in values]

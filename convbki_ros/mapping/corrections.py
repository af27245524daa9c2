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

A Path that moves no scan by correction_min_move is a look at the log, counted, no line (SLAMs
re-send their path). A newer Path stops a running correction before its next scan: it goes on
with the newer poses where they agree on the scans done, else begins again. Live clouds at hand
go first. A shutdown stops it between scans; the log keeps its Path (``ScanLog.pending``).

A reset, a load or a forgotten box while a correction runs abandons it (its map would bring
back what they removed): the SLAM's next Path corrects the map as it is then.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from convbki_core.correction.replay import (
    CorrectionResult,
    continue_correction,
    correction_moves,
    keyframe_correction,
    pose_displacements,
)
from convbki_ros.inputs.path_decoding import PathError, decode_path, path_pose_count
from convbki_ros.inputs.path_keyframes import Keyframes, path_keyframes
from convbki_ros.mapping.correction_waits import let_live_scans_first, wait_for_scans_up_to
from convbki_ros.mapping.log_status import scan_log_values
from convbki_ros.outputs.status import problem_key


@dataclass
class CorrectionCounts:
    """What the correction thread has done, for ``/diagnostics``."""

    received: int = 0  # Paths that passed their checks
    refused: int = 0  # Paths that did not (bad input, nothing in the log to move)
    pending: int = 0  # 1 while a Path waits or is being applied
    done: int = 0  # corrections applied (the map replaced)
    unchanged: int = 0  # Paths that moved no scan by correction_min_move (or by the tolerance): nothing to do
    superseded: int = 0  # Paths a newer one replaced before their correction began
    retargeted: int = 0  # newer Paths that took over a running correction's scans not yet mapped again
    restarted: int = 0  # running corrections a newer Path made stale: begun again from the first scan it moves
    abandoned: int = 0  # corrections a reset, a load or a forgotten box overtook
    last: CorrectionResult | None = None
    last_check_ms: float = 0.0  # the last Path's look at the log (decoding, checks, its moves)


@dataclass
class Progress:
    """A running correction: scans mapped again of those it has to map (which grows with the live scans)."""

    done: int
    total: int
    started: float  # time.monotonic()

    def expected_end_s(self) -> float | None:
        """Seconds from now to the end at the pace so far; None before any scan is done."""
        elapsed = time.monotonic() - self.started
        if not self.done or elapsed <= 0:
            return None
        return (self.total - self.done) * elapsed / self.done


@dataclass
class Plan:
    """What one Path does to the logged scans: ``moves`` (new poses by scan index)."""

    keyframes: Keyframes
    correction: object  # ``KeyframeCorrection``
    moves: dict
    skipped: int
    frozen_note: str


class CorrectionRunner:
    """The correction thread of ``MappingCore``: takes Paths, replaces the map with corrected ones."""

    def __init__(self, core, node, warnings):
        self.core, self.node, self.warnings = core, node, warnings
        self.counts = CorrectionCounts()
        self.progress: Progress | None = None
        self._waiting: Keyframes | None = None
        self._busy = False
        self._stopping = False
        self._changed = threading.Condition()
        # The poses the running correction maps its moved scans at: (scan indices ascending, (n, 4, 4)).
        self._target: tuple[np.ndarray, np.ndarray] | None = None
        self._spare = None  # the map the last correction replaced: its window is reused by the next
        self.thread = threading.Thread(target=self._run, name="convbki_correction", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self, wait: float = 10.0) -> None:
        """Stop the thread; a correction under way stops before its next scan (the map in service
        is left as it is, and its log keeps the Path: ``map_tool correct`` applies it to a saved map)."""
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        if self.thread.is_alive():
            self.thread.join(wait)

    def min_move(self) -> float:
        """correction_min_move in metres (its -1: half a voxel)."""
        value = float(self.node.param("correction_min_move"))
        return self.core.mapper.resolution / 2.0 if value < 0 else value

    # -- input (executor thread) ---------------------------------------------------------------
    def on_path(self, raw: bytes) -> None:
        """A Path as its serialized bytes (a raw subscription): its pose count is read and checked
        against max_path_poses before anything is decoded, and the poses are then read with numpy,
        not as hundreds of thousands of Python objects. A Path that moves no logged scan by
        correction_min_move beyond where the map has it (or where the correction under way puts
        it) ends here: counted, without a line (a SLAM re-sends its path many times a second)."""
        looked = time.perf_counter()
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
            waiting = self._waiting is not None
        same = not waiting and self._moves_nothing(keyframes)
        with self._changed:
            self.counts.received += 1
            self.counts.last_check_ms = (time.perf_counter() - looked) * 1e3
            if same:
                self.counts.unchanged += 1
                return
            self.counts.superseded += int(self._waiting is not None)
            self._waiting = keyframes
            self.counts.pending = 1
            self._changed.notify_all()

    def _moves_nothing(self, keyframes: Keyframes) -> bool:
        """Whether ``keyframes`` move no logged scan by correction_min_move or more from where the
        map has it, or the correction under way will put it (stamps and poses only, vectorised)."""
        mapper = self.core.mapper
        table = mapper.scan_log.table()
        correction = keyframe_correction(table, keyframes.stamps_ns, keyframes.poses)
        if correction is None:
            return False  # nothing logged in its span yet: the thread waits for its clouds, or says why not
        with self._changed:
            target = self._target
        if target is None:  # against the poses the map has: on the changes alone
            moved = correction_moves(correction, table, mapper.correction_reach())
            return bool(moved.max() < self.min_move())
        # Against where the correction under way puts its scans, and the map the others.
        poses, reached = correction.pose_array(table)
        if not reached.any():
            return False
        reference = table.poses.copy()
        rows = np.searchsorted(table.indices, target[0])
        found = (rows < len(table)) & (table.indices[np.minimum(rows, len(table) - 1)] == target[0])
        reference[rows[found]] = target[1][found]
        moved = pose_displacements(reference[reached], poses[reached], mapper.correction_reach())
        return bool(moved.max() < self.min_move())

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
                    self._target = None
                    self.progress = None
                    self.counts.pending = int(self._waiting is not None)

    def _apply(self, keyframes: Keyframes) -> None:
        core, started = self.core, time.monotonic()
        # While the clouds up to the newest keyframe come and are integrated, a log at its bounds
        # would freeze the oldest scans, which this Path moves: none falls out until the copy.
        with core.map_lock:
            waited_on = core.mapper.scan_log
            waited_on.hold(waited_on.first_index)
        live = None
        try:
            wait_for_scans_up_to(self.core, int(keyframes.stamps_ns[-1]))
            with core.map_lock:
                live, lineage = core.mapper, core.lineage
                log = live.scan_log.copy()
                # The scans the live map takes from now on stay logged until the new map has them.
                live.scan_log.hold(log.next_index)
        finally:
            if live is None or waited_on is not live.scan_log:  # (a load meanwhile gave the map another log)
                waited_on.hold(None)
        try:
            self._correct(keyframes, live, lineage, log, started)
        finally:
            live.scan_log.hold(None)

    def _plan(self, keyframes: Keyframes, live, log) -> Plan | None:
        """What ``keyframes`` move of ``log``: None (said, counted) when they reach no logged scan;
        a plan without moves (counted) when they move none by the tolerance."""
        table = log.table()
        correction = keyframe_correction(table, keyframes.stamps_ns, keyframes.poses)
        if correction is None:
            self._refuse(self._outside_log(keyframes, log))
            return None
        moved = correction.poses_for(table)
        frozen_note = ""
        if log.frozen and len(table) and keyframes.stamps_ns[0] < table.stamps_ns[0]:
            frozen_note = (f"; its keyframes reach back before the oldest logged scan: the {log.frozen} scans before "
                           f"it stayed where they were ({log.frozen_why or 'frozen into the map'})")
        tolerance = float(self.node.param("correction_tolerance"))
        moves, skipped, _ = live.plan_correction(moved, tolerance, log=log)
        if not moves:
            with self._changed:
                self.counts.unchanged += 1
        return Plan(keyframes, correction, moves, skipped, frozen_note)

    def _set_target(self, live, plan: Plan) -> None:
        indices = np.array(sorted(plan.moves), np.int64)
        with self._changed:
            self._target = (indices, np.stack([plan.moves[int(i)] for i in indices]))
        live.scan_log.pending = (plan.keyframes.stamps_ns, plan.keyframes.poses)

    def _between(self, since: int, live):
        """``continue_correction``'s check before each scan: the progress; False when a newer Path
        waits or the node stops."""
        def between(index: int) -> bool:
            let_live_scans_first(self.core.queue, lambda: self._stopping)
            with self._changed:
                if self.progress is not None:
                    self.progress.done = index - since
                    self.progress.total = max(live.scans_integrated - since, self.progress.done)
                return self._waiting is None and not self._stopping
        return between

    def _correct(self, keyframes: Keyframes, live, lineage: int, log, started: float) -> None:
        core = self.core
        plan = self._plan(keyframes, live, log)
        if plan is None or not plan.moves:
            return
        self._set_target(live, plan)
        result, new, since = CorrectionResult(scans=len(plan.moves), skipped=plan.skipped), None, 0
        newer = 0
        while True:
            if new is None:  # (again) from the base of the segment holding the first scan the Path moves
                segment_start = log.segment_for(min(plan.moves)).first_index
                with self._changed:
                    self.progress = Progress(0, live.scans_integrated - segment_start, time.monotonic())
                new, first = live.corrected(plan.moves, log=log, reuse=self._spare,
                                            between=self._between(segment_start, live))
                self._spare = None
                since = segment_start
                result.replayed = first.replayed
                result.largest_move = first.largest_move
            else:
                result.replayed += continue_correction(new, log, plan.moves, new.scans_integrated,
                                                       between=self._between(since, live))
            with self._changed:
                stopping, taking_over = self._stopping, self._waiting
                if taking_over is not None:
                    self._waiting = None
            if stopping:
                return  # the map in service stays; its log keeps the Path (saved with it)
            if taking_over is not None:
                newer += 1
                plan, new, log = self._take_over(taking_over, live, plan, new, since)
                if plan is None:
                    return
                result.scans = len(plan.moves)
                continue
            # Caught up with the copy of the log: catch up with the live scans, until one at most is left.
            with core.map_lock:
                if core.lineage != lineage or core.mapper is not live:
                    self._abandon()
                    return
                behind = live.scans_integrated - new.scans_integrated
                if behind <= 1:
                    self._extend(plan, live, live.scan_log, new.scans_integrated, result)
                    result.replayed += continue_correction(new, live.scan_log, plan.moves, new.scans_integrated)
                    new.frame_id = live.frame_id
                    new.scan_log.pending = None
                    core.replace_mapper(new)
                    break
                log = live.scan_log.copy()
            self._extend(plan, live, log, new.scans_integrated, result)
        result.seconds = time.monotonic() - started
        previous = live.voxel_keys()  # the replaced map changes no more: read without the lock
        with core.map_lock:
            if core.mapper is new:
                new.announce_replacement(previous)
        self.node.outputs.map_replaced()
        live.retire()  # its window is kept for the next correction; its voxels and log are freed
        self._spare = live
        with self._changed:
            self.counts.done += 1
            self.counts.last = result
        newer_note = f"; {newer} newer Paths took over while it ran" if newer else ""
        self.node.get_logger().info(
            f"pose_corrections applied: {result.scans} scans moved (largest move {result.largest_move:.2f} m, "
            f"{result.skipped} within correction_tolerance left alone), {result.replayed} mapped again, "
            f"in {result.seconds:.2f} s{newer_note}{plan.frozen_note}")

    def _take_over(self, keyframes: Keyframes, live, running: Plan, new, since: int):
        """A newer Path came while a correction ran: its plan, and the new map to go on with.
        Where it agrees with the running correction on every scan already mapped again (each
        within correction_tolerance of where that put it), the correction goes on with the newer
        poses for the rest; otherwise it begins again from the first scan the newer Path moves.
        Returns (the plan, the map to go on with or None to begin again, the log copy it was
        planned on); a plan of None when the newer Path is refused or moves nothing (the map in
        service is then where it says)."""
        wait_for_scans_up_to(self.core, int(keyframes.stamps_ns[-1]))
        with self.core.map_lock:
            log = live.scan_log.copy()
        plan = self._plan(keyframes, live, log)
        if plan is not None and not plan.moves:
            live.scan_log.pending = None  # the map already is where the newest Path says
        if plan is None or not plan.moves:
            return None, None, log
        self._set_target(live, plan)
        if min(plan.moves) >= since:
            table = log.table(since)
            done = table.indices < new.scans_integrated
            indices, logged = table.indices[done], table.poses[done]

            def poses_by(moves):
                return np.array([moves.get(int(i), pose) for i, pose in zip(indices, logged)]).reshape(-1, 4, 4)
            tolerance = float(self.node.param("correction_tolerance"))
            moved = pose_displacements(poses_by(running.moves), poses_by(plan.moves), live.correction_reach())
            if (moved < tolerance).all():
                with self._changed:
                    self.counts.retargeted += 1
                return plan, new, log
        with self._changed:
            self.counts.restarted += 1
        self._spare = new  # its window is reused for the new start
        return plan, None, log

    def _extend(self, plan: Plan, live, log, since: int, result: CorrectionResult) -> None:
        """Scans logged since the correction began that the keyframes reach (clouds stamped before
        the newest keyframe that came late) move with the others."""
        late = [(index, scan) for index, scan in log.scans(since) if index not in plan.moves]
        tolerance = float(self.node.param("correction_tolerance"))
        more, skipped, largest = live.plan_correction(plan.correction.poses_for(late), tolerance, log=log)
        plan.moves.update(more)
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
                  ("corrections_superseded", counts.superseded), ("corrections_retargeted", counts.retargeted),
                  ("corrections_restarted", counts.restarted), ("corrections_abandoned", counts.abandoned),
                  ("correction_min_move_m", f"{self.min_move():.3f}"),
                  ("path_check_ms_last", f"{counts.last_check_ms:.2f}")]
        with self._changed:
            progress = None if self.progress is None else Progress(**vars(self.progress))
        if progress is not None:
            end = progress.expected_end_s()
            values += [("correction_progress", f"{progress.done}/{progress.total}"),
                       ("correction_running_s", f"{time.monotonic() - progress.started:.1f}"),
                       ("correction_expected_end_s", "" if end is None else f"{end:.1f}")]
        if counts.last is not None:
            values += [("correction_last_scans", counts.last.scans),
                       ("correction_last_largest_move_m", f"{counts.last.largest_move:.3f}"),
                       ("correction_last_s", f"{counts.last.seconds:.3f}"),
                       ("correction_last_replayed", counts.last.replayed)]
        log = self.core.mapper.scan_log
        if log is not None:
            values += scan_log_values(log, self.core.queue.newest_ns)
        return [(key, str(value)) for key, value in values]

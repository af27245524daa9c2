"""The node's files: the map loaded at start or on request, saved on request, on a timer and at
shutdown, and exported as PLY. What happens at start is ``files.start``; where the node may
write, and which files it may replace, ``files.folder`` (``map_folder``, fixed at start).

Nothing a user saved is lost:

* ``map_file``'s folder is made (or refused, exit code 2) and written to once at start, so a
  folder that does not exist, is read-only or sits on a full disk is found before a whole
  session's map depends on it;
* a request writes only the node's own files, in ``map_folder``: never through a link, never
  over another program's file (``WriteFolder.problem``, checked at every write);
* every save is atomic (a temporary file, fsync, rename) and keeps the file it replaces as
  ``<map_file>.prev``; the temporary files of saves that were killed are removed at start;
* a ``map_file`` that cannot be read, or (with ``map_file_mismatch`` set_aside) holds a map of
  another set-up, is moved aside at the first save to a name of its own,
  ``<map_file>.unreadable-<UTC time>`` or ``<map_file>.other-setup-<UTC time>``, never over
  another file; by default a map of another set-up stops the start (exit code 2);
* a save the user did not ask for (autosave, shutdown) never replaces the file with a map
  that lost evidence the file holds: after a reset, a forgotten box, or a ``map_file`` set to
  a file this map did not come from, the file is kept until ``~/save_map`` writes there, and
  then, if it holds voxels, it is first moved to ``<map_file>.kept-<UTC time>`` (at most
  ``max_kept_maps`` of them; a save that would need one more is refused);
* a save that fails is an ERROR on ``/diagnostics`` until one succeeds, and at shutdown an
  error line and a non-zero exit code.

Every write copies the map under the lock (a fraction of the time a write takes) and writes
the copy without it, so updates go on while a large map is written. Saves, loads and exports
run one after the other on the node's file thread: the service callbacks await it, so the
executor goes on taking clouds and odometry while a large file is written or read.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from rclpy.task import Future

from convbki_core.io.atomic import previous_path, set_aside
from convbki_core.io.map_file import MapFileError, MapSetupError, map_file_voxels
from convbki_core.io.ply import write_voxels_ply
from convbki_ros.files.folder import KEPT, NEW_FILE_MODE, FileKind, WriteFolder, check_map_folder, kept_maps
from convbki_ros.files.start import OTHER_SETUP, UNREADABLE, StartMap, other_setup, refusal, ways_out
from convbki_ros.outputs.status import ERROR, WARN
from convbki_ros.params import StartupError

MAX_SEGMENTS = 1000  # segment files on_pose_jump new_file makes of one map_file, at most


def segment_number(path: str) -> int:
    """N of a ``<stem>.segment-N<suffix>`` path (1 for any other)."""
    _, sep, tail = Path(path).stem.rpartition(".segment-")
    return int(tail) if sep and tail.isdigit() else 1


def next_segment_path(path: str, taken: set[str] = frozenset()) -> str:
    """The first ``<stem>.segment-N<suffix>`` beside ``path`` (N from 2) that neither exists nor
    is ``taken``; a path that is a segment already counts on from its own N."""
    target = Path(path)
    stem, number = target.stem, 2
    head, sep, tail = stem.rpartition(".segment-")
    if sep and tail.isdigit():
        stem, number = head, int(tail) + 1
    while True:
        candidate = str(target.with_name(f"{stem}.segment-{number}{target.suffix}"))
        if candidate not in taken and not os.path.lexists(candidate):
            return candidate
        number += 1


DEFAULT_PLY = "convbki_map.ply"  # ~/export_ply's file in map_folder when neither ply_file nor map_file is set
class MapFiles:
    """Load, save and export for ``MapperNode`` (whose ``core`` holds the map and its lock), in
    the ``folder`` fixed at start."""

    def __init__(self, node, folder: WriteFolder):
        self.node = node
        self.core = node.core
        self.folder = folder
        self.saved_version: int | None = 0  # map_version at the last save or load of map_file (None: never)
        self.saved_pending = None  # the scan log's pending Path at that save or load
        # core.lineage when the map last was what map_file holds (saved or loaded); None: never.
        # While it differs, the map may lack evidence the file holds, and only ~/save_map writes there.
        self.lineage_in_file: int | None = self.core.lineage
        # (path, why): a map_file that could not be loaded, moved aside before the first save writes there
        self.to_set_aside: tuple[str, str] | None = None
        self.save_error: str | None = None  # the last failed save, until a save succeeds
        self.last_save: str | None = None  # what the last save (or attempt) said
        self._file_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="convbki_files")

    async def on_file_thread(self, job, *args):
        """``job(*args)`` on the file thread, awaited (for other long jobs of the node's services)."""
        return await self._on_file_thread(job, *args)

    async def _on_file_thread(self, job, *args):
        """``job(*args)`` on the file thread; the executor runs other callbacks while it works."""
        done = Future()

        def run() -> None:
            try:
                done.set_result(job(*args))
            except BaseException as error:  # handed to the awaiting callback
                done.set_exception(error)
            executor = self.node.executor
            if executor is not None:
                executor.wake()

        self._file_thread.submit(run)
        return await done

    def close(self) -> None:
        """Let the file job in progress finish (a save is never cut short), take no more."""
        self._file_thread.shutdown(wait=True, cancel_futures=True)

    @property
    def path(self) -> str:
        return self.node.param("map_file")

    # -- start -----------------------------------------------------------------------------------
    def load_at_start(self, start: StartMap | None) -> None:
        """The map file read at start (``read_map_file_at_start``) into the map, or one error line
        and an empty map when it could not be read or holds a map of another set-up."""
        if start is None:
            return
        path, error = start.path, start.error
        if error is None:
            try:
                count, _ = self.core.load_map(path, start.contents)
            except MapSetupError as unfit:
                if self.node.param("map_file_mismatch") == "refuse":
                    raise StartupError(f"{other_setup(path, unfit.differences)}; {ways_out(unfit.differences)}") \
                        from None
                error = MapSetupError(other_setup(path, unfit.differences), unfit.differences)
            except MapFileError as unusable:
                if self.node.param("refuse_bad_map_file"):
                    raise refusal(unusable) from None
                error = unusable
        if error is not None:
            why = OTHER_SETUP if isinstance(error, MapSetupError) else UNREADABLE
            self.to_set_aside = (path, why)
            switch = "map_file_mismatch is set_aside" if why == OTHER_SETUP else \
                "set refuse_bad_map_file to exit instead"
            self.node.get_logger().error(
                f"{error}; starting with an EMPTY map ({switch}). The file is kept: the first save moves it to "
                f"{path}.{why}-<UTC time>, a name of its own, before writing the new map")
            return
        self._file_holds_the_map()
        self.node.get_logger().info(f"loaded {count} voxels from {path}")

    # -- saving ----------------------------------------------------------------------------------
    def _file_holds_the_map(self) -> None:
        self.saved_version = self.core.map_version
        self.lineage_in_file = self.core.lineage
        self.saved_pending = self._pending()

    def _pending(self):
        """The SLAM Path the map's log holds, not yet applied (None: none)."""
        log = self.core.mapper.scan_log
        return None if log is None else log.pending

    def file_may_hold_more(self) -> bool:
        """map_file exists and may hold evidence the map lacks (a reset, a forgotten box, another file)."""
        return self.lineage_in_file != self.core.lineage and os.path.lexists(self.path)

    def save_map(self, requested: bool = True) -> tuple[bool, str]:
        """Write the map to map_file; (success, what happened). ``requested``: the user asked for
        this file to be written (``~/save_map``); otherwise a file that may hold evidence the map
        lacks is kept as it is."""
        path = self.path
        if not path:
            return False, "map_file parameter is empty: nowhere to save"
        if not requested and self.file_may_hold_more():
            return True, f"kept {path} as it is: {self.kept_reason()}"
        kept_note = ""
        try:
            if self.to_set_aside is not None and self.to_set_aside[0] == path and os.path.lexists(path):
                why = self.to_set_aside[1]  # the file named at start: moved to a name of its own, not replaced
                kept = set_aside(path, why)
                what = "the unreadable map file" if why == UNREADABLE else "the map file of another set-up"
                self.node.get_logger().warning(f"moved {what} {path} to {kept}")
            self.to_set_aside = None
            problem = self.folder.problem(path, FileKind.MAP)
            if problem:
                return self._failed_save(f"could not save {path}: {problem}")
            if self.file_may_hold_more():
                refused, kept_note = self._keep_the_file()
                if refused:
                    return self._failed_save(refused)
            replaces = os.path.lexists(path)
            with self.core.map_lock:
                snapshot = self.core.mapper.snapshot()
                version, lineage = self.core.map_version, self.core.lineage
            snapshot.write(path, new_mode=NEW_FILE_MODE)
        except (OSError, ValueError) as error:
            return self._failed_save(f"could not save {path}: {getattr(error, 'strerror', None) or error}")
        self.saved_version, self.lineage_in_file, self.save_error = version, lineage, None
        self.saved_pending = None if snapshot.scan_log is None else snapshot.scan_log.pending
        kept = f" (the file before kept as {previous_path(path).name})" if replaces else ""
        self.last_save = f"saved {len(snapshot)} voxels to {path}{kept}{kept_note}"
        return True, self.last_save

    def _failed_save(self, message: str) -> tuple[bool, str]:
        self.save_error = self.last_save = message
        return False, message

    def _keep_the_file(self) -> tuple[str | None, str]:
        """map_file holds evidence the map lacks and is about to be replaced: a map file with
        voxels is moved to ``<map_file>.kept-<UTC time>`` first, so that no number of saves after
        a reset or a forgotten box loses the last map that held them. (a refusal or None, a note
        for the save's line)."""
        path = self.path
        voxels = map_file_voxels(path)
        if not voxels:
            return None, ""  # an empty map (or none): nothing to lose
        limit = int(self.node.param("max_kept_maps"))
        kept = kept_maps(path)
        if len(kept) >= limit:
            why = (f"evidence this map no longer has ({self.core.forgotten_by})" if self.lineage_in_file is not None
                   else "a map this one did not come from")
            names = ", ".join(k.name for k in kept[:3]) + (", ..." if len(kept) > 3 else "")
            return (f"not saved: {path} holds {voxels} voxels of {why}, and {len(kept)} earlier maps are kept beside "
                    f"it already (max_kept_maps = {limit}): move some of them ({names}) away first"), ""
        moved = set_aside(path, KEPT)
        self.lineage_in_file = self.core.lineage  # the file is out of the way: nothing of it can be lost now
        return None, f"; the map it held ({voxels} voxels) is kept as {moved.name}"

    def kept_reason(self) -> str:
        why = ("this map was neither loaded from it nor saved to it" if self.lineage_in_file is None else
               f"it holds evidence this map no longer has ({self.core.forgotten_by})")
        return f"{why}; call ~/save_map to write this map there, or set map_file to another file"

    def health(self) -> tuple[int, str] | None:
        """(level, message) of what the user must know about saving, for /diagnostics: ERROR while
        the last save failed, WARN while this map is not saved automatically; None when all is well."""
        if self.save_error:
            return ERROR, self.save_error
        saves_by_itself = self.node.param("save_on_shutdown") or self.node.param("autosave_period") > 0
        if saves_by_itself and self.core.map_version != self.saved_version and self.file_may_hold_more():
            return WARN, f"this map is not saved automatically: {self.path} is kept as it is, as {self.kept_reason()}"
        return None

    async def on_save_map(self, request, response):
        response.success, response.message = await self._on_file_thread(self.save_map, True)
        self._log_outcome(response.success, response.message)
        return response

    def autosave(self) -> None:
        """(Timer) queue a save of a changed map on the file thread."""
        if self.path and self.core.map_version != self.saved_version and not self.file_may_hold_more():
            self._file_thread.submit(self._autosave)

    def _autosave(self) -> None:
        if self.core.map_version != self.saved_version:  # a save queued before it may have done it
            ok, message = self.save_map(requested=False)
            self._log_outcome(ok, f"autosave: {message}")

    def save_on_shutdown(self) -> tuple[bool, str | None]:
        """Save at shutdown when asked to and the map changed: (success, what happened or None)."""
        path = self.path
        if not (self.node.param("save_on_shutdown") and path and self.core.map_version):
            return True, None
        # A correction stopped by the shutdown leaves its Path in the log: that is worth a save.
        if self.core.map_version == self.saved_version and self._pending() is self.saved_pending:
            return True, f"the map is unchanged since it was last saved to (or loaded from) {path}"
        return self.save_map(requested=False)

    # -- a new map file for a new segment (on_pose_jump new_file) --------------------------------------
    def start_new_segment(self, where: str) -> str:
        """(Executor thread; map_file is set) The map so far is written to map_file on the file
        thread, and a new, empty map starts whose saves go to the next free
        ``<stem>.segment-N<suffix>``; what was done, in words.

        When map_file may hold evidence this map lacks, the map so far goes to a segment file too,
        so that nothing saved is overwritten."""
        path = self.path
        old = path if not self.file_may_hold_more() else next_segment_path(path)
        new = next_segment_path(path, taken={old})
        if segment_number(new) > MAX_SEGMENTS:
            return (f"map kept: {MAX_SEGMENTS} segment files of {Path(path).name} exist already, the most "
                    "on_pose_jump new_file makes (a source of odometry jumps must not fill the disk); the scans after "
                    "the jump are added where the odometry now says")
        _, snapshot = self.core.take_and_reset(f"a new segment at {where}", keep=True)
        self._file_thread.submit(self._write_segment, snapshot, old)
        # Through the parameter (its checks and callbacks), so ros2 param get shows the file in use.
        from rclpy.parameter import Parameter

        result = self.node.set_parameters([Parameter("map_file", Parameter.Type.STRING, new)])[0]
        if not result.successful:
            return (f"the map so far ({len(snapshot)} voxels) is being saved to {old}; a new map starts, but "
                    f"map_file stays {path} ({result.reason})")
        return f"the map so far ({len(snapshot)} voxels) is being saved to {old}; a new map starts for the new " \
               f"segment, saved to {new} (map_file is now {new})"

    def _write_segment(self, snapshot, path: str) -> None:
        problem = self.folder.problem(path, FileKind.MAP)
        try:
            if problem:
                raise ValueError(problem)
            snapshot.write(path, new_mode=NEW_FILE_MODE)
        except (OSError, ValueError) as error:
            self.save_error = self.last_save = f"could not save the segment to {path}: " \
                                               f"{getattr(error, 'strerror', None) or error}"
            self._log_outcome(False, self.save_error)
            return
        self.last_save = f"saved the segment before the jump, {len(snapshot)} voxels, to {path}"
        self._log_outcome(True, self.last_save)

    # -- map_file at run time ----------------------------------------------------------------------
    def check_new_path(self, name: str, path: str) -> str | None:
        """Why ``path`` cannot become parameter ``name`` (map_file or ply_file) at run time (None when
        it can): a file of the node's own kind in map_folder, in a folder that exists and can be
        written (no folder is made on request)."""
        if not path:
            return None
        kind = FileKind.MAP if name == "map_file" else FileKind.PLY
        problem = self.folder.problem(path, kind)
        if problem:
            return f"{name} {path}: {problem}"
        return check_map_folder(path, make=False) if kind is FileKind.MAP else None

    def path_changed(self) -> None:
        """map_file now names another file: the map is not what it holds (if it exists)."""
        self.saved_version = None
        self.lineage_in_file = None if os.path.lexists(self.path) else self.core.lineage
        self.to_set_aside = None

    # -- loading at run time -------------------------------------------------------------------------
    async def on_load_map(self, request, response):
        response.success, response.message = await self._on_file_thread(self._load_map)
        self._log_outcome(response.success, response.message)
        return response

    def _load_map(self) -> tuple[bool, str]:
        path = self.path
        if not path:
            return False, "map_file parameter is empty: nothing to load"
        try:
            count, replaced = self.core.load_map(path)
        except MapFileError as error:
            return False, f"{error}; the map is unchanged"
        self._file_holds_the_map()
        self.node.outputs.map_replaced()
        return True, f"loaded {count} voxels from {path} (replacing {replaced})"

    # -- PLY -----------------------------------------------------------------------------------
    async def on_export_ply(self, request, response):
        response.success, response.message = await self._on_file_thread(self._export_ply)
        self._log_outcome(response.success, response.message)
        return response

    def ply_path(self) -> str:
        """Where ~/export_ply writes: ply_file, else map_file with the suffix .ply, else
        convbki_map.ply in map_folder ("" when there is no folder)."""
        path = self.node.param("ply_file")
        if path:
            return path
        if self.path:
            return str(Path(self.path).with_suffix(".ply"))
        return os.path.join(self.folder.root, DEFAULT_PLY) if self.folder.root else ""

    def _export_ply(self) -> tuple[bool, str]:
        path = self.ply_path()
        problem = self.folder.problem(path, FileKind.PLY)
        if problem:
            return False, f"could not write {path or 'a PLY file'}: {problem}"
        try:
            with self.core.map_lock:
                indices, alpha = self.core.mapper.items()
            voxels = self.core.mapper.voxel_set(indices, alpha)
            count = write_voxels_ply(voxels, path, max_variance=self.node.param("max_variance") or None,
                                     new_mode=NEW_FILE_MODE)
        except OSError as error:
            return False, f"could not write {path}: {error.strerror or error}"
        return True, f"wrote {count} voxels to {path}"

    def _log_outcome(self, ok: bool, message: str) -> None:
        # Two call sites on purpose: rclpy remembers the severity of each logging call site
        # and raises (stopping the node) when one line logs at two severities.
        if ok:
            self.node.get_logger().info(message)
        else:
            self.node.get_logger().error(message)

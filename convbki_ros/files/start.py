"""The node's map file at start, before the mapper is built: its folder made and checked, the
temporary files of killed saves removed, the file read and checked against the node's set-up,
and the folder the node may write in fixed (``map_folder``).

Everything here runs before the mapper is built, so that a folder that cannot be written, or a
map file that cannot be used, is said at once (one line, exit code 2) rather than after seconds
of compiling; ``MapFiles.load_at_start`` then puts the file read here into the map.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from convbki_core.io.atomic import previous_path, remove_stale_temp_files
from convbki_core.io.map_file import MapFileError, MapSetupError, SetupDifference, read_map, setup_differences
from convbki_ros.files.folder import WriteFolder, check_map_folder
from convbki_ros.params import StartupError


def check_map_file_at_start(node) -> WriteFolder:
    """``map_file``'s folder exists (made when missing) and can be written, else ``StartupError``;
    returns the folder the node may write in (``map_folder``), which must hold the start values
    of ``map_file`` and ``ply_file``. A node that never saves by itself (no autosave, no save on
    shutdown) only warns about a folder it cannot write. Called before the mapper is built, so
    that a bad folder is said at once."""
    path = node.param("map_file")
    if path:
        _check_map_file_folder(node, path)
    folder, problem = WriteFolder.at_start(node.param("map_folder"), path, node.param("ply_file"))
    if problem:
        raise StartupError(problem)
    return folder


def _check_map_file_folder(node, path: str) -> None:
    existed = Path(path).parent.is_dir()
    problem = check_map_folder(path)
    saves_by_itself = node.param("save_on_shutdown") or node.param("autosave_period") > 0
    if problem and saves_by_itself:
        raise StartupError(f"{problem}: this session's map could not be saved (choose another map_file, or set "
                           "save_on_shutdown false and autosave_period 0 to only read it)")
    if problem:
        node.get_logger().warning(f"{problem}: ~/save_map will fail")
    elif not existed:
        node.get_logger().info(f"made the folder {Path(path).parent} for map_file")
    _remove_killed_saves(node, path)
    _warn_if_no_room(node, path)


def _remove_killed_saves(node, path: str) -> None:
    """Remove the temporary files that saves of map_file (and of its ``.prev``) left when they
    were killed: only this node's own kind (``.NAME.PID.HOST.RANDOM.tmp``), of processes that
    are gone. Nothing of this process can be mid-save yet, so its own id counts as gone too."""
    removed = remove_stale_temp_files(path, own_too=True) + remove_stale_temp_files(previous_path(path), own_too=True)
    if removed:
        names = ", ".join(file.name for file, _ in removed)
        megabytes = sum(size for _, size in removed) / 1e6
        node.get_logger().info(f"removed {len(removed)} temporary file(s) of killed saves beside map_file "
                               f"({megabytes:.1f} MB): {names}")


def _warn_if_no_room(node, path: str) -> None:
    """Say so when the disk holds less free space than the map already saved there needs."""
    try:
        size = Path(path).stat().st_size
        free = shutil.disk_usage(Path(path).parent).free
    except OSError:
        return
    if free < size:
        node.get_logger().warning(f"map_file {path}: {free / 1e6:.1f} MB free on its disk, less than the "
                                  f"{size / 1e6:.1f} MB of the map there: a save is likely to fail")


@dataclass(frozen=True)
class LogPlace:
    """Where the scan log's files go (``scan_log_folder``), and what they must not lose."""

    path: str
    ours: bool  # chosen by the node (not scan_log_folder): removed at shutdown when left empty
    keep_named_by: tuple[str, ...]  # map files saved before, whose logs' files there stay


def scan_log_folder_at_start(node, write_folder: WriteFolder) -> LogPlace | None:
    """The scan log's folder, made (owner only) and checked writable, else ``StartupError``; None
    when the log stays in memory (``scan_log`` false, ``scan_log_disk_gigabytes`` 0). Empty
    ``scan_log_folder``: ``<map_file>.scan_log`` beside map_file, else a folder of this process in
    the user's cache folder. The map files in the folder the node writes in, and map_file with
    its ``.prev``, keep the files their logs name there."""
    if not node.param("scan_log") or node.param("scan_log_disk_gigabytes") <= 0:
        return None
    chosen, map_file = node.param("scan_log_folder"), node.param("map_file")
    cache = not chosen and not map_file
    if cache:
        root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        chosen = os.path.join(root, "convbki_ros", f"scan_log-{os.getpid()}")
        _remove_logs_of_dead_processes(os.path.dirname(chosen))
    elif not chosen:
        chosen = f"{map_file}.scan_log"
    path = os.path.abspath(chosen)
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        if not os.path.isdir(path) or not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(errno.EACCES, "not a folder it can write")
    except (OSError, ValueError) as error:
        why = f"scan_log_folder {path} cannot be used ({getattr(error, 'strerror', None) or error})"
        if node.param("scan_log_folder"):  # the user's own choice: said at once
            raise StartupError(f"{why}; set scan_log_folder to a folder the node can write, or "
                               "scan_log_disk_gigabytes 0 to keep the log in memory") from None
        node.get_logger().warning(f"{why}: the scan log is kept in memory only (scan_log_megabytes bounds it)")
        return None
    maps = [map_file, str(previous_path(map_file))] if map_file else []
    if write_folder.root:
        with contextlib.suppress(OSError):
            maps += [entry.path for entry in os.scandir(write_folder.root)
                     if entry.is_file(follow_symlinks=False) and entry.path not in maps]
    return LogPlace(path, not node.param("scan_log_folder"), tuple(maps))


def _remove_logs_of_dead_processes(parent: str) -> None:
    """The cache folders of nodes that are gone (killed before their shutdown removed them): their
    log files, then the folder. Only this project's file names are deleted."""
    from convbki_core.correction.log_folder import is_log_file

    with contextlib.suppress(OSError):
        for entry in os.scandir(parent):
            pid = entry.name.removeprefix("scan_log-")
            if not entry.name.startswith("scan_log-") or not pid.isdigit() or _alive(int(pid)):
                continue
            with contextlib.suppress(OSError):
                for file in os.scandir(entry.path):
                    if is_log_file(file.name):
                        os.unlink(file.path)
                os.rmdir(entry.path)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # another user's process: alive
    return True


def use_scan_log_folder(node, mapper, place: LogPlace | None) -> None:
    """Give ``mapper``'s scan log the folder chosen at start (``scan_log_folder_at_start``)."""
    if place is None:
        return
    try:
        mapper.use_log_folder(place.path, place.keep_named_by)
    except OSError as error:
        raise StartupError(f"scan_log_folder {place.path} cannot be used "
                           f"({getattr(error, 'strerror', None) or error})") from None
    node.get_logger().info(f"scan log in {place.path} (up to {node.param('scan_log_disk_gigabytes'):g} GB there, "
                           f"{node.param('scan_log_megabytes'):g} MB in memory)")


def close_scan_log_folder(mapper, place: LogPlace | None) -> None:
    """At shutdown, after the last save: write what is handed over, delete what no saved map names
    (and the folder, where the node chose it and it is left empty)."""
    log = mapper.scan_log
    if log is not None and log.folder is not None:
        log.folder.close(remove_folder=place is not None and place.ours)


# What a map file moved aside is named after: why it could not be loaded.
UNREADABLE, OTHER_SETUP = "unreadable", "other-setup"
# The parameter that makes a difference of set-up go away, by what differs.
MATCHING_PARAMETER = {"resolution": "resolution", "num_classes": "num_classes", "prior": "prior",
                      "frame_id": "map_frame"}


@dataclass(frozen=True)
class StartMap:
    """``map_file`` as read at start, before the mapper is built: what ``read_map`` gave, or the
    one-line reason it cannot be loaded."""

    path: str
    contents: tuple | None  # (metadata, indices, alpha)
    error: MapFileError | None = None


def read_map_file_at_start(node) -> StartMap | None:
    """Read ``map_file`` (None when there is none) and check that it fits the node's set-up,
    before the mapper is built, so that a refusal comes at once rather than after seconds of
    compiling. A file that cannot be read is refused under ``refuse_bad_map_file``; a map of
    another set-up (resolution, classes, prior, map_frame) is refused unless
    ``map_file_mismatch`` is set_aside. Otherwise the reason is kept for ``load_at_start``."""
    path = node.param("map_file")
    if not path or not Path(path).exists():
        return None
    try:
        contents = read_map(path, with_scan_log=True)
    except MapFileError as error:
        if node.param("refuse_bad_map_file"):
            raise refusal(error) from None
        return StartMap(path, None, error)
    differences = setup_differences(contents[0], node.param("resolution"), node.param("num_classes"),
                                    node.param("prior"), node.param("map_frame") or None)
    if differences:
        error = MapSetupError(other_setup(path, differences), differences)
        if node.param("map_file_mismatch") == "refuse":
            raise StartupError(f"{error}; {ways_out(differences)}")
        return StartMap(path, None, error)
    return StartMap(path, contents)


def other_setup(path: str, differences: list[SetupDifference]) -> str:
    """A map file of another set-up, in words."""
    return f"map_file {path} holds a map of another set-up ({'; '.join(d.words() for d in differences)})"


def ways_out(differences: list[SetupDifference]) -> str:
    """The two ways to start with a map file of another set-up: parameters that match it, or
    another map_file."""
    matching = " ".join(f"-p {MATCHING_PARAMETER[d.what]}:={d.in_file}" for d in differences)
    kernel = " (and a kernel_file of as many classes)" if any(d.what == "num_classes" for d in differences) else ""
    return (f"to load it, start with {matching}{kernel}; to start a new map, set map_file to another file "
            "(or map_file_mismatch:=set_aside: an empty map, and this file moved aside at the first save)")


def refusal(error: MapFileError) -> MapFileError:
    """The start-up error of a map file that cannot be used under ``refuse_bad_map_file``."""
    return MapFileError(f"{error} (refuse_bad_map_file is true: not starting)")

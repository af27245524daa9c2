"""Where the node may write: one folder, fixed at start (``map_folder``).

The node writes files on requests that anyone on its ROS domain can make (``~/save_map``,
``~/export_ply``, setting ``map_file`` or ``ply_file``), and it often runs as root in a
container. So what a request can write is decided once, at start, by whoever starts the node:

* the folder is ``map_folder``, by default the folder of ``map_file`` (else of ``ply_file``), made
  at start when missing and resolved once then (a link in its path is followed at start, never
  again); with neither set, nothing is written on request;
* ``map_file`` and ``ply_file`` must name files inside it, or inside a folder below it that
  exists (no folder is made on a request); a relative name set at run time is taken inside it;
* a name whose last part is a link, or an existing entry that is not a regular file, is refused;
  so is an existing file of another kind than the one about to be written (a ConvBKI map file
  for ``map_file`` and its ``.prev``, a PLY file this project wrote for ``ply_file``): a request
  can never replace someone else's file, only the node's own;
* new files are made readable by their owner only (``NEW_FILE_MODE``): a map's scan log holds
  every point the robot saw. A file that is replaced keeps its own mode.
"""

from __future__ import annotations

import os
import stat
import tempfile
from enum import Enum
from pathlib import Path

from convbki_core.io.atomic import previous_path
from convbki_core.io.map_file import map_file_voxels
from convbki_core.io.ply import is_own_ply

NEW_FILE_MODE = 0o600  # the node's new files: owner only
NEW_FOLDER_MODE = 0o700  # a folder the node makes at start


class FileKind(Enum):
    """What the node writes at a path, and so what an existing file there must already be."""

    MAP = "a ConvBKI map file"
    PLY = "a PLY file of this node"

    def is_own(self, path: str) -> bool:
        return map_file_voxels(path) is not None if self is FileKind.MAP else is_own_ply(path)


def _shown(path: str, limit: int = 120) -> str:
    """A path for a one-line message: printable, and cut when absurdly long."""
    text = path if path.isprintable() else repr(path)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(path)} characters)"


class WriteFolder:
    """The folder the node writes in (``root``, resolved at start), or none (``root`` None:
    nothing is written on request)."""

    def __init__(self, root: str | None):
        self.root = root

    @classmethod
    def at_start(cls, map_folder: str, map_file: str, ply_file: str) -> tuple[WriteFolder, str | None]:
        """The folder of a node started with these parameters, and the reason it cannot start
        (None when it can): ``map_folder`` (made when missing), else ``map_file``'s or
        ``ply_file``'s folder; the start values of ``map_file`` and ``ply_file`` must lie in it."""
        chosen = map_folder or (os.path.dirname(os.path.abspath(map_file)) if map_file else "") or \
            (os.path.dirname(os.path.abspath(ply_file)) if ply_file else "")
        if not chosen:
            return cls(None), None
        try:
            if map_folder and not os.path.isdir(map_folder):
                os.makedirs(map_folder, mode=NEW_FOLDER_MODE)
            root = os.path.realpath(chosen)
            if not os.path.isdir(root):
                return cls(None), f"map_folder {_shown(chosen)} is not a folder"
        except (OSError, ValueError) as error:
            why = getattr(error, "strerror", None) or error
            return cls(None), f"map_folder {_shown(chosen)} cannot be made ({why})"
        folder = cls(root)
        for name, value in (("map_file", map_file), ("ply_file", ply_file)):
            problem = value and folder.outside(value)
            if problem:
                return cls(None), f"{name} {_shown(value)} {problem} (map_folder: set it to a folder that holds both " \
                                  "map_file and ply_file)"
        return folder, None

    def resolve(self, value: str) -> str:
        """``value`` as an absolute path: a relative one is taken inside the folder (the working
        directory when there is none)."""
        base = self.root or os.getcwd()
        return os.path.normpath(os.path.join(base, value))

    def outside(self, value: str) -> str | None:
        """Why ``value`` (absolute, or relative to the working directory) is not a name inside the
        folder whose parent folder exists; None when it is."""
        if "\0" in value:
            return "holds a NUL character"
        path = os.path.abspath(value)
        try:
            parent = os.path.realpath(os.path.dirname(path))
            parent_is_folder = os.path.isdir(parent)
            name_length_ok = len(os.path.basename(path).encode()) <= os.pathconf(parent, "PC_NAME_MAX") \
                if parent_is_folder else True
        except (OSError, ValueError) as error:
            return f"cannot be used ({getattr(error, 'strerror', None) or error})"
        if self.root is None or os.path.commonpath([self.root, parent]) != self.root:
            return f"is outside the folder the node writes in ({self.root or 'none: map_folder was not set at start'})"
        if not parent_is_folder:
            return "is in a folder that does not exist (no folder is made on request)"
        if os.path.basename(path) in ("", ".", "..") or not name_length_ok:
            return "is not a file name it can write"
        return None

    def problem(self, value: str, kind: FileKind) -> str | None:
        """Why the node may not write ``kind`` at ``value`` on a request; None when it may."""
        if not value:
            return "no file is named"
        if self.root is None:
            return "the node writes no file on request: neither map_folder nor map_file nor ply_file was set at start"
        outside = self.outside(value)
        if outside:
            return outside
        path = os.path.abspath(value)
        targets = [path, str(previous_path(path))] if kind is FileKind.MAP else [path]
        for target in targets:
            try:
                info = os.lstat(target)
            except FileNotFoundError:
                continue
            except OSError as error:
                return f"{_shown(target)} cannot be checked ({error.strerror or error})"
            if stat.S_ISLNK(info.st_mode):
                return f"{_shown(target)} is a link: not writing through it, nor replacing it"
            if not stat.S_ISREG(info.st_mode):
                return f"{_shown(target)} is not a regular file"
            if not kind.is_own(target):
                return f"{_shown(target)} exists and is not {kind.value}: not replacing it"
        return None

    def describe(self) -> str:
        return self.root or "none"


KEPT = "kept"  # <map_file>.kept-<UTC time>: a map a save would have replaced after the map lost evidence


def kept_maps(path: str) -> list[Path]:
    """The maps kept beside ``path`` (``<name>.kept-<UTC time>``), oldest first."""
    target = Path(path)
    prefix = f"{target.name}.{KEPT}-"
    try:
        with os.scandir(target.parent) as entries:
            return sorted(target.parent / entry.name for entry in entries
                          if entry.name.startswith(prefix) and entry.is_file(follow_symlinks=False))
    except OSError:
        return []


def check_map_folder(path: str, make: bool = True) -> str | None:
    """Write a file in ``path``'s folder (``make``: first make the folder if it is missing, which
    only the start does); the reason it cannot be used (None when it can)."""
    target = Path(path)
    try:
        if target.is_dir():
            return f"map_file {path} is a folder, not a file"
    except (OSError, ValueError) as error:
        return f"map_file {path} cannot be used ({getattr(error, 'strerror', None) or error})"
    folder = target.parent
    try:
        if make and not folder.is_dir():
            folder.mkdir(parents=True, mode=NEW_FOLDER_MODE)
    except OSError as error:
        return f"map_file {path}: its folder cannot be made ({error.strerror or error})"
    try:  # a byte written and synced: a read-only folder and a full disk both fail here
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{target.name}.probe-") as probe:
            probe.write(b"\0")
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as error:
        return f"map_file {path}: its folder {folder} cannot be written ({error.strerror or error})"
    return None

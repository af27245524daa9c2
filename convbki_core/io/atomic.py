"""Atomic file writing: nothing a user saved is ever half-overwritten.

Every file the project writes goes through here: a temporary file in the destination
folder, flushed and fsync'ed, then renamed over the destination (atomic on POSIX), and
finally the folder itself is fsync'ed so the rename survives a power cut. A crash at any
moment leaves either the old file or the new one, never a mix.

A file written with ``keep_previous`` keeps the version it replaces beside it, as
``NAME.prev``: a hard link to the old file made before the rename (no copy, no extra space;
a copy where the file system has no hard links), itself put in place by a rename. Every
moment of a save leaves ``NAME`` whole, and ``NAME.prev`` is either the file before this
save or the one before that.

Temporary files and what happens to them when a writer is killed (``kill -9``, power cut):

* they are named ``.NAME.PID.HOST.RANDOM.tmp`` next to ``NAME``: hidden, obviously
  temporary, and carrying the id of the process that writes them;
* a writer that fails with an exception removes its own temporary file;
* one that is killed cannot, so every save of ``NAME`` first removes the temporary files
  of ``NAME`` whose writer process no longer exists. Stale files therefore never pile up:
  there is at most one per killed writer until the next save of the same file. Files of a
  live process (a concurrent save from another process or thread) are left alone.

On a folder shared between machines (NFS) a process id means nothing to another machine,
so names also carry a tag of the writer's host (``.NAME.PID.HOST.RANDOM.tmp``) and only
files written on this host are ever removed; another machine's are left alone.
"""

from __future__ import annotations

import errno
import itertools
import os
import shutil
import socket
import stat
import tempfile
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

TEMP_SUFFIX = ".tmp"
PREVIOUS_SUFFIX = ".prev"  # NAME.prev: the version a save with keep_previous replaced
# This machine, in temporary names: a short hash of the host name (names stay short and safe).
HOST_TAG = f"{zlib.crc32(socket.gethostname().encode()):08x}"


def writer_tag(pid: int | None = None) -> str:
    """``PID.HOST`` of a writer (default: this process), as temporary names carry it."""
    return f"{os.getpid() if pid is None else pid}.{HOST_TAG}"


def _stale_writer(tag: str) -> bool:
    """True when ``tag`` (``PID.HOST``) names a process of this host that no longer exists."""
    pid, _, host = tag.partition(".")
    return host == HOST_TAG and pid.isdigit() and not _process_alive(int(pid))


def temp_prefix(path: str | Path) -> str:
    """The name prefix of ``path``'s temporary files: ``.NAME.`` (the process id follows)."""
    return f".{Path(path).name}."


def previous_path(path: str | Path) -> Path:
    """Where a save with ``keep_previous`` keeps the version it replaced: ``NAME.prev``."""
    path = Path(path)
    return path.with_name(path.name + PREVIOUS_SUFFIX)


def _temp_file(path: Path) -> BinaryIO:
    folder = path.parent if str(path.parent) else Path(".")
    return tempfile.NamedTemporaryFile(mode="wb", dir=folder, prefix=f"{temp_prefix(path)}{writer_tag()}.",
                                       suffix=TEMP_SUFFIX, delete=False)


def _keep_previous(path: Path) -> None:
    """Put the current ``path`` (if any) in place as ``NAME.prev``, atomically, with its permissions."""
    previous = previous_path(path)
    remove_stale_temp_files(previous)
    with _temp_file(previous) as handle:
        temp = Path(handle.name)
    try:
        temp.unlink()
        try:
            os.link(path, temp)
        except FileNotFoundError:
            return  # nothing to keep: the first save of this file
        except OSError:  # no hard links here (some network and FUSE file systems): a copy
            # Opened without following a link and created private, then given the original's mode:
            # a copy must not be readable by more people than the file it keeps.
            source_fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
            with os.fdopen(source_fd, "rb") as source, \
                    os.fdopen(os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as copy:
                shutil.copyfileobj(source, copy, 1 << 20)
                os.fchmod(copy.fileno(), os.fstat(source.fileno()).st_mode & 0o7777)
                copy.flush()
                os.fsync(copy.fileno())
        os.replace(temp, previous)
    finally:
        temp.unlink(missing_ok=True)


@contextmanager
def atomic_open(path: str | Path, keep_previous: bool = False, new_mode: int | None = None) -> Iterator[BinaryIO]:
    """Open a temporary binary file next to ``path``; on clean exit it replaces ``path``
    (and with ``keep_previous`` the file it replaces becomes ``NAME.prev``).

    The result keeps the permissions of the file it replaces; a new file gets ``new_mode``
    (default: what a plain ``open()`` gives, 0666 minus the umask). A link at ``path`` is
    replaced, never followed. On an exception the temporary file is removed and ``path`` is
    left as it was.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    remove_stale_temp_files(path)
    handle = _temp_file(path)
    temp_path = Path(handle.name)
    try:
        # Temporary files are created 0600; give the result the permissions a plain open() would.
        os.chmod(temp_path, _final_mode(path, new_mode))
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        if keep_previous:
            _keep_previous(path)
        os.replace(temp_path, path)
    except BaseException:
        temp_path.unlink(missing_ok=True)
        raise
    _fsync_folder(folder)


def atomic_write_bytes(path: str | Path, data: bytes, keep_previous: bool = False,
                       new_mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically (``keep_previous``: the file it replaces becomes
    ``NAME.prev``; ``new_mode``: the permissions of a new file, see ``atomic_open``)."""
    with atomic_open(path, keep_previous, new_mode) as handle:
        handle.write(data)


def atomic_write_with(path: str | Path, writer: Callable[[BinaryIO], None], keep_previous: bool = False,
                      new_mode: int | None = None) -> None:
    """Call ``writer(file)`` on a temporary file that atomically becomes ``path`` (``keep_previous``:
    the file it replaces becomes ``NAME.prev``; ``new_mode``: the permissions of a new file)."""
    with atomic_open(path, keep_previous, new_mode) as handle:
        writer(handle)


def temp_files(path: str | Path) -> list[Path]:
    """Every temporary file of ``path`` in its folder, live or stale."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    prefix = temp_prefix(path)
    try:  # .NAME.PID...: another file's (.NAME.prev.PID...) begins with a letter there
        with os.scandir(folder) as entries:
            return sorted(folder / entry.name for entry in entries
                          if entry.name.startswith(prefix) and entry.name.endswith(TEMP_SUFFIX)
                          and entry.name[len(prefix):len(prefix) + 1].isdigit())
    except OSError:
        return []


def remove_stale_temp_files(path: str | Path, own_too: bool = False) -> list[tuple[Path, int]]:
    """Remove ``path``'s temporary files left by processes that no longer exist; returns each
    removed file with its size in bytes. ``own_too``: this process's files count as stale too,
    for a program that has not started writing ``path`` yet (in a container every start may get
    the same process id as the run that was killed)."""
    removed = []
    prefix = temp_prefix(path)
    for candidate in temp_files(path):
        owner = ".".join(candidate.name[len(prefix):].split(".")[:2])
        if not (_stale_writer(owner) or (own_too and owner == writer_tag())):
            continue  # not one of ours, another host's, or its writer may still be writing it
        try:
            size = candidate.stat().st_size
            candidate.unlink()
            removed.append((candidate, size))
        except FileNotFoundError:
            pass  # another writer cleaned it first
        except OSError:
            pass  # cannot remove it (read-only folder): the save itself will report that
    return removed


def set_aside(path: str | Path, why: str) -> Path:
    """Move ``path`` to a name of its own beside it, ``NAME.WHY-YYYYmmddTHHMMSSZ`` (UTC; ``-2``,
    ``-3``, ... appended when that name is taken), never over another file; returns the new path.

    The new name is taken with a hard link, which fails rather than replace an existing file,
    and the old name is then removed; where the file system has no hard links, a rename to a
    name checked to be free."""
    path = Path(path)
    base = f"{path.name}.{why}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    for number in itertools.count(1):
        target = path.with_name(base if number == 1 else f"{base}-{number}")
        try:
            os.link(path, target, follow_symlinks=False)
        except FileExistsError:
            continue
        except OSError as error:
            if error.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK, errno.EXDEV):
                raise
            if os.path.lexists(target):
                continue
            os.rename(path, target)
        else:
            os.unlink(path)
        _fsync_folder(path.parent if str(path.parent) else Path("."))
        return target
    raise AssertionError("unreachable")


def staging_prefix(final: str | Path) -> str:
    """Name prefix of the hidden staging folders beside ``final``: ``.NAME.partial-PID.HOST-``."""
    return f".{Path(final).name}.partial-{writer_tag()}-"


def remove_stale_staging_folders(final: str | Path) -> int:
    """Remove staging folders of ``final`` left by runs that were killed (their process is gone).

    A run killed mid-way (kill -9, power loss) cannot clean up, and its staging folder may
    hold gigabytes (a half-written bag). The next run for the same output removes it.
    """
    final = Path(final)
    folder = final.parent if str(final.parent) else Path(".")
    head = f".{final.name}.partial-"
    removed = 0
    try:
        entries = [entry.name for entry in os.scandir(folder) if entry.name.startswith(head) and entry.is_dir()]
    except OSError:
        return 0
    for name in entries:
        if not _stale_writer(name[len(head):].split("-", 1)[0]):
            continue  # not named by us, another host's, or its run may still be going
        shutil.rmtree(folder / name, ignore_errors=True)
        removed += 1
    return removed


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True  # maybe another thread of this process, mid-save
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # exists but belongs to another user (or cannot be asked): keep its file
    return True


def _final_mode(path: Path, new_mode: int | None = None) -> int:
    """The existing file's permissions (of a link itself, never of what it points to), else
    ``new_mode``, else 0666 minus the process umask."""
    try:
        info = path.lstat()
        if not stat.S_ISLNK(info.st_mode):
            return info.st_mode & 0o7777
    except OSError:
        pass
    if new_mode is not None:
        return new_mode
    umask = 0o022
    try:  # Linux exposes the umask without changing it (os.umask would, racing other threads)
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                umask = int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o666 & ~umask


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # some file systems do not allow opening folders; the rename is still atomic
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)

"""Atomic file writing: nothing a user saved is ever half-overwritten.

Every file the project writes goes through here: a temporary file in the destination
folder, flushed and fsync'ed, then renamed over the destination (atomic on POSIX), and
finally the folder itself is fsync'ed so the rename survives a power cut. A crash at any
moment leaves either the old file or the new one, never a mix.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


@contextmanager
def atomic_open(path: str | Path) -> Iterator[BinaryIO]:
    """Open a temporary binary file next to ``path``; on clean exit it replaces ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    handle = tempfile.NamedTemporaryFile(mode="wb", dir=folder, prefix=f".{path.name}.", suffix=".tmp", delete=False)
    temp_path = Path(handle.name)
    try:
        # Temporary files are created 0600; give the result the permissions a plain open() would.
        os.chmod(temp_path, _final_mode(path))
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temp_path, path)
    except BaseException:
        temp_path.unlink(missing_ok=True)
        raise
    _fsync_folder(folder)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path) as handle:
        handle.write(data)


def atomic_write_with(path: str | Path, writer: Callable[[BinaryIO], None]) -> None:
    """Call ``writer(file)`` on a temporary file that atomically becomes ``path``."""
    with atomic_open(path) as handle:
        writer(handle)


def _final_mode(path: Path) -> int:
    """The existing file's permissions, else 0666 minus the process umask."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        pass
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

"""The scan log's folder: where logged scans and segment bases go, so that a log can reach
back over a whole drive while memory holds only its newest part.

A ``LogFolder`` writes on a thread of its own (the update thread only hands it objects):

* every logged scan's encoded bytes (``ScanBytes``), appended to a data file
  (``scans-<id>.bin``; a new one begins with each segment of the log, so a segment that falls
  out frees whole files);
* every segment's base (``SegmentBase``: the map as it was where the segment began): the
  chunks of the map no earlier base wrote, appended to a chunk file (``chunks-<id>.bin``), and
  an index naming every chunk of the base (``base-<id>.npz``, written whole and renamed into
  place; ``store_parts``). Consecutive bases share what the map did not rewrite between them,
  so a base costs about the window's voxels and its index, not the whole map.

Files are never rewritten: a map file that names a range of one stays valid while the file
exists, so a save references the folder instead of copying it (``log_file``), and the map
file's ``.prev`` references the same files. A file is deleted (``tidy``) only when no log of
this process holds it (the live log, a correction's copy, a save's snapshot) and no map file
saved or found at start names it. Writes that fail (a full disk) leave the scan in memory and
are reported (``error``); the log then bounds its memory by letting old segments fall out,
as without a folder.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import queue
import threading
import uuid
import weakref
import zipfile
from pathlib import Path

import numpy as np

from convbki_core.memory.store_parts import ChunkPlaces

DATA_PREFIX, BASE_PREFIX, CHUNK_PREFIX = "scans-", "base-", "chunks-"
DATA_SUFFIX, BASE_SUFFIX = ".bin", ".npz"
CHUNK_FILE_BYTES = 256 * 1024 * 1024  # a chunk file is closed past this and a new one begun
_IOV_MAX = 512  # buffers per writev
FOLDER_MODE, FILE_MODE = 0o700, 0o600  # a scan log holds every point the robot saw: its owner's only


def is_log_file(name: str) -> bool:
    """Whether ``name`` is one of the files a log folder writes (the only ones it ever deletes)."""
    return (name.startswith((DATA_PREFIX, CHUNK_PREFIX)) and name.endswith(DATA_SUFFIX)) or \
        (name.startswith(BASE_PREFIX) and name.endswith(BASE_SUFFIX))


class SegmentBase:
    """A segment's base: the map (a ``VoxelStore``) as it was where the segment began, in
    memory, in a file of the log's folder (``place``), or both. Shared by every copy of the
    segment, so that it is written once.

    ``window``: the window's voxels then, (indices, alpha), not yet written into ``store`` (a
    copy of the global store then): the base is built (``store``) on the log's writer thread, or
    by the first reader, so that the update thread only gathers the window."""

    def __init__(self, store, memory_bytes: int = 0, place: tuple | None = None, num_classes: int = 0,
                 prior: float = 0.0, depends: frozenset[str] = frozenset(),
                 window: tuple[np.ndarray, np.ndarray] | None = None):
        self._store = store  # None once released (the files hold it)
        self._window = window  # still to be written into the store (None: built)
        self._build_lock = threading.Lock()
        if window is not None:
            memory_bytes = sum(part.nbytes for part in window)
        self.memory_bytes = int(memory_bytes)  # what it holds beside the map's own store
        # (the ``LogFolder``, its index file's name, the bytes it added to the folder) once written
        self.place = place
        self.depends = depends  # the chunk files its index names
        self.num_classes = store.num_classes if store is not None else int(num_classes)
        self.prior = float(store.prior) if store is not None else float(prior)

    @property
    def in_memory(self) -> bool:
        return self._store is not None

    @property
    def built(self) -> bool:
        return self._window is None

    @property
    def disk_bytes(self) -> int:
        return 0 if self.place is None else int(self.place[2])

    def build(self) -> None:
        """Write the window's voxels into the store (once; any thread): the map as it was. What it
        holds beside the map then is about the window's voxels, compacted."""
        with self._build_lock:
            if self._window is None:
                return
            before = self._store.copy()  # the chunks shared with the map when the base was taken
            self._store.write(*self._window, bounded=False)  # the map as it was, whatever its budget
            self.memory_bytes = self._store.bytes_not_shared_with(before)
            self._window = None

    def store(self):
        """The base's store: the one in memory, else read from its file (a new store each time)."""
        store = self._store
        if store is not None:
            self.build()
            return store
        folder, name, _ = self.place
        return folder.read_base(name, self.num_classes, self.prior)

    def held_store(self):
        """The store while it is in memory and built (else None): what a recount reads."""
        return self._store if self._window is None else None

    def release(self) -> int:
        """Let the store go where the file holds it; returns the memory let go."""
        if self.place is None or self._store is None:
            return 0
        self._store = None
        return self.memory_bytes


class LogFolder:
    """The files of a scan log in ``path`` (made when missing, owner only), written on a thread of
    its own. ``max_bytes``: what the live log may hold here (its oldest segments fall out past it)."""

    def __init__(self, path: str | Path, max_bytes: int = 0, writes: bool = True):
        self.path = Path(os.path.abspath(path))
        if writes:
            os.makedirs(self.path, mode=FOLDER_MODE, exist_ok=True)
            if not os.access(self.path, os.W_OK | os.X_OK):
                raise PermissionError(f"{self.path}: not writable")
        self.max_bytes = int(max_bytes)
        self.error: str | None = None  # the last write that failed, in words (None: none)
        self.written_bytes = 0
        self.backlog_bytes = 0  # scan bytes handed over and not yet written
        self._tasks: queue.Queue = queue.Queue()
        self._lock = threading.Lock()  # the data file being appended, and the files a tidy-up may delete
        self._data: tuple[str, int, int] | None = None  # (name, descriptor, size) of the data file appended
        self._chunks: tuple[str, int, int] | None = None  # the same of the chunk file appended
        self._holders: weakref.WeakSet = weakref.WeakSet()  # the ``ScanLog``s whose files must stay
        self._kept: dict[str, set[str]] = {}  # a map file's path -> the files of this folder it names
        # The files this object may delete: those it wrote, and those a log of its held (a map
        # file's loaded log). Another process's files, or another folder object's, are never its.
        self._own: set[str] = set()
        self._places = ChunkPlaces()  # the chunks written so far, named again by later bases
        self._thread: threading.Thread | None = None
        self._closed = False

    # -- what the logs hand it -------------------------------------------------------------------
    @classmethod
    def reader(cls, path: str | Path) -> LogFolder:
        """A folder only read from (the one a map file's log names): nothing is made or written."""
        folder = cls(path, writes=False)
        folder._closed = True
        return folder

    def same(self, other) -> bool:
        """Whether ``other`` is a ``LogFolder`` of the same folder."""
        return isinstance(other, LogFolder) and other.path == self.path

    def hold(self, log) -> None:
        """Keep the files ``log`` (a ``ScanLog``) refers to while it lives."""
        self._holders.add(log)

    def put_scan(self, data) -> None:
        """Write a scan's bytes (``ScanBytes``) to the data file; sets its ``place`` when done."""
        if self._closed:
            return
        with self._lock:
            self.backlog_bytes += data.size
        self._submit(("scan", data))

    def put_base(self, base: SegmentBase) -> None:
        """Write a segment's base to a file of its own, and begin a new data file (a segment's
        scans follow its base)."""
        self._submit(("base", base))

    def tidy(self) -> None:
        """Delete, on the writer thread, the files nothing holds any more (``remove_unheld``)."""
        self._submit(("tidy", None))

    def keep_for(self, map_path: str | Path, names: set[str]) -> None:
        """A map file at ``map_path`` names these files: keep them. Its file before (``.prev``) keeps
        the names it had; a map path's names are replaced by its next save."""
        map_path = str(map_path)
        with self._lock:
            if map_path in self._kept:
                self._kept[map_path + ".prev"] = self._kept[map_path]
            self._kept[map_path] = set(names)

    def keep_named_by(self, map_paths) -> None:
        """Keep the files the map files at ``map_paths`` name (read at start: the maps saved before)."""
        for map_path in map_paths:
            names = referenced_files(map_path, self.path)
            if names:
                with self._lock:
                    self._kept.setdefault(str(map_path), set()).update(names)

    def _submit(self, task) -> None:
        if self._closed:
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name="scan log writer", daemon=True)
            self._thread.start()
        self._tasks.put(task)

    # -- reading ------------------------------------------------------------------------------
    def read(self, name: str, offset: int, size: int) -> bytes:
        """``size`` bytes of file ``name`` from ``offset``; OSError where the file lacks them."""
        descriptor = os.open(self.path / name, os.O_RDONLY)
        try:
            data = os.pread(descriptor, size, offset)
        finally:
            os.close(descriptor)
        if len(data) != size:
            raise OSError(f"{self.path / name}: holds {len(data)} of the {size} bytes of a logged scan")
        return data

    def read_base(self, name: str, num_classes: int, prior: float):
        """The store a base's index names (``store_parts``); OSError or ValueError where its files
        are gone or damaged."""
        from convbki_core.memory.store_parts import INDEX_NAMES, store_of_index

        with np.load(self.path / name, allow_pickle=False) as archive:
            index = {part: archive[part] for part in INDEX_NAMES}
        files = {str(chunk_file): np.memmap(self.path / str(chunk_file), np.uint8, mode="r")
                 for chunk_file in index["names"]}
        # This folder's own chunks are named again by the bases taken from the store read (a correction's).
        return store_of_index(index, files, num_classes, prior, self._places if not self._closed else None)

    @property
    def nbytes(self) -> int:
        """What the folder's log files take on disk now."""
        total = 0
        for entry in os.scandir(self.path):
            if is_log_file(entry.name):
                with contextlib.suppress(OSError):
                    total += entry.stat().st_size
        return total

    # -- the writer thread ----------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            kind, item = self._tasks.get()
            try:
                if kind == "stop":
                    return
                if kind == "scan":
                    try:
                        self._write_scan(item)
                    finally:
                        with self._lock:
                            self.backlog_bytes -= item.size
                elif kind == "base":
                    self._write_base(item)
                elif kind == "tidy":
                    self.remove_unheld()
            except Exception as error:
                self.error = f"could not write the scan log in {self.path}: {getattr(error, 'strerror', None) or error}"
            finally:
                self._tasks.task_done()

    def _write_scan(self, data) -> None:
        if data.place is not None or not data.in_memory:
            return
        points, values = data.parts()
        with self._lock:
            if self._data is None:
                name = f"{DATA_PREFIX}{uuid.uuid4().hex[:16]}{DATA_SUFFIX}"
                descriptor = os.open(self.path / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, FILE_MODE)
                self._data = (name, descriptor, 0)
                self._own.add(name)
            name, descriptor, size = self._data
        written = os.writev(descriptor, [points, values])
        if written != data.size:
            raise OSError(f"wrote {written} of {data.size} bytes")
        with self._lock:
            self._data = (name, descriptor, size + written)
            data.place = (self, name, size)
            self.written_bytes += written

    def _write_base(self, base: SegmentBase) -> None:
        from convbki_core.memory.store_parts import chunks_of

        self._next_data_file()
        if base.place is not None or not base.in_memory:
            return
        base.build()
        store = base.held_store()
        if store is None:  # released meanwhile (only a written base is)
            return
        chunks = chunks_of(store)
        count = len(chunks)
        keys = np.array([key for key, _ in chunks], np.int64).reshape(count, 3)
        numbers, offsets = np.zeros(count, np.int32), np.zeros(count, np.int64)
        voxels = np.array([chunk.offsets.size for _, chunk in chunks], np.int64)
        entries = np.array([chunk.classes.size for _, chunk in chunks], np.int64)
        names: dict[str, int] = {}
        new = []
        for row, (_, chunk) in enumerate(chunks):
            known = self._places.get(chunk)
            if known is None:
                new.append(row)
            else:
                numbers[row], offsets[row] = names.setdefault(known[0], len(names)), known[1]
        added = self._write_chunks([chunks[row][1] for row in new], new, numbers, offsets, names)
        name = f"{BASE_PREFIX}{uuid.uuid4().hex[:16]}{BASE_SUFFIX}"
        temporary = self.path / f".{name}.part"
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE)
        with os.fdopen(descriptor, "wb") as stream:
            np.savez(stream, keys=keys, chunk_file=numbers, offset=offsets, voxels=voxels, entries=entries,
                     names=np.array(list(names), dtype="U64").reshape(-1))
            stream.flush()
            os.fsync(stream.fileno())
            size = stream.tell()
        os.replace(temporary, self.path / name)
        with self._lock:
            self._own.add(name)
            base.depends = frozenset(names)
            base.place = (self, name, size + added)
            self.written_bytes += size

    def _write_chunks(self, chunks: list, rows: list[int], numbers: np.ndarray, offsets: np.ndarray,
                      names: dict[str, int]) -> int:
        """Append ``chunks`` (those no base wrote before) to chunk files, filling their ``rows`` of
        the index; returns the bytes written."""
        from convbki_core.memory.store_parts import chunk_buffers, chunk_size

        written = 0
        for start in range(0, len(chunks), _IOV_MAX // 4):
            batch = chunks[start:start + _IOV_MAX // 4]
            with self._lock:
                if self._chunks is not None and self._chunks[2] >= CHUNK_FILE_BYTES:
                    os.fsync(self._chunks[1])
                    os.close(self._chunks[1])
                    self._chunks = None
                if self._chunks is None:
                    file = f"{CHUNK_PREFIX}{uuid.uuid4().hex[:16]}{DATA_SUFFIX}"
                    descriptor = os.open(self.path / file, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND,
                                         FILE_MODE)
                    self._chunks = (file, descriptor, 0)
                    self._own.add(file)
                file, descriptor, size = self._chunks
            buffers = [buffer for chunk in batch for buffer in chunk_buffers(chunk)]
            expected = sum(chunk_size(chunk) for chunk in batch)
            if os.writev(descriptor, buffers) != expected:
                raise OSError(f"could not write {expected} bytes of the map's chunks")
            number = names.setdefault(file, len(names))
            for chunk, row in zip(batch, rows[start:start + len(batch)]):
                numbers[row], offsets[row] = number, size
                self._places.put(chunk, file, size)
                size += chunk_size(chunk)
            with self._lock:
                self._chunks = (file, descriptor, size)
            written += expected
        if written:
            os.fsync(self._chunks[1])
        self.written_bytes += written
        return written

    def _next_data_file(self) -> None:
        with self._lock:
            if self._data is not None:
                os.fsync(self._data[1])
                os.close(self._data[1])
                self._data = None

    def flush(self) -> None:
        """Wait until everything handed over so far is written and on disk (before a map file
        names it)."""
        if self._thread is not None:
            self._tasks.join()
        with self._lock:
            if self._data is not None:
                os.fsync(self._data[1])

    # -- freeing ------------------------------------------------------------------------------
    def held_names(self, logs: bool = True) -> set[str]:
        """The files some log of this process (``logs``) or a map file this process knows holds (the
        logs' become this object's to delete once they let them go)."""
        names: set[str] = set()
        for log in list(self._holders):
            names |= log.file_names(self)
        with self._lock:
            self._own |= names
            if not logs:
                names = set()
            for kept in self._kept.values():
                names |= kept
            for current in (self._data, self._chunks):
                if current is not None:
                    names.add(current[0])
        return names

    def remove_unheld(self, logs: bool = True) -> int:
        """Delete the log files of this object's (written or held) that nothing holds now
        (``held_names``; ``logs`` false: only what map files name counts); returns how many."""
        held = self.held_names(logs)
        removed = 0
        with self._lock:  # no scan is placed in a new file meanwhile
            for current in (self._data, self._chunks):
                if current is not None:
                    held.add(current[0])
            gone = set()
            for entry in os.scandir(self.path):
                if is_log_file(entry.name) and entry.name in self._own and entry.name not in held:
                    try:
                        os.unlink(entry.path)
                        self._own.discard(entry.name)
                        gone.add(entry.name)
                        removed += 1
                    except OSError:
                        pass
        if gone:
            self._places.forget(gone)  # chunks of a deleted file are written again when next named
        return removed

    def close(self, remove_folder: bool = False) -> None:
        """Write what is handed over, stop the writer, delete what no map file names (the logs of
        the process end with it); ``remove_folder``: also remove the folder when it is left empty."""
        if self._closed:
            return
        self.flush()
        self._closed = True
        if self._thread is not None:
            self._tasks.put(("stop", None))
            self._thread.join()
        self._next_data_file()
        with self._lock:
            if self._chunks is not None:
                os.close(self._chunks[1])
                self._chunks = None
        self.remove_unheld(logs=False)
        if remove_folder:
            with contextlib.suppress(OSError):
                os.rmdir(self.path)


def files_of_meta(meta: dict) -> list[str]:
    """The files a map file's log metadata names (relative to the map file's folder, or absolute);
    ValueError where the list is damaged."""
    files = meta.get("files") or []
    if not isinstance(files, list) or not all(isinstance(name, str) for name in files):
        raise ValueError("its list of files is damaged")
    return files


def referenced_files(map_path: str | Path, folder: Path) -> set[str]:
    """The files of ``folder`` the scan log of the map file at ``map_path`` names (read from its
    log's metadata alone; none where it is not such a file)."""
    try:
        with zipfile.ZipFile(map_path) as archive, archive.open("scan_log_meta.npy") as member:
            meta = json.loads(np.lib.format.read_array(io.BytesIO(member.read()), allow_pickle=False).tobytes())
        base, real_folder = Path(map_path).parent, os.path.realpath(folder)
        return {Path(name).name for name in files_of_meta(meta)
                if os.path.realpath(base / name).startswith(real_folder + os.sep)}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, AttributeError, TypeError):
        return set()

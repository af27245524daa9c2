"""Map saves survive kill -9 at any point of a save, keep the file they replace as NAME.prev, leave
no temporary file when they fail, and clear the ones killed saves left. (Broken map files are
refused with a reason: test_map_file_errors.py.)

The kill test runs a real writer: a process that builds a ConvBKIMapper holding a map of
tens of thousands of voxels and saves it to one path, each save a new, recognisable
version (``scans_integrated`` = version, and a block of marker voxels whose every
concentration equals the version). To avoid paying the torch import for every kill, the
writer forks a child per round and the child does the saving.

Kills land at chosen points, not at random moments: the child's file operations are
instrumented (the temporary file's creation, each write to it, the fsyncs, the rename),
and when the child reaches the point the test chose for the round it says so and stops
itself (SIGSTOP); the test then checks the files on disk and SIGKILLs it. So every
phase of a save is killed on every run, whatever the machine's speed, and what the file
must hold afterwards is known exactly: the previous version before the rename, the new
one from the rename on.
"""

from __future__ import annotations

import os
import re
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import small_saved_map, sorted_map

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.io import atomic
from convbki_core.io.atomic import (
    atomic_write_bytes,
    atomic_write_with,
    previous_path,
    remove_stale_temp_files,
    set_aside,
    temp_files,
    writer_tag,
)
from convbki_core.io.map_file import read_map

REPO = Path(__file__).resolve().parents[2]
MARKERS = 2000  # voxels whose concentrations carry the version number
GRID = (300, 12, 20)  # the map: a 60 m x 2.4 m x 4 m slab of 0.2 m voxels (72,000 voxels)

# The writer process. Versions: 0 written before the first fork; round r's child writes
# r * 1000 + 1, + 2, ... until it reaches the round's kill point. Points of a save, in order:
# "start" (nothing done yet), "open" (temporary file created, empty), "write" (after each write
# to it), "fsync" (1: the temporary file's, before the rename; 2: the folder's, after it),
# "replace" (just before the rename), "replaced" (just after it). Lines on stdout: "ready WRITES"
# (writes of one save), "child PID", "at PHASE COUNT VERSION" (the child stopped there), "done V",
# "dead PID". Both write whole lines with os.write (unbuffered, one write a line, so lines never
# interleave), and every line the child wrote is in the pipe before the parent reports its death.
WRITER = r"""
import os, signal, sys
import numpy as np
from convbki_core import ConvBKIMapper, KernelConfig
from convbki_core.config import MapperConfig
import convbki_core.io.atomic as atomic

path, markers, grid_shape = sys.argv[1], int(sys.argv[2]), [int(v) for v in sys.argv[3].split(",")]
config = KernelConfig("single", 0.2, 3, 20, ell=[0.3])
mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-2, -2, -1), (2, 2, 1)), device="cpu"), config)
grid = np.stack(np.meshgrid(*(np.arange(n) for n in grid_shape), indexing="ij"), -1).reshape(-1, 3)
rng = np.random.default_rng(0)
mapper.store.write(grid, rng.random((len(grid), 20), dtype=np.float32) + 0.001)
marker_index = grid[:markers]
target, counts, state = None, {}, {"save": 0, "version": 0}

def point(phase):
    counts[phase] = counts.get(phase, 0) + 1
    if target == (phase, state["save"], counts[phase]):
        os.write(1, f"at {phase} {counts[phase]} {state['version']}\n".encode())
        os.kill(os.getpid(), signal.SIGSTOP)  # the test kills it here

class Watched:
    def __init__(self, handle):
        self.handle = handle
    def __getattr__(self, name):
        return getattr(self.handle, name)
    def __enter__(self):
        self.handle.__enter__()
        return self
    def __exit__(self, *exc):
        return self.handle.__exit__(*exc)
    def write(self, data):
        written = self.handle.write(data)
        point("write")
        return written

real_temporary, real_fsync, real_replace = atomic.tempfile.NamedTemporaryFile, os.fsync, os.replace

def temporary(*args, **kwargs):
    handle = real_temporary(*args, **kwargs)
    point("open")
    return Watched(handle)

def fsync(descriptor):
    point("fsync")
    real_fsync(descriptor)

def replace(source, destination):
    point("replace")
    real_replace(source, destination)
    point("replaced")

atomic.tempfile.NamedTemporaryFile, os.fsync, os.replace = temporary, fsync, replace

def save(version):
    counts.clear()
    state["save"] += 1
    state["version"] = version
    point("start")
    mapper.store.write(marker_index, np.full((markers, 20), float(version), np.float32))
    mapper.scans_integrated = version
    mapper.save(path)

save(0)
os.write(1, f"ready {counts['write']}\n".encode())
for line in sys.stdin:
    command, *argument = line.split()
    if command != "fork":
        break
    round_number, phase, save_number, count = int(argument[0]), argument[1], int(argument[2]), int(argument[3])
    pid = os.fork()
    if pid == 0:
        target, state["save"] = (phase, save_number, count), 0
        version = round_number * 1000
        while True:
            version += 1
            save(version)
            os.write(1, f"done {version}\n".encode())
    os.write(1, f"child {pid}\n".encode())
    os.waitpid(pid, 0)
    os.write(1, f"dead {pid}\n".encode())
"""


class LineReader:
    """Lines of a pipe with a timeout, so a stuck writer fails the test instead of hanging it."""

    def __init__(self, stream):
        self.stream = stream
        self.selector = selectors.DefaultSelector()
        self.selector.register(stream, selectors.EVENT_READ)
        self.buffer = b""

    def line(self, timeout: float = 120.0) -> str:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not self.selector.select(left):
                raise AssertionError(f"the writer said nothing for {timeout} s")
            chunk = os.read(self.stream.fileno(), 65536)
            if not chunk:
                raise AssertionError("the writer exited")
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line.decode()


def scans_and_sorted_map(path: Path) -> tuple[int, np.ndarray, np.ndarray]:
    metadata, indices, alpha = sorted_map(path)
    return metadata["scans_integrated"], indices, alpha


def kill_points(writes: int) -> list[tuple[str, int, int]]:
    """(phase, save of the child, occurrence in that save) of every round's kill. A save renames
    twice: the file it replaces to NAME.prev (a hard link), then its staging file to NAME."""
    return [("start", 2, 1), ("open", 1, 1), ("write", 1, 1), ("write", 2, max(1, writes // 2)),
            ("write", 1, writes), ("fsync", 2, 1), ("replace", 1, 1), ("replaced", 1, 1), ("replace", 2, 2),
            ("replaced", 1, 2), ("fsync", 2, 2), ("start", 3, 1), ("write", 2, 2)]  # the last leaves a staging file


BEFORE_RENAME = {"open", "write", "replace"}  # and fsync 1, and the first rename (NAME.prev)


def test_map_save_survives_kill_9_at_every_point_of_a_save(tmp_path):
    path = tmp_path / "map.npz"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               # One thread for torch/OpenMP/numba: the writer forks, and a thread pool does not survive fork.
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(MARKERS), ",".join(map(str, GRID))],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, cwd=tmp_path)
    try:
        reader = LineReader(writer.stdout)
        ready = reader.line(timeout=180)
        assert ready.startswith("ready "), ready
        writes = int(ready.split()[1])
        assert writes >= 3, "a save writes its file in several pieces, so a kill can land between them"
        version, reference_index, reference_alpha = scans_and_sorted_map(path)
        assert version == 0 and len(reference_index) == int(np.prod(GRID))
        marker = np.zeros(len(reference_index), bool)
        marker[:MARKERS] = True  # the grid's first rows are also first in sorted order
        last_done = 0
        for round_number, (phase, save_number, count) in enumerate(kill_points(writes), start=1):
            writer.stdin.write(f"fork {round_number} {phase} {save_number} {count}\n".encode())
            writer.stdin.flush()
            child, stopped_at = None, None
            while stopped_at is None:
                kind, *rest = reader.line().split()
                if kind == "child":
                    child = int(rest[0])
                elif kind == "done":
                    last_done = int(rest[0])
                else:
                    assert kind == "at", kind
                    stopped_at = (rest[0], int(rest[1]), int(rest[2]))
            if child is None:  # the child may speak before its parent names it
                kind, pid = reader.line().split()
                assert kind == "child", kind
                child = int(pid)
            this_version = round_number * 1000 + save_number
            assert stopped_at == (phase, count, this_version)
            if save_number > 1:  # the child's earlier saves completed
                assert last_done == this_version - 1

            # What is on disk at the kill: the child's staging file exists exactly while it writes.
            staging = [p for p in temp_files(path) if f".{child}." in p.name]
            renamed = (phase == "replaced" and count == 2) or (phase == "fsync" and count == 2)
            mid_save = phase in BEFORE_RENAME or (phase, count) in {("fsync", 1), ("replaced", 1)}
            assert len(staging) == (1 if mid_save else 0), (phase, count, staging)
            os.kill(child, signal.SIGKILL)
            assert reader.line() == f"dead {child}"

            # Stale files never pile up: a save first removes the temporary files of dead writers
            # (the earlier rounds'), so only the staging file of the child just killed is left.
            assert temp_files(path) == staging
            version, index, alpha = scans_and_sorted_map(path)  # the file must load after every kill
            assert version == (this_version if renamed else last_done), (phase, count, version)
            np.testing.assert_array_equal(index, reference_index)
            assert (alpha[marker] == float(version)).all()
            np.testing.assert_array_equal(alpha[~marker], reference_alpha[~marker])
            # NAME.prev is a whole map too: an older version, or the same one when the kill came between
            # the save's two renames.
            previous_version, previous_index, _ = scans_and_sorted_map(previous_path(path))
            between_renames = (phase, count) in {("replaced", 1), ("replace", 2)}
            assert previous_version == version if between_renames else previous_version < version, \
                (phase, count, previous_version, version)
            np.testing.assert_array_equal(previous_index, reference_index)
            last_done = version
        writer.stdin.write(b"quit\n")
        writer.stdin.flush()
        assert writer.wait(timeout=60) == 0
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait()
    # The last writer, killed mid-save, left its temporary file; removing stale files removes it.
    stale = temp_files(path)
    assert len(stale) == 1
    sizes = [file.stat().st_size for file in stale]
    assert remove_stale_temp_files(path) == list(zip(stale, sizes))
    assert temp_files(path) == []


def test_stale_temp_files_of_live_processes_and_other_names_are_kept(tmp_path):
    path = tmp_path / "map.npz"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".map.npz.{writer_tag(dead.pid)}.abc.tmp"
    mine = tmp_path / f".map.npz.{writer_tag()}.def.tmp"  # this process: maybe another thread mid-save
    parent = tmp_path / f".map.npz.{writer_tag(os.getppid())}.ghi.tmp"  # a live process
    other = tmp_path / f".other.npz.{writer_tag(dead.pid)}.abc.tmp"  # another file's
    remote = tmp_path / f".map.npz.{dead.pid}.0badc0de.jkl.tmp"  # another host's (NFS): its pid means nothing here
    for p in (stale, mine, parent, other, remote):
        p.write_bytes(b"partial")
    atomic_write_bytes(path, b"complete")
    assert path.read_bytes() == b"complete"
    assert not stale.exists() and mine.exists() and parent.exists() and other.exists() and remote.exists()
    # A program that has not begun to write the file (a node at start) counts its own process's
    # files as stale too: a killed run in a container may have had the same process id.
    assert remove_stale_temp_files(path, own_too=True) == [(mine, len(b"partial"))]
    assert parent.exists() and other.exists() and remote.exists()


def test_a_file_set_aside_gets_a_name_of_its_own_and_never_replaces_another(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    path.write_bytes(b"first")
    first = set_aside(path, "unreadable")
    assert re.fullmatch(r"map\.npz\.unreadable-\d{8}T\d{6}Z", first.name), first.name
    assert first.read_bytes() == b"first" and not path.exists()
    # Within one second (the clock held), each file still gets a name of its own, and a file
    # already there under the next name is not replaced either.
    monkeypatch.setattr(atomic.time, "strftime", lambda form, moment=None: "20261206T120000Z")
    squatter = tmp_path / "map.npz.unreadable-20261206T120000Z-2"
    squatter.write_bytes(b"someone else's")
    kept = []
    for content in (b"second", b"third", b"fourth"):
        path.write_bytes(content)
        kept.append(set_aside(path, "unreadable"))
    assert [file.name for file in kept] == ["map.npz.unreadable-20261206T120000Z",
                                            "map.npz.unreadable-20261206T120000Z-3",
                                            "map.npz.unreadable-20261206T120000Z-4"]
    assert [file.read_bytes() for file in kept] == [b"second", b"third", b"fourth"]
    assert squatter.read_bytes() == b"someone else's" and first.read_bytes() == b"first"


def test_failed_save_leaves_the_old_file_and_no_temp_file(tmp_path):
    path = tmp_path / "map.npz"
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-1, -1, -1), (1, 1, 1)), device="cpu"),
                           ConvBKIKernel("single", 4, 3, 0.2, ell=0.3))
    mapper.store.write(np.array([[0, 0, 0], [1, 2, 3]]), np.ones((2, 4), np.float32))
    mapper.save(path)
    before = path.read_bytes()
    mapper.store.write(np.array([[2**40, 0, 0]]), np.ones((1, 4), np.float32))  # beyond int32: refused
    with pytest.raises(ValueError, match="int32"):
        mapper.save(path)
    assert path.read_bytes() == before and temp_files(path) == []


# ----------------------------------------------------------------------------- the file a save replaces


def test_a_save_keeps_the_file_it_replaces_as_prev_and_a_failed_save_keeps_both(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    atomic_write_bytes(path, b"first", keep_previous=True)
    assert path.read_bytes() == b"first" and not previous_path(path).exists()  # nothing was replaced
    atomic_write_bytes(path, b"second", keep_previous=True)
    assert previous_path(path).read_bytes() == b"first" and path.read_bytes() == b"second"
    assert os.stat(previous_path(path)).st_nlink == 1  # a file of its own once the next rename happened

    def fail(handle):
        handle.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write_with(path, fail, keep_previous=True)
    assert path.read_bytes() == b"second" and previous_path(path).read_bytes() == b"first"
    assert temp_files(path) == [] and temp_files(previous_path(path)) == []

    # Without hard links (some network file systems) the file before is copied.
    def no_links(source, destination):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    atomic_write_bytes(path, b"third", keep_previous=True)
    assert previous_path(path).read_bytes() == b"second" and path.read_bytes() == b"third"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npz", "map.npz.prev"]


def test_a_map_save_over_a_map_keeps_the_map_before_it_loadable(tmp_path):
    path = small_saved_map(tmp_path)
    before = path.read_bytes()
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-1, -1, -1), (1, 1, 1)), device="cpu"),
                           ConvBKIKernel("single", 4, 3, 0.2, ell=0.3))
    mapper.load(path)
    mapper.store.write(np.array([[9, 9, 9]]), np.full((1, 4), 2.0, np.float32))
    mapper.save(path)
    assert previous_path(path).read_bytes() == before
    assert len(read_map(path)[1]) == 4 and len(read_map(previous_path(path))[1]) == 3

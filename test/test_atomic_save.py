"""Map saves survive kill -9 at any moment, and broken map files are refused with a reason.

The kill test runs a real writer: a process that builds a ConvBKIMapper holding a map of
a few hundred thousand voxels and saves it to one path over and over, each save a new,
recognisable version (``scans_integrated`` = version, and a block of marker voxels whose
every concentration equals the version). To avoid paying the torch import for every kill,
the writer forks a child per round and the child does the saving; the test SIGKILLs the
child at a random moment, then checks the file on disk.
"""

from __future__ import annotations

import io
import json
import os
import random
import selectors
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from convbki_core import ConvBKIKernel, ConvBKIMapper, MapFileError
from convbki_core.io.atomic import atomic_write_bytes, remove_stale_temp_files, temp_files, writer_tag
from convbki_core.io.map_file import MAP_VERSION, read_map

REPO = Path(__file__).resolve().parents[1]
KILLS = 25
MARKERS = 2000  # voxels whose concentrations carry the version number

# The writer process. Versions: 0 written before the first fork; round r's child writes
# r * 1000 + 1, + 2, ... until killed. Lines on stdout: "ready SECONDS" (one save's time),
# "child PID", "start V", "done V", "dead PID". Both write whole lines with os.write
# (unbuffered, one write a line, so lines never interleave), and every line the child wrote
# is in the pipe before the parent reports its death.
WRITER = r"""
import os, sys, time
import numpy as np
from convbki_core.kernels import KernelConfig
from convbki_core.mapper import ConvBKIMapper

path, markers = sys.argv[1], int(sys.argv[2])
config = KernelConfig("single", 0.2, 3, 20, ell=[0.3])
mapper = ConvBKIMapper(config, local_bounds=((-2, -2, -1), (2, 2, 1)), device="cpu")
# A realistic map: a 240 m x 60 m x 4 m slab of 0.2 m voxels (~ 300k voxels), random concentrations.
grid = np.stack(np.meshgrid(np.arange(1200), np.arange(12), np.arange(20), indexing="ij"), -1).reshape(-1, 3)
rng = np.random.default_rng(0)
alpha = rng.random((len(grid), 20), dtype=np.float32) + 0.001
mapper.store.write(grid, alpha)
marker_index = grid[:markers]

def save(version):
    mapper.store.write(marker_index, np.full((markers, 20), float(version), np.float32))
    mapper.scans_integrated = version
    mapper.save(path)

started = time.perf_counter()
save(0)
os.write(1, f"ready {time.perf_counter() - started:.4f}\n".encode())
for line in sys.stdin:
    command, _, argument = line.strip().partition(" ")
    if command != "fork":
        break
    round_number = int(argument)
    pid = os.fork()
    if pid == 0:
        version = round_number * 1000
        while True:
            version += 1
            os.write(1, f"start {version}\n".encode())
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

    def line(self, timeout: float = 60.0) -> str:
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


def sorted_map(path: Path) -> tuple[int, np.ndarray, np.ndarray]:
    metadata, indices, alpha = read_map(path)
    order = np.lexsort(indices.T[::-1])
    return metadata["scans_integrated"], indices[order], alpha[order]


def test_map_save_survives_kill_9_at_random_moments(tmp_path):
    path = tmp_path / "map.npz"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
               # One thread for torch/OpenMP/numba: the writer forks, and a thread pool does not survive fork.
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(MARKERS)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, env=env, cwd=tmp_path)
    rng = random.Random(1234)
    try:
        reader = LineReader(writer.stdout)
        ready = reader.line(timeout=180)
        assert ready.startswith("ready "), ready
        save_seconds = float(ready.split()[1])
        version, reference_index, reference_alpha = sorted_map(path)
        assert version == 0 and len(reference_index) == 1200 * 12 * 20
        marker = np.zeros(len(reference_index), bool)
        marker[:MARKERS] = True  # the grid's first rows are also first in sorted order
        last_done, killed_mid_write, versions_seen, children = 0, 0, {0}, set()
        for round_number in range(1, KILLS + 1):
            writer.stdin.write(f"fork {round_number}\n".encode())
            writer.stdin.flush()
            last_started = last_done
            child = None

            def follow(line: str) -> None:
                nonlocal last_started, last_done
                kind, number = line.split()
                if kind == "start":
                    last_started = int(number)
                elif kind == "done":
                    last_done = int(number)
                else:
                    raise AssertionError(line)

            while not (line := reader.line()).startswith("child "):
                follow(line)  # the child may speak before its parent names it
            child = int(line.split()[1])
            children.add(child)
            # Anywhere in the first ~3 saves, so kills land in every phase of a save.
            time.sleep(rng.uniform(0.0, 3.0 * save_seconds))
            live_temp = [p for p in temp_files(path) if f".{child}." in p.name]
            os.kill(child, signal.SIGKILL)
            while (line := reader.line()) != f"dead {child}":
                follow(line)
            left = temp_files(path)
            # Stale files never pile up: every save first removes the temporary files of dead
            # writers, so at most one remains, that of the last child killed after it created
            # its file (this one, or an earlier one when the later children died before saving).
            assert len(left) <= 1 and all(int(p.name.split(".")[3]) in children for p in left), left
            killed_mid_write += bool(left and live_temp)

            version, index, alpha = sorted_map(path)  # the file must load after every kill
            assert version in {last_done, last_started}, (version, last_done, last_started)
            np.testing.assert_array_equal(index, reference_index)
            assert (alpha[marker] == float(version)).all()
            np.testing.assert_array_equal(alpha[~marker], reference_alpha[~marker])
            last_done = version
            versions_seen.add(version)
        writer.stdin.write(b"quit\n")
        writer.stdin.flush()
        assert writer.wait(timeout=60) == 0
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait()
    # Some kills hit a save after its temporary file existed and before its rename (else the
    # test proved nothing), and saves did complete between kills.
    print(f"save {save_seconds:.3f} s, {killed_mid_write} of {KILLS} kills mid-write, versions {sorted(versions_seen)}")
    assert killed_mid_write >= 3, killed_mid_write
    assert len(versions_seen) >= 3, versions_seen  # low bar: a loaded CI machine saves slowly
    # A writer killed mid-save leaves its temporary file; the next save of the file removes it.
    stale = temp_files(path)
    assert len(stale) <= 1 and remove_stale_temp_files(path) == len(stale)
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


def test_failed_save_leaves_the_old_file_and_no_temp_file(tmp_path):
    path = tmp_path / "map.npz"
    mapper = ConvBKIMapper(ConvBKIKernel("single", 4, 3, 0.2, ell=0.3), local_bounds=((-1, -1, -1), (1, 1, 1)),
                           device="cpu")
    mapper.store.write(np.array([[0, 0, 0], [1, 2, 3]]), np.ones((2, 4), np.float32))
    mapper.save(path)
    before = path.read_bytes()
    mapper.store.write(np.array([[2**40, 0, 0]]), np.ones((1, 4), np.float32))  # beyond int32: refused
    with pytest.raises(ValueError, match="int32"):
        mapper.save(path)
    assert path.read_bytes() == before and temp_files(path) == []


# ----------------------------------------------------------------------------- broken map files


def _saved_map(folder: Path) -> Path:
    mapper = ConvBKIMapper(ConvBKIKernel("single", 4, 3, 0.2, ell=0.3), local_bounds=((-1, -1, -1), (1, 1, 1)),
                           device="cpu")
    mapper.store.write(np.array([[0, 0, 0], [1, 2, 3], [-4, 5, 6]]), np.arange(12, dtype=np.float32).reshape(3, 4))
    path = folder / "good.npz"
    mapper.save(path)
    return path


def _npy_bytes(array: np.ndarray) -> bytes:
    """A bare .npy file's bytes (np.save to a path would append .npy to the name)."""
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _rewrite(good: Path, out: Path, change) -> Path:
    """A copy of ``good`` with its metadata changed by ``change(dict)``."""
    with np.load(good) as archive:
        arrays = {name: archive[name] for name in archive.files}
    metadata = json.loads(arrays["metadata"].tobytes())
    change(metadata)
    arrays["metadata"] = np.frombuffer(json.dumps(metadata).encode(), np.uint8)
    np.savez(out, **arrays)
    return out


def _rewrite_arrays(good: Path, out: Path, change) -> Path:
    """A copy of ``good`` with its arrays (a dict of writable copies) changed by ``change(dict)``."""
    with np.load(good) as archive:
        arrays = {name: archive[name].copy() for name in archive.files}
    change(arrays)
    np.savez(out, **arrays)
    return out


def _as_version_1(good: Path, out: Path, change, alpha_change=lambda alpha: None) -> Path:
    """``good`` in the version 1 layout (dense ``alpha``), metadata changed by ``change(dict)``."""
    metadata, indices, alpha = read_map(good)
    metadata["version"] = 1
    change(metadata)
    alpha_change(alpha)
    np.savez(out, metadata=np.frombuffer(json.dumps(metadata).encode(), np.uint8),
             voxel_index=indices.astype(np.int32), alpha=alpha)
    return out


@pytest.mark.parametrize("make, message", [
    (lambda good, p: p.write_bytes(b""), "empty file"),
    (lambda good, p: p.write_bytes(good.read_bytes()[:100]), "truncated or corrupted"),
    (lambda good, p: p.write_bytes(good.read_bytes()[:-30]), "truncated or corrupted"),
    (lambda good, p: p.write_text("# a PLY or text file\n"), "truncated or corrupted"),
    (lambda good, p: p.write_bytes(_npy_bytes(np.zeros((3, 3)))), "single NumPy array"),
    (lambda good, p: np.savez(p, voxels=np.zeros(3)), "missing class_count, class_id, metadata, value, voxel_index"),
    (lambda good, p: zipfile.ZipFile(p, "w").writestr("readme.txt", "hello"), "missing"),
    (lambda good, p: p.mkdir(), "is a folder"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=MAP_VERSION + 1)), "version 3 is not supported"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=[2])), "version \\[2\\] is not supported"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(format="octomap")), "format is 'octomap'"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(num_classes="20")), "num_classes"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(num_classes=3)), "inconsistent arrays"),  # class id 3
    (lambda good, p: _as_version_1(good, p, lambda m: m.update(num_classes=5)), "inconsistent arrays"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(resolution=-0.2)), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(resolution=10**400)), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.pop("resolution")), "resolution"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(scans_integrated=-1)), "scans_integrated"),
    (lambda good, p: _rewrite(good, p, lambda m: m.pop("prior")), "prior must be a positive number"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(prior=0)), "prior must be a positive number"),
    (lambda good, p: _rewrite(good, p, lambda m: m.update(version=1)), "missing alpha"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.pop("class_id")), "missing class_id"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(class_count=a["class_count"][:2])),
     "inconsistent arrays"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(value=a["value"][:-1])), "inconsistent arrays"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_count"].__setitem__(0, 3)), "sums to 11"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_count"].__setitem__(0, 5)), "class_count beyond"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(1, 4)), "class_id beyond"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(1, 0)), "must ascend"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["class_id"].__setitem__(2, 1)), "must ascend"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, -1.0)), "non-negative"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, np.inf)), "finite"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a["value"].__setitem__(5, np.nan)), "finite"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(class_id=a["class_id"].astype(np.float32))),
     "unexpected array types"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(voxel_index=a["voxel_index"].astype(np.float32))),
     "unexpected array types"),
    (lambda good, p: _rewrite_arrays(good, p, lambda a: a.update(voxel_index=a["voxel_index"][[0, 1, 1]])),
     "duplicate voxel indices"),
    (lambda good, p: _as_version_1(good, p, lambda m: None, alpha_change=lambda a: a.__setitem__((0, 1), -1.0)),
     "non-negative"),
])
def test_broken_map_files_raise_map_file_error_naming_file_and_problem(tmp_path, make, message):
    good = _saved_map(tmp_path)
    bad = tmp_path / "bad.npz"
    make(good, bad)
    with pytest.raises(MapFileError, match=message) as error:
        read_map(bad)
    assert str(error.value).startswith(f"{bad}: ") and "\n" not in str(error.value)
    metadata, indices, alpha = read_map(good)  # the good file is fine
    assert metadata["num_classes"] == 4 and indices.shape == (3, 3) and alpha.max() == 11.0


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_any_truncation_or_byte_corruption_gives_map_file_error_or_the_map(tmp_path_factory, data):
    """Cut anywhere, or with bytes overwritten: either MapFileError or exactly the saved map."""
    folder = tmp_path_factory.mktemp("corrupt")
    good = _saved_map(folder)
    blob = bytearray(good.read_bytes())
    if data.draw(st.booleans(), label="truncate"):
        blob = blob[: data.draw(st.integers(0, len(blob) - 1), label="length")]
    else:
        for _ in range(data.draw(st.integers(1, 8), label="edits")):
            at = data.draw(st.integers(0, len(blob) - 1), label="at")
            blob[at] = data.draw(st.integers(0, 255), label="byte")
    bad = folder / "bad.npz"
    bad.write_bytes(bytes(blob))
    try:
        metadata, indices, alpha = read_map(bad)
    except MapFileError as error:
        assert str(error).startswith(f"{bad}: ")
        return
    # A change the zip checksums do not cover (e.g. in a header's padding) may still load: then it is the map.
    _, good_indices, good_alpha = read_map(good)
    np.testing.assert_array_equal(indices, good_indices)
    np.testing.assert_array_equal(alpha, good_alpha)
    assert metadata["num_classes"] == 4

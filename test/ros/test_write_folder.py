"""Where the node may write (convbki_ros.files.folder), in one process: the folder fixed at start,
what a request may name in it, the kinds of files it may replace, the modes of what it writes,
the maps it keeps, and the segment files' bound. (Over DDS, from other processes:
test_hostile.py.)"""

import os
import stat

import numpy as np
import pytest

from convbki_core.io import atomic
from convbki_core.io.map_file import MapSnapshot, map_file_voxels
from convbki_core.io.ply import is_own_ply, write_voxels_ply
from convbki_ros.files.folder import NEW_FILE_MODE, FileKind, WriteFolder, kept_maps
from convbki_ros.files.map_files import MAX_SEGMENTS, next_segment_path, segment_number


def snapshot(voxels: int) -> MapSnapshot:
    indices = np.arange(3 * voxels, dtype=np.int64).reshape(voxels, 3)
    alpha = np.full((voxels, 4), 1e-3, np.float32)
    alpha[:, 1] = 2.0
    metadata = {"format": "convbki_map", "resolution": 0.2, "num_classes": 4, "prior": 1e-3, "frame_id": "map"}
    return MapSnapshot(metadata, indices, alpha)


class Voxels:
    def __init__(self, count: int):
        self.centres = np.zeros((count, 3), np.float32)
        self.label = np.ones(count, np.int64)
        self.variance = np.zeros(count, np.float32)

    def __len__(self) -> int:
        return len(self.label)


@pytest.fixture
def area(tmp_path):
    """A folder the node writes in (maps/ below it), and beside it a victim outside it."""
    root = tmp_path / "robot"
    (root / "maps").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim").write_bytes(b"keep me\n")
    (root / "notes.txt").write_bytes(b"a user's notes\n")
    (root / "escape").symlink_to(outside, target_is_directory=True)
    (root / "maps" / "link.npz").symlink_to(outside / "victim")
    snapshot(3).write(root / "maps" / "map.npz")
    write_voxels_ply(Voxels(2), root / "maps" / "map.ply")
    return root, outside


def test_the_folder_is_fixed_at_start_and_holds_the_start_files(tmp_path, area):
    root, _ = area
    folder, problem = WriteFolder.at_start("", str(root / "maps" / "map.npz"), "")
    assert problem is None and folder.root == str(root / "maps")  # map_file's folder by default
    folder, problem = WriteFolder.at_start("", "", str(root / "shown.ply"))
    assert problem is None and folder.root == str(root)  # else ply_file's
    assert WriteFolder.at_start("", "", "")[0].root is None  # neither: nothing written on request
    folder, problem = WriteFolder.at_start(str(root / "maps"), str(root / "maps" / "map.npz"), str(root / "x.ply"))
    assert folder.root is None and "ply_file" in problem and "outside the folder" in problem
    made = tmp_path / "new" / "folder"
    folder, problem = WriteFolder.at_start(str(made), "", "")  # at start only, a missing map_folder is made
    assert problem is None and made.is_dir() and stat.S_IMODE(made.stat().st_mode) == 0o700
    linked = tmp_path / "linked"
    linked.symlink_to(root, target_is_directory=True)
    assert WriteFolder.at_start(str(linked), "", "")[0].root == str(root)  # resolved once, at start


def test_a_request_may_name_only_the_nodes_own_kind_of_file_in_the_folder(area):
    root, outside = area
    folder = WriteFolder(str(root))
    maps = root / "maps"
    allowed = [(maps / "map.npz", FileKind.MAP), (maps / "new.npz", FileKind.MAP), (maps / "map.ply", FileKind.PLY),
               (root / "other.ply", FileKind.PLY)]
    for path, kind in allowed:
        assert folder.problem(str(path), kind) is None, path
    refused = {str(outside / "victim"): "outside the folder", str(root / "escape" / "victim"): "outside the folder",
               str(root / ".." / "outside" / "victim"): "outside the folder", str(root / "notes.txt"): "not a ConvBKI",
               str(maps / "link.npz"): "is a link", str(maps / "nowhere" / "map.npz"): "does not exist",
               str(maps / "map.ply"): "not a ConvBKI", str(root): "outside the folder",
               str(maps / ("x" * 300 + ".npz")): "not a file name", "map\0.npz": "NUL", "": "no file"}
    for value, why in refused.items():
        problem = folder.problem(value, FileKind.MAP)
        assert problem and any(w in problem for w in why.split("|")), (value, problem)
    assert "not a PLY file of this node" in folder.problem(str(maps / "map.npz"), FileKind.PLY)
    (maps / "map.npz.prev").write_bytes(b"not a map")  # a map file's .prev is replaced too: checked alike
    assert "map.npz.prev exists and is not a ConvBKI map file" in folder.problem(str(maps / "map.npz"), FileKind.MAP)
    assert folder.resolve("sub/x.npz") == str(root / "sub" / "x.npz")
    assert "writes no file on request" in WriteFolder(None).problem(str(maps / "map.npz"), FileKind.MAP)


def test_files_are_told_apart_by_their_headers_without_following_links(area):
    root, _ = area
    maps = root / "maps"
    assert map_file_voxels(maps / "map.npz") == 3 and is_own_ply(maps / "map.ply")
    assert map_file_voxels(maps / "map.ply") is None and not is_own_ply(maps / "map.npz")
    assert map_file_voxels(root / "notes.txt") is None and map_file_voxels(maps / "missing.npz") is None
    (maps / "map_link.npz").symlink_to(maps / "map.npz")
    assert map_file_voxels(maps / "map_link.npz") is None  # a link is never one of the node's files
    np.savez(maps / "other.npz", metadata=np.frombuffer(b'{"format": "other"}', np.uint8),
             voxel_index=np.zeros((1, 3), np.int32))
    assert map_file_voxels(maps / "other.npz") is None


def test_new_files_are_private_and_a_replaced_file_and_its_prev_keep_their_mode(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    snapshot(2).write(path, new_mode=NEW_FILE_MODE)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    os.chmod(path, 0o640)
    snapshot(3).write(path, new_mode=NEW_FILE_MODE)
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert stat.S_IMODE(atomic.previous_path(path).stat().st_mode) == 0o640  # a hard link

    def no_hard_links(*args, **kwargs):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(atomic.os, "link", no_hard_links)  # a file system without hard links: .prev is a copy
    os.chmod(path, 0o600)
    snapshot(4).write(path, new_mode=NEW_FILE_MODE)
    previous = atomic.previous_path(path)
    assert map_file_voxels(previous) == 3 and stat.S_IMODE(previous.stat().st_mode) == 0o600


def test_kept_maps_and_segment_files_are_found_and_bounded(tmp_path):
    path = tmp_path / "map.npz"
    for name in ("map.npz.kept-20261207T100000Z", "map.npz.kept-20261207T090000Z", "map.npz.kept-x/"):
        (tmp_path / name.rstrip("/")).mkdir() if name.endswith("/") else (tmp_path / name).write_bytes(b"")
    assert [p.name for p in kept_maps(str(path))] == ["map.npz.kept-20261207T090000Z", "map.npz.kept-20261207T100000Z"]
    assert segment_number(str(tmp_path / "map.npz")) == 1 and segment_number(str(tmp_path / "map.segment-7.npz")) == 7
    assert next_segment_path(str(tmp_path / "map.segment-7.npz")) == str(tmp_path / "map.segment-8.npz")
    assert MAX_SEGMENTS == 1000

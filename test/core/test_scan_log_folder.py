"""The scan log on disk: memory keeps the newest scans, the folder the rest; a correction that
reaches into scans read back from the folder equals the map built from scratch; a save names
the folder's files instead of copying them (its ``.prev`` too); the folder's bound freezes the
oldest scans and deletes their files, never those a saved map names; a map whose log files
are gone still loads."""

import gc
import os
import shutil

import numpy as np

from convbki_core import ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.correction.log_folder import is_log_file
from convbki_core.correction.replay import keyframe_corrections
from convbki_core.datasets.drift import read_loop_closure
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import voxel_keys
from convbki_core.io.map_file import read_map

WINDOW = ((-20.0, -20.0, -3.0), (20.0, 20.0, 3.0))  # test_correction's: voxels go through the store
CLOSURE = 25


def sorted_items(mapper):
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T[::-1])
    return indices[order], alpha[order]


def log_files(folder):
    return sorted(name for name in os.listdir(folder) if is_log_file(name))


def map_drive(mapper, dataset, poses, count, stamps, first=0):
    for k in range(first, count):
        frame = dataset[k]
        mapper.integrate(frame.points, frame.input_values, poses[k], frame.input_moving, stamp_ns=int(stamps[k]))
    return mapper


def scan_megabytes(dataset) -> float:
    """What one of the drive's scans costs the log, in MB."""
    probe = ConvBKIMapper(MapperConfig().replace(device="cpu", local_bounds=WINDOW))
    frame = dataset[0]
    probe.integrate(frame.points, frame.input_values, np.eye(4), frame.input_moving)
    return probe.scan_log.disk_bytes / 1e6 or probe.scan_log.nbytes / 1e6


def test_a_correction_reaching_into_scans_on_disk_equals_the_map_from_scratch(drift_drive, tmp_path):
    dataset = SemanticKittiSequence(drift_drive, "00")
    closure = read_loop_closure(dataset)
    robot = closure.robot_poses()
    # Memory for 12 scans: a segment every 3, the older ones only in the folder.
    config = MapperConfig().replace(device="cpu", local_bounds=WINDOW, scan_log_megabytes=12 * scan_megabytes(dataset))
    live = ConvBKIMapper(config)
    live.use_log_folder(tmp_path / "log")
    map_drive(live, dataset, robot, CLOSURE, closure.stamps_ns)
    log = live.scan_log
    log.folder.flush()
    segments = log.segments()
    assert log.first_index == 0 and len(log) == CLOSURE and len(segments) >= 6
    assert not segments[0].resident and not segments[1].base.in_memory  # read back from the folder when needed
    assert log.nbytes <= log.max_bytes + segments[-1].nbytes
    assert log.disk_bytes >= sum(scan.data.size for _, scan in log.scans())
    written = sum(os.path.getsize(tmp_path / "log" / name) for name in log_files(tmp_path / "log"))
    assert written >= log.disk_bytes - 450 * len(log)

    wanted = keyframe_corrections(log.scans(), closure.stamps_ns[closure.keyframes], closure.truth[closure.keyframes])
    assert min(wanted) < segments[1].first_index  # the correction begins in a segment memory let go
    fixed, result = live.corrected(wanted)
    assert result.scans > 0 and result.replayed == CLOSURE - live.scan_log.segment_for(min(wanted)).first_index
    poses = [wanted.get(k, robot[k]) for k in range(CLOSURE)]
    scratch = map_drive(ConvBKIMapper(config), dataset, poses, CLOSURE, closure.stamps_ns)
    got, want = sorted_items(fixed), sorted_items(scratch)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])  # every concentration, bit for bit
    # The corrected log shares the scans' files (nothing written twice) and has bases of its own.
    assert {scan.data.place[1] for _, scan in fixed.scan_log.scans()} <= set(log_files(tmp_path / "log"))
    live.scan_log.replace_from(0, fixed.scan_log.segments())

    # A save names the folder's files: the map file holds no scan bytes, and its .prev names the same.
    path = tmp_path / "map.npz"
    live.save(path)
    live.save(path)
    bare = live.snapshot()
    bare.scan_log = None
    bare.write(tmp_path / "bare.npz")
    log_in_file = os.path.getsize(path) - os.path.getsize(tmp_path / "bare.npz")
    assert 0 < log_in_file < live.scan_log.disk_bytes / 20 and os.path.exists(f"{path}.prev")
    for saved in (path, f"{path}.prev"):
        metadata, _, _ = read_map(saved, with_scan_log=True)
        again = metadata["scan_log"]
        assert [(i, s.stamp_ns, s.points_data, s.values_data) for i, s in again.scans()] == \
            [(i, s.stamp_ns, s.points_data, s.values_data) for i, s in live.scan_log.scans()]

    # A restart: the folder closed; a new mapper on it keeps the files the map files name, loads
    # the map with its log and corrects it again, exactly.
    named = live.scan_log.file_names(live.scan_log.folder)
    live.scan_log.folder.close()
    assert set(log_files(tmp_path / "log")) == named
    loaded = ConvBKIMapper(config)
    loaded.use_log_folder(tmp_path / "log", keep_named_by=[path, f"{path}.prev"])
    loaded.load(path)
    assert len(loaded.scan_log) == CLOSURE and loaded.scan_log.frozen == 0
    truth = {k: closure.truth[k] @ np.linalg.inv(closure.truth[0]) @ poses[0] for k in range(CLOSURE)}
    again, _ = loaded.corrected(truth)
    once_more = map_drive(ConvBKIMapper(config), dataset, [truth[k] for k in range(CLOSURE)], CLOSURE,
                          closure.stamps_ns)
    np.testing.assert_array_equal(sorted_items(again)[1], sorted_items(once_more)[1])
    assert len(log_files(tmp_path / "log")) > len(named)  # the new bases of its correction

    # Reset: the log lets its files go; those the saved maps name stay.
    loaded.reset()
    del fixed, again
    gc.collect()  # the corrections' mappers (reference cycles): their logs held files
    loaded.scan_log.folder.close()  # (the chunk file being appended stays until then)
    assert set(log_files(tmp_path / "log")) == named
    # A map whose log files are gone still loads: its log begins at the map, saying why.
    shutil.rmtree(tmp_path / "log")
    fresh = ConvBKIMapper(config)
    fresh.load(path)
    assert len(fresh) > 0 and len(fresh.scan_log) == 0 and "files of its scan log are gone" in \
        fresh.scan_log.frozen_why


def test_the_folders_bound_freezes_the_oldest_scans_and_deletes_their_files(drift_drive, tmp_path):
    dataset = SemanticKittiSequence(drift_drive, "00")
    closure = read_loop_closure(dataset)
    scan_mb = scan_megabytes(dataset)
    # Memory for 8 scans: a segment every 2.
    config = MapperConfig().replace(device="cpu", local_bounds=WINDOW, scan_log_megabytes=8 * scan_mb)
    mapper = ConvBKIMapper(config)
    mapper.use_log_folder(tmp_path / "log")
    saved_after = 8
    map_drive(mapper, dataset, closure.robot_poses(), saved_after, closure.stamps_ns)
    mapper.save(tmp_path / "map.npz")
    saved = mapper.scan_log.file_names(mapper.scan_log.folder)
    # The folder's bound from here on: about four of its segments (a segment's base, the whole map
    # of this small drive, takes as much as dozens of its 16-beam scans).
    mapper.scan_log.folder.flush()
    mapper.scan_log.folder.max_bytes = int(4.5 * max(s.disk_bytes for s in mapper.scan_log.segments()))
    map_drive(mapper, dataset, closure.robot_poses(), CLOSURE, closure.stamps_ns, first=saved_after)
    log = mapper.scan_log
    log.folder.flush()
    log.trim()  # (each scan logged checks the bound; the writer has caught up since the last)
    log.folder.remove_unheld()
    assert log.frozen > 0 and len(log) > 0 and log.first_index == log.frozen and "fell out" in log.frozen_why
    assert log.disk_bytes <= log.folder.max_bytes
    on_disk = set(log_files(tmp_path / "log"))
    assert on_disk == log.file_names(log.folder) | saved  # nothing else is left behind
    # The saved map still reads its whole log, though the live log let those scans go.
    metadata, _, _ = read_map(tmp_path / "map.npz", with_scan_log=True)
    assert len(metadata["scan_log"]) == saved_after and metadata["scan_log"].scans()[0][1].points().shape[1] == 3


def test_a_base_is_built_by_the_writer_and_one_at_most_waits_for_it(drift_drive, tmp_path):
    dataset = SemanticKittiSequence(drift_drive, "00")
    robot = read_loop_closure(dataset).robot_poses()
    # Memory for 4 scans: a segment would begin after every scan.
    config = MapperConfig().replace(device="cpu", local_bounds=WINDOW, scan_log_megabytes=4 * scan_megabytes(dataset))
    live = ConvBKIMapper(config)
    live.use_log_folder(tmp_path / "log")
    folder = live.scan_log.folder
    handed = []
    folder._submit = handed.append  # the writer is held back: nothing is written until the test says
    map_drive(live, dataset, robot, 6, np.arange(6) * 100_000_000)
    segments = live.scan_log.segments()
    # The base taken after the first scan waits unbuilt (the window's voxels only); the segment
    # it begins grows meanwhile instead of queueing more bases.
    assert [len(s.scans) for s in segments] == [1, 5]
    waiting = segments[1].base
    assert not waiting.built and waiting.place is None and folder.backlog_bytes > 0
    assert waiting.memory_bytes >= 12 * len(waiting._window[0])  # counted against the log's memory bound
    del folder._submit
    for task in handed:
        folder._submit(task)
    folder.flush()
    assert waiting.built and waiting.place is not None and folder.backlog_bytes == 0
    map_drive(live, dataset, robot, 7, np.arange(7) * 100_000_000, first=6)
    assert [len(s.scans) for s in live.scan_log.segments()] == [1, 6, 0]  # the next segment begins at once
    # The base the writer built is the map after the first scan: a replay from it gives the live map.
    fixed, _ = live.corrected({k: robot[k] for k in range(1, 7)}, tolerance=-1.0)
    got, want = sorted_items(fixed), sorted_items(live)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_a_corrections_map_keeps_no_changes_of_voxels_it_mapped_again(drift_drive, tmp_path):
    dataset = SemanticKittiSequence(drift_drive, "00")
    closure = read_loop_closure(dataset)
    robot = closure.robot_poses()
    config = MapperConfig().replace(device="cpu", local_bounds=WINDOW, track_changes=True)
    live = map_drive(ConvBKIMapper(config), dataset, robot, CLOSURE, closure.stamps_ns)
    assert live.window._evicted_changes  # the live map keeps them until its changes are taken
    wanted = keyframe_corrections(live.scan_log.scans(), closure.stamps_ns[closure.keyframes],
                                  closure.truth[closure.keyframes])
    fixed, result = live.corrected(wanted)
    # The new map's next changes are all of it: what left its window while it mapped again is not
    # kept besides (on a long drive that was about 100 bytes a voxel, growing with every scan).
    assert result.replayed > 10 and fixed.window._evicted_changes == []
    changes = fixed.take_changes()
    indices, _ = fixed.items()
    assert len(changes.indices) == len(indices) > 0
    # The keys of a map's voxels without their concentrations (what a replaced map hands over).
    np.testing.assert_array_equal(np.sort(fixed.voxel_keys()), np.sort(voxel_keys(indices)))

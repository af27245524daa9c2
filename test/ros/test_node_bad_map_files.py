"""The mapper node meeting a bad map_file at start, in separate processes.

A file that is not a map is refused before the mapper loads (refuse_bad_map_file), or else the
node starts empty and its first save moves the file to a name of its own, never over one set
aside before (and removes the temporary files that killed saves left). A map of another
set-up stops the start, naming what differs; with map_file_mismatch set_aside, mistaken
restarts lose no map.
"""

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
from mapper_rig import WAIT, Rig, expect_file_holds, offline_map
from ros_helpers import IMPORT_LOG, domain_id, split_import_log, start

from convbki_core.io.atomic import writer_tag

SET_ASIDE_NAME = r"\d{8}T\d{6}Z(?:-\d+)?"  # <map_file>.<why>-<UTC time>[-N]


def start_refused(*parameters: str) -> subprocess.Popen:
    """A node started with ``parameters`` that must refuse to start (``refused`` reads how): it
    runs beside a test's other nodes, as it needs no map file but its own."""
    return start("convbki_ros.main", domain_id(), "--ros-args", "-p", "device:=cpu", *parameters, env=IMPORT_LOG)


def refused(process: subprocess.Popen):
    """(exit code, output, the modules imported before the error line) of a ``start_refused``."""
    try:
        code = process.wait(timeout=60)
        output, imported = split_import_log(process.communicate()[0])
    finally:
        if process.poll() is None:
            process.kill()
    return code, output, imported


def test_bad_map_files_met_in_three_starts_are_each_set_aside_under_a_name_of_their_own(tmp_path):
    good = tmp_path / "good.npz"
    offline_map(1).save(good)
    folder = tmp_path / "robot"
    map_file = folder / "maps" / "map.npz"
    map_file.parent.mkdir(parents=True)
    random_bytes = np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, points=np.zeros((10, 3)))  # a valid archive, not a map
    bad_files = {"truncated": good.read_bytes()[: good.stat().st_size // 2], "random bytes": random_bytes,
                 "foreign": foreign.read_bytes()}

    # Refusing (refuse_bad_map_file): exit 2 naming the file and the problem, before the mapper is
    # loaded (Python's import log before the error line), and the file as it was. A file of its
    # own, so that this start runs while the first of the starts below comes up.
    refused_file = tmp_path / "refused" / "map.npz"
    refused_file.parent.mkdir()
    refused_file.write_bytes(bad_files["foreign"])
    refusing = start_refused("-p", f"map_file:={refused_file}", "-p", "refuse_bad_map_file:=true")

    # Not refusing, three starts, each meeting another bad file: each start says so, starts empty,
    # and its first save moves the bad file to a name of its own (said in the log), never over
    # the one set aside before.
    # What saves killed by an earlier run left (removed at start: this node's own kind of temporary
    # file, of processes that are gone) and what is not theirs (kept).
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    killed_saves = [map_file.parent / f".map.npz.{writer_tag(dead.pid)}.x1.tmp",
                    map_file.parent / f".map.npz.prev.{writer_tag(dead.pid)}.x2.tmp"]
    not_theirs = [map_file.parent / f".other.npz.{writer_tag(dead.pid)}.x3.tmp",  # another file's
                  map_file.parent / f".map.npz.{writer_tag(os.getpid())}.x4.tmp",  # a live process's
                  map_file.parent / f".map.npz.{dead.pid}.0badc0de.x5.tmp",  # another host's (NFS)
                  map_file.parent / "map.npz.tmp"]  # the user's
    for path in killed_saves + not_theirs:
        path.write_bytes(b"\0" * 1000)
    set_aside: dict[str, Path] = {}
    for kind, content in bad_files.items():
        map_file.write_bytes(content)
        rig = Rig(folder, map_file=map_file, diagnostics_period=0.05)
        try:
            if refusing is not None:
                code, output, imported = refused(refusing)
                refusing = None
                assert code == 2, output
                assert "torch" not in imported, "the unreadable map file was refused only after the mapper was loaded"
                assert re.search(rf"mapper: error: {re.escape(str(refused_file))}: not a ConvBKI map file .*"
                                 r"\(refuse_bad_map_file is true: not starting\)", output), output
                assert "Traceback" not in output and refused_file.read_bytes() == bad_files["foreign"]
            if kind == "truncated":
                names = ", ".join(path.name for path in killed_saves)
                assert rig.log.find(r"\[INFO\].*removed 2 temporary file\(s\) of killed saves beside map_file "
                                    rf"\(0\.0 MB\): {re.escape(names)}"), rig.log.text()
                assert not any(path.exists() for path in killed_saves) and all(path.exists() for path in not_theirs)
            assert re.search(rf"\[ERROR\].*{re.escape(str(map_file))}: not a (readable )?ConvBKI map file.*starting "
                             rf"with an EMPTY map.*the first save moves it to {re.escape(str(map_file))}\.unreadable-"
                             r"<UTC time>", rig.log.text()), rig.log.text()
            assert rig.stats().voxels == 0
            if kind == "truncated":  # one start maps too: SIGTERM then saves what changed since the save
                rig.integrate_good_cloud()
            saved = rig.call("save_map")
            assert saved.success, saved.message
            moved = rig.wait_log(rf"\[WARN\].*moved the unreadable map file {re.escape(str(map_file))} to "
                                 rf"({re.escape(str(map_file))}\.unreadable-{SET_ASIDE_NAME})$", 0)
            set_aside[kind] = Path(moved[0].group(1))
            if kind == "truncated":
                final = rig.integrate_good_cloud()
                rig.process.send_signal(signal.SIGTERM)
            else:
                rig.process.send_signal(signal.SIGINT)
            assert rig.process.wait(timeout=WAIT) == 0
        finally:
            output = rig.close()
        assert "Traceback" not in output, output
        if kind == "truncated":
            assert f"on shutdown: saved {final.voxels} voxels to {map_file} (the file before kept as map.npz.prev)" \
                in output, output
            expect_file_holds(map_file, offline_map(2))
    assert len(set(set_aside.values())) == 3
    for kind, content in bad_files.items():
        assert set_aside[kind].read_bytes() == content, kind


def test_a_map_of_another_set_up_stops_the_start_and_two_mistaken_restarts_lose_no_map(tmp_path):
    """A valid 0.2 m map, a start with resolution 0.4 by mistake, then the defaults again: each
    mistaken start is refused with what differs, and with map_file_mismatch set_aside neither
    the 0.2 m map nor the 0.4 m map made meanwhile is lost."""
    folder = tmp_path / "robot"
    map_file = folder / "maps" / "map.npz"
    map_file.parent.mkdir(parents=True)
    one_scan = offline_map(1)
    one_scan.save(map_file)
    fine_map = map_file.read_bytes()

    # Each refused start runs while the set_aside start after it comes up: that one leaves the file
    # alone until it saves (at Ctrl-C, once the refused start has ended).
    # The mistake: refused at once, naming what differs and the two ways out; the map as it was.
    refusing = start_refused("-p", f"map_file:={map_file}", "-p", "resolution:=0.4")
    kept = []
    for parameters in (("-p", "resolution:=0.4"), ()):
        rig = Rig(folder, *parameters, "-p", "map_file_mismatch:=set_aside", map_file=map_file,
                  diagnostics_period=0.05)
        try:
            code, output, imported = refused(refusing)
            if parameters:
                assert code == 2 and "torch" not in imported, output
                assert re.search(rf"mapper: error: map_file {re.escape(str(map_file))} holds a map of another "
                                 r"set-up \(resolution 0\.2 m in the file, 0\.4 m here\); to load it, start with -p "
                                 r"resolution:=0\.2; to start a new map, set map_file to another file \(or "
                                 r"map_file_mismatch:=set_aside", output), output
                assert output.count("mapper: error:") == 1 and "Traceback" not in output
                assert map_file.read_bytes() == fine_map
            else:  # the defaults again, before the user notices the parameter: refused too, the file now 0.4 m
                assert code == 2 and "(resolution 0.4 m in the file, 0.2 m here); to load it, start with -p " \
                    "resolution:=0.4" in output, output
            assert re.search(r"\[ERROR\].*holds a map of another set-up \(resolution 0\.[24] m in the file, "
                             r"0\.[24] m here\); starting with an EMPTY map \(map_file_mismatch is set_aside\)",
                             rig.log.text()), rig.log.text()
            assert rig.stats().voxels == 0
            rig.integrate_good_cloud()
            rig.process.send_signal(signal.SIGINT)  # saves on shutdown: the file is moved aside first
            assert rig.process.wait(timeout=WAIT) == 0
        finally:
            output = rig.close()
        moved = re.search(rf"\[WARN\].*moved the map file of another set-up {re.escape(str(map_file))} to "
                          rf"({re.escape(str(map_file))}\.other-setup-{SET_ASIDE_NAME})\n", output)
        assert moved, output
        kept.append(Path(moved.group(1)))
        if not parameters:
            break
        coarse_map = map_file.read_bytes()
        refusing = start_refused("-p", f"map_file:={map_file}")
    # Both maps are in the folder, byte for byte, where the lines said; map_file holds the new 0.2 m map.
    assert kept[0] != kept[1]
    assert kept[0].read_bytes() == fine_map and kept[1].read_bytes() == coarse_map
    expect_file_holds(map_file, one_scan)
    assert sorted(path.name for path in map_file.parent.iterdir()) == \
        sorted(["map.npz", "map.npz.scan_log", *(p.name for p in kept)])

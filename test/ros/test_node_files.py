"""Nothing a user saved is lost, and the services steer the node's files: a reset followed by
Ctrl-C keeps the saved map byte for byte; ``~/load_map``, ``~/clear_box`` and a run-time
``map_file`` each show in the published map; a late subscriber never first gets a stale map;
``map_file`` in a missing, a read-only and a full folder is answered at start, while mapping
and at shutdown (exit code), and the old file stays byte for byte. Real processes over DDS."""

import os
import re
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mapper_rig import BOUNDS, TRANSLATION, WAIT, Rig, close_together, expect_file_holds, offline_map
from ros_helpers import IMPORT_LOG, NodeLog, domain_id, split_import_log, start

from convbki_core.config import MapperConfig
from convbki_core.mapper import ConvBKIMapper
from convbki_core.paths import kernel_path

WITHOUT_PERMISSION_OVERRIDE = ("setpriv", "--bounding-set", "-dac_override,-dac_read_search") \
    if os.geteuid() == 0 and shutil.which("setpriv") else ()
NEEDS_READ_ONLY = pytest.mark.skipif(os.geteuid() == 0 and not WITHOUT_PERMISSION_OVERRIDE,
                                     reason="root writes into read-only folders, and setpriv is not here to stop that")


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The nodes of three tests below, started side by side (each test takes its own): "reset"
    (nobody watches its map), "new folder" (its map_file in a folder that does not exist yet) and
    "refusing writes" (a saved map in a folder that the test makes read-only under it)."""
    new_folder, refusing_writes = tmp_path_factory.mktemp("new_folder"), tmp_path_factory.mktemp("refusing_writes")
    saved = refusing_writes / "maps" / "map.npz"
    saved.parent.mkdir()
    offline_map(1).save(saved)
    rigs = {"reset": Rig(tmp_path_factory.mktemp("reset"), watch_map=False, diagnostics_period=0.05, wait=False),
            "new folder": Rig(new_folder, map_file=new_folder / "new" / "maps" / "map.npz", diagnostics_period=0.05,
                              wait=False),
            "refusing writes": Rig(refusing_writes, map_file=saved, prefix=WITHOUT_PERMISSION_OVERRIDE,
                                   diagnostics_period=0.05, wait=False)}
    yield rigs
    close_together(*rigs.values())


def shown_voxels(mapper: ConvBKIMapper):
    """Centres of the voxels the node publishes (expected class other than 0, free space)."""
    voxels = mapper.voxels()
    return voxels.centres[voxels.label != 0]


def first_map_of_a_late_subscriber(rig: Rig):
    """The first /semantic_map a subscriber that arrives now receives (the latched sample): a
    reader made now in the rig's probe (whose participant DDS knows already), removed after, so
    that nobody listens again."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    received: list = []
    late = rig.probe.node.create_subscription(PointCloud2, "/semantic_map", received.append, QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    try:
        assert rig.probe.spin_until(lambda: received, WAIT), "a late subscriber got no map"
        return received[0]
    finally:
        rig.probe.node.destroy_subscription(late)


def points_of(msg) -> np.ndarray:
    data = np.frombuffer(bytes(msg.data), np.float32).reshape(msg.width, msg.point_step // 4)
    return data[:, :3]


def test_reset_then_ctrl_c_keeps_the_saved_map_and_late_subscribers_get_the_current_map(nodes):
    shown = len(shown_voxels(offline_map(1)))
    rig = nodes["reset"].wait_ready()
    try:
        stats = rig.integrate_good_cloud()
        saved = rig.call("save_map")
        assert saved.success, saved.message
        before = rig.map_file.read_bytes()
        assert first_map_of_a_late_subscriber(rig).width == shown
        # Nobody listens now. A reset says what it forgot and that the saved file is kept.
        published = rig.stats().maps_published
        reset = rig.call("reset")
        assert reset.success and reset.message == f"map reset: forgot {stats.voxels} voxels; {rig.map_file} keeps " \
            "the map as it was until ~/save_map writes this one there", reset.message
        rig.wait_stats(lambda s: s.voxels == 0 and s.maps_published > published)
        assert first_map_of_a_late_subscriber(rig).width == 0  # the map as it is, not as it was

        # The map grows while nobody listens: the latched map follows it.
        published = rig.stats().maps_published
        after = rig.integrate_good_cloud()
        rig.wait_stats(lambda s: s.maps_published > published)
        assert first_map_of_a_late_subscriber(rig).width == shown
        # A filter that hides every voxel, set while nobody listens: a late subscriber gets it applied.
        published = rig.stats().maps_published
        assert rig.set_parameters(max_variance=1e-9)[0].successful
        rig.wait_stats(lambda s: s.maps_published > published)
        assert first_map_of_a_late_subscriber(rig).width == 0
        assert rig.set_parameters(max_variance=0.0)[0].successful

        # This map is not saved by itself, and /diagnostics says so.
        unsaved = rig.wait_stats(lambda s: s.level == 1 and "not saved automatically" in s.message)
        assert "(~/reset)" in unsaved.message, unsaved
        rig.process.send_signal(signal.SIGINT)
        assert rig.process.wait(timeout=WAIT) == 0
    finally:
        output = rig.close()
    assert after.voxels > 0
    assert re.search(rf"on shutdown: kept {re.escape(str(rig.map_file))} as it is: it holds evidence this map no "
                     r"longer has \(~/reset\); call ~/save_map to write this map there", output), output
    assert rig.map_file.read_bytes() == before
    assert not Path(f"{rig.map_file}.prev").exists()


def test_load_map_clear_box_and_a_run_time_map_file_show_in_the_published_map(tmp_path):
    from sensor_msgs.msg import PointCloud2

    start_file = tmp_path / "maps" / "map.npz"
    start_file.parent.mkdir()
    original = offline_map(2)
    original.save(start_file)
    other_resolution = tmp_path / "coarse.npz"
    ConvBKIMapper(MapperConfig.paper(local_bounds=(BOUNDS[:3], BOUNDS[3:]), resolution=0.4, device="cpu"),
                  kernel_path("semantic_kitti_compound")).save(other_resolution)
    read_only = tmp_path / "read_only"
    read_only.mkdir(mode=0o555)
    rig = Rig(tmp_path, map_file=start_file, prefix=WITHOUT_PERMISSION_OVERRIDE, diagnostics_period=0.05)
    try:
        assert rig.log.find(rf"loaded {len(original)} voxels from {re.escape(str(start_file))}")
        # Before any odometry, the view shows the loaded map around the sensor position the file recorded.
        views = rig.probe.subscribe(PointCloud2, "/semantic_map/view", latched=True)
        shown = shown_voxels(original)
        near = np.hypot(*(shown[:, :2] - TRANSLATION[:2]).T) <= 30.0
        assert rig.probe.spin_until(lambda: views and views[-1].width == int(near.sum()), WAIT), \
            (views[-1].width if views else None, int(near.sum()))
        assert rig.stats().odometry_in == 0

        # ~/clear_box forgets the voxels whose centres lie in the box, in the published map too.
        box_min, box_max = [2.0, 0.0, -5.0], [7.0, 3.0, 5.0]
        assert all(result.successful for result in rig.set_parameters(clear_box_min=box_min, clear_box_max=box_max))
        centres = original.voxels().centres
        inside = ((centres >= box_min) & (centres <= box_max)).all(axis=1)
        assert 0 < inside.sum() < len(centres)
        cleared = rig.call("clear_box")
        assert cleared.success and cleared.message.startswith(
            f"forgot {int(inside.sum())} voxels in the box {box_min} .. {box_max} (frame 'map')"), cleared.message
        remaining = shown[~((shown >= box_min) & (shown <= box_max)).all(axis=1)]
        cleared_map = rig.map_message(len(remaining))
        assert not ((points_of(cleared_map) >= box_min) & (points_of(cleared_map) <= box_max)).all(axis=1).any()
        refused = rig.set_parameters(clear_box_min=[1.0, 2.0])[0]
        assert not refused.successful and "needs 3 finite numbers" in refused.reason

        # map_file at run time: a folder that does not exist is refused (no request makes one); once it
        # exists in map_folder, map_file takes it and ~/save_map writes there.
        new_file = tmp_path / "elsewhere" / "new.npz"
        refused = rig.set_parameters(map_file=str(new_file))[0]
        assert not refused.successful and "is in a folder that does not exist" in refused.reason, refused
        assert not new_file.parent.exists()
        new_file.parent.mkdir()
        assert rig.set_parameters(map_file=str(new_file))[0].successful
        saved = rig.call("save_map")
        assert saved.success and saved.message == f"saved {len(original) - int(inside.sum())} voxels to {new_file}"
        expected = offline_map(2)
        expected.forget_box(box_min, box_max)
        expect_file_holds(new_file, expected)
        if WITHOUT_PERMISSION_OVERRIDE or os.geteuid() != 0:  # a folder that cannot be written is refused
            refused = rig.set_parameters(map_file=str(read_only / "map.npz"))[0]
            assert not refused.successful and refused.reason == (
                f"map_file {read_only / 'map.npz'}: its folder {read_only} cannot be written (Permission denied)")
            assert rig.parameter("map_file") == str(new_file)

        # ~/load_map replaces the map with map_file's; a file of another grid is refused, the map kept.
        assert rig.set_parameters(map_file=str(other_resolution))[0].successful
        refused = rig.call("load_map")
        assert not refused.success and "map resolution 0.4 m differs from the mapper's 0.2 m" in refused.message \
            and refused.message.endswith("; the map is unchanged"), refused.message
        assert rig.stats().voxels == len(original) - int(inside.sum())
        assert rig.set_parameters(map_file=str(start_file))[0].successful
        loaded = rig.call("load_map")
        assert loaded.success and loaded.message == (f"loaded {len(original)} voxels from {start_file} (replacing "
                                                     f"{len(original) - int(inside.sum())})"), loaded.message
        reloaded = rig.map_message(len(shown))
        assert len(points_of(reloaded)) == len(shown)
        rig.process.send_signal(signal.SIGINT)
        assert rig.process.wait(timeout=WAIT) == 0
    finally:
        read_only.chmod(0o755)
        output = rig.close()
    assert f"on shutdown: the map is unchanged since it was last saved to (or loaded from) {start_file}" in output
    expect_file_holds(start_file, original)
    assert "Traceback" not in output, output


# ----------------------------------------------------------------------------- map_file's folder


def start_node(domain: int, map_file: Path, *parameters: str, env: dict | None = None) -> subprocess.Popen:
    return start("convbki_ros.main", domain, "--ros-args", "-p", "device:=cpu", "-p", f"local_bounds:={BOUNDS}",
                 "-p", f"map_file:={map_file}", *parameters, prefix=WITHOUT_PERMISSION_OVERRIDE, env=env)


def test_a_map_file_in_a_missing_folder_gets_its_folder_and_the_map(nodes):
    rig = nodes["new folder"].wait_ready()
    map_file = rig.map_file
    try:
        assert rig.log.find(rf"made the folder {re.escape(str(map_file.parent))} for map_file")
        final = rig.integrate_good_cloud()
        rig.process.send_signal(signal.SIGINT)
        assert rig.process.wait(timeout=WAIT) == 0
    finally:
        output = rig.close()
    assert f"on shutdown: saved {final.voxels} voxels to {map_file}" in output, output
    expect_file_holds(map_file, offline_map(1))


@NEEDS_READ_ONLY
def test_a_map_file_in_a_read_only_folder_is_refused_at_start_and_the_file_kept(tmp_path):
    folder = tmp_path / "read_only"
    folder.mkdir()
    offline_map(1).save(folder / "map.npz")
    before = (folder / "map.npz").read_bytes()
    folder.chmod(0o555)
    try:
        # Python's import log (before the error line): the folder is checked before torch is loaded.
        node = start_node(domain_id(), folder / "map.npz", env=IMPORT_LOG)
        # Only reading it (no save by itself) is fine: a warning, and the node starts (beside the other).
        reading = NodeLog(start_node(domain_id(), folder / "map.npz", "-p", "save_on_shutdown:=false"))
        try:
            logged = node.communicate(timeout=120)[0]
            assert reading.wait_for("mapper ready", timeout=60), reading.text()
        finally:
            seen = reading.close()
        assert reading.process.returncode == 0, seen
    finally:
        folder.chmod(0o755)
    output, imported = split_import_log(logged)
    assert node.returncode == 2, output
    assert "torch" not in imported, "the map folder was checked only after the mapper was loaded"
    lines = output.strip().splitlines()
    assert len(lines) == 1 and lines[0] == (
        f"mapper: error: map_file {folder / 'map.npz'}: its folder {folder} cannot be written (Permission denied): "
        "this session's map could not be saved (choose another map_file, or set save_on_shutdown false and "
        "autosave_period 0 to only read it)"), output
    assert f"its folder {folder} cannot be written (Permission denied): ~/save_map will fail" in seen, seen
    assert (folder / "map.npz").read_bytes() == before


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs mounted for the test (root only)."""
    mount_point = tmp_path / "disk"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount_point)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (mounting needs root and CAP_SYS_ADMIN: "
                    f"{mounted.stderr.strip()}); the errors while mapping and at shutdown are still checked "
                    "without a mount, by a folder that refuses writes after the start")
    yield mount_point
    subprocess.run(["umount", "-l", str(mount_point)], check=False)


def fill(disk: Path, leave: int) -> None:
    """Fill ``disk`` until at most ``leave`` bytes are free."""
    free = shutil.disk_usage(disk).free - leave
    with open(disk / "filler", "ab") as filler:
        try:
            filler.write(b"\0" * max(free, 0))
            filler.flush()
            os.fsync(filler.fileno())
        except OSError:
            pass


@NEEDS_READ_ONLY
def test_a_folder_that_refuses_writes_after_the_start_fails_every_save_and_keeps_the_file(nodes):
    """The full disk's errors while mapping and at shutdown, with no mount: the folder passes the
    check at start, then refuses writes (made read-only under the running node): every save
    fails and says why, shutdown exits 1, and the file and the folder stay as they were."""
    rig = nodes["refusing writes"].wait_ready()
    map_file = rig.map_file
    before = map_file.read_bytes()  # as the fixture saved it before the start
    try:
        rig.integrate_good_cloud(translation=TRANSLATION + [6.0, 0.0, 0.0])
        map_file.parent.chmod(0o555)
        failed = rig.call("save_map")
        assert not failed.success and failed.message == f"could not save {map_file}: Permission denied", \
            failed.message
        unsaved = rig.wait_stats(lambda s: s.level == 2)
        assert failed.message in unsaved.message, unsaved
        rig.process.send_signal(signal.SIGINT)
        code = rig.process.wait(timeout=WAIT)
    finally:
        map_file.parent.chmod(0o755)
        output = rig.close()
    assert code == 1, output  # a supervisor learns that this session's map was not saved
    assert f"[convbki_mapper] error on shutdown: could not save {map_file}: Permission denied" in output, output
    assert map_file.read_bytes() == before
    assert sorted(p.name for p in map_file.parent.iterdir()) == ["map.npz", "map.npz.scan_log"]


def test_a_map_file_on_a_full_disk_is_refused_at_start_and_an_error_while_mapping_and_at_shutdown(tmp_path,
                                                                                                  small_disk):
    map_file = small_disk / "map.npz"
    offline_map(1).save(map_file)
    before = map_file.read_bytes()
    fill(small_disk, leave=0)
    node = start_node(domain_id(), map_file)
    output = node.communicate(timeout=120)[0]
    assert node.returncode == 2, output
    assert output.strip() == (f"mapper: error: map_file {map_file}: its folder {small_disk} cannot be written (No "
                              "space left on device): this session's map could not be saved (choose another map_file, "
                              "or set save_on_shutdown false and autosave_period 0 to only read it)"), output

    # Room for the check at start, not for a map: mapping goes on, every save fails and says why.
    (small_disk / "filler").unlink()
    fill(small_disk, leave=64 * 1024)
    rig = Rig(tmp_path, map_file=map_file, diagnostics_period=0.05)
    try:
        assert rig.log.find(r"\[WARN\].*MB free on its disk, less than the .* MB of the map there")
        rig.integrate_good_cloud(translation=TRANSLATION + [6.0, 0.0, 0.0])
        failed = rig.call("save_map")
        assert not failed.success and failed.message == f"could not save {map_file}: No space left on device"
        unsaved = rig.wait_stats(lambda s: s.level == 2)
        assert failed.message in unsaved.message, unsaved
        rig.process.send_signal(signal.SIGINT)
        code = rig.process.wait(timeout=WAIT)
    finally:
        output = rig.close()
    assert code == 1, output  # a supervisor learns that this session's map was not saved
    assert f"[convbki_mapper] error on shutdown: could not save {map_file}: No space left on device" in output, output
    assert map_file.read_bytes() == before
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler", "map.npz"]  # (the empty log folder removed)

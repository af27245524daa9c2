"""The mapper node under bad input, over DDS, in a separate process.

Each bad message is published to a running node; the test then checks the node is alive,
logged one warning naming the problem, counted the message as dropped (or rejected), and
left the map as it was: the node's own counters on /diagnostics (scans integrated, map
voxels, and the map's version, which every change of the map bumps) are equal before and
after, and the latest /semantic_map is byte for byte the one before. Every rig first
integrates a good cloud, so "the map did not change" is a check that can fail. To keep the
time down, one node takes many cases in sequence (a second, started beside it, maps the
partial clouds from an empty map); at the end its map must still save and load. (The reset
options and autosave: test_node_resets.py; bad map files at start:
test_node_bad_map_files.py.)
"""

import array
import os
import re
import resource
import shutil
from pathlib import Path

import numpy as np
import pytest
from mapper_rig import (
    LABELS,
    POINTS,
    SECOND,
    TRANSLATION,
    Rig,
    Stats,
    close_together,
    cloud,
    expect_file_holds,
    fields,
    odometry,
    offline_map,
)

from convbki_core.io.labels import load_label_map
from convbki_ros.inputs.cloud_decoding import decode_cloud

# Root ignores file permissions through two capabilities; a node started without them (still
# uid 0) meets a read-only folder as any user would. Empty when not root or no setpriv.
WITHOUT_PERMISSION_OVERRIDE = ("setpriv", "--bounding-set", "-dac_override,-dac_read_search") \
    if os.geteuid() == 0 and shutil.which("setpriv") else ()


def big_endian_cloud(stamp: int):
    """The good cloud with its bytes in big-endian order, as a big-endian sensor would send it."""
    msg = cloud(stamp)
    layout = np.dtype({"names": ["x", "y", "z", "label"], "formats": [">f4", ">f4", ">f4", ">u4"],
                       "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    swapped = np.zeros(len(POINTS), layout)
    for axis, name in enumerate("xyz"):
        swapped[name] = POINTS[:, axis]
    swapped["label"] = LABELS
    msg.is_bigendian = True
    msg.data = array.array("B", swapped.tobytes())
    return msg


class Baseline:
    """The node's map as it stands: counters, and the /semantic_map message that shows it."""

    def __init__(self, rig: Rig):
        self.rig = rig
        self.stats = rig.stats()
        assert self.stats.integrated > 0 and self.stats.voxels > 0, "the map must hold something to compare"
        # Voxels that rays emptied hold evidence but are not shown: the map holds fewer than map_voxels.
        self.map = bytes(rig.map_message(rig.shown_voxels()).data)

    def expect_untouched(self, now: Stats) -> None:
        assert rig_alive(self.rig)
        assert (now.integrated, now.voxels, now.map_version) == \
            (self.stats.integrated, self.stats.voxels, self.stats.map_version), (self.stats, now)
        assert bytes(self.rig.maps[-1].data) == self.map


def rig_alive(rig: Rig) -> bool:
    return rig.process.poll() is None


def expect_dropped(rig: Rig, baseline: Baseline, messages: list, warning: str, reason: str,
                   copies: int = 2) -> None:
    """Publish ``messages`` (odometry first, then the cloud) ``copies`` times; the node must warn
    once (throttled), count every cloud as dropped for ``reason`` and leave the map alone."""
    before = rig.stats()
    mark = rig.log.mark()
    for _ in range(copies):
        rig.publish(*messages)
    now = rig.wait_stats(lambda s: s.reasons.get(reason, 0) >= before.reasons.get(reason, 0) + copies)
    assert now.reasons.get(reason, 0) == before.reasons.get(reason, 0) + copies, now
    assert now.dropped == before.dropped + copies and now.scans_in == before.scans_in + copies, (before, now)
    assert len(rig.wait_log(r"\[WARN\].*" + warning, mark)) == 1, rig.log.text(mark)
    baseline.expect_untouched(now)


# ----------------------------------------------------------------------------- node A: defaults


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    """The module's two nodes, started side by side: "robust" takes the bad inputs in sequence (a
    cloud waits 0.5 s for its pose and 0.3 s for its TF before it is dropped: the default
    robustness parameters but for these waits, which only the cases that time out sit through),
    "partial" maps the partial clouds from an empty map. Both report every 0.05 s."""
    nodes = {"robust": Rig(tmp_path_factory.mktemp("robust"), "-p", "pose_wait_timeout:=0.5",
                           "-p", "transform_timeout:=0.3", prefix=WITHOUT_PERMISSION_OVERRIDE,
                           diagnostics_period=0.05, wait=False),
             "partial": Rig(tmp_path_factory.mktemp("partial"), diagnostics_period=0.05, wait=False)}
    try:
        yield nodes
    finally:
        outputs = close_together(*nodes.values())
    assert not any("Traceback" in output for output in outputs), outputs


@pytest.fixture(scope="module")
def rig(nodes):
    """The node with the default robustness parameters, holding one good scan."""
    rig = nodes["robust"].wait_ready()
    rig.integrate_good_cloud()
    return rig


def test_malformed_clouds_are_dropped_with_one_warning_each(rig):
    baseline = Baseline(rig)
    count = len(POINTS)

    def case(make, warning: str, reason: str = "bad cloud") -> None:
        stamp = rig.next_stamp()
        expect_dropped(rig, baseline, [odometry(stamp), make(stamp)], warning, reason)

    case(lambda t: cloud(t, **{"x": POINTS[:, 0], "y": POINTS[:, 1], "label": LABELS}),
         r"dropping cloud: cloud has no z field \(fields: x, y, label\)")
    case(lambda t: cloud(t, **{"x": POINTS[:, 0], "y": POINTS[:, 1], "z": POINTS[:, 2],
                               "intensity": POINTS[:, 0]}),
         r"cloud has neither a `label` field nor `prob_0..prob_\{C-1\}` fields")
    case(lambda t: cloud(t, **fields(points=POINTS.astype(np.int16))),
         r"field 'x' has unsupported datatype int16 \(expected float32, float64\)")
    case(lambda t: cloud(t, **fields(labels=LABELS.astype(np.float32))),
         r"field 'label' has unsupported datatype float32")

    def unknown_datatype(stamp):
        msg = cloud(stamp)
        msg.fields[3].datatype = 42
        return msg

    case(unknown_datatype, r"field 'label' has unknown datatype 42")

    def short_data(stamp):
        msg = cloud(stamp)
        msg.data = msg.data[:-100]
        return msg

    # Refused on arrival, before it is queued: a cloud's data must be what its header says.
    case(short_data, rf"its data is {16 * count - 100} bytes, fewer than its header says: height \* row_step = 1 "
                     rf"\* {16 * count}")

    def long_data(stamp):  # a header claiming one point that carries megabytes
        msg = cloud(stamp, **fields(points=POINTS[:1], labels=LABELS[:1]))
        msg.data = bytes(msg.data) + bytes(2_000_000)
        return msg

    case(long_data, r"its data is 2000016 bytes, more than its header says: height \* row_step = 1 \* 16 = 16")

    def step_too_small(stamp):  # x, y, z, label laid out in 16 bytes, point_step claims 12 (and the data agrees)
        msg = cloud(stamp)
        msg.point_step, msg.row_step = 12, 12 * count
        msg.data = msg.data[:12 * count]
        return msg

    case(step_too_small, r"field 'label' \(offset 12, 4 bytes\) does not fit in point_step 12")

    def one_row_without_row_step(stamp):  # refused like a two-row cloud's short row_step (test_cloud_codec)
        msg = cloud(stamp)
        msg.row_step = 0
        return msg

    case(one_row_without_row_step, rf"row_step 0 is smaller than width \* point_step = {count} \* 16")

    def all_non_finite(stamp):
        points = POINTS.copy()
        points[0::2, 0] = np.nan
        points[1::2, 2] = np.inf
        return cloud(stamp, **fields(points=points))

    case(all_non_finite, rf"dropping cloud: no usable point \({count} of {count} points dropped: {count} with "
         r"NaN/inf coordinates\)", "no usable points")

    def probabilities(stamp, bad_row):
        rows = np.tile(bad_row, (count, 1))
        return cloud(stamp, **{"x": POINTS[:, 0], "y": POINTS[:, 1], "z": POINTS[:, 2],
                               **{f"prob_{c}": rows[:, c] for c in range(20)}})

    negative = np.full(20, 0.1, np.float32)
    negative[3] = -0.5
    case(lambda t: probabilities(t, negative), rf"dropping cloud: no usable point \({count} of {count} points "
         rf"dropped: {count} with negative probabilities\)", "no usable points")
    case(lambda t: probabilities(t, np.zeros(20, np.float32)), rf"\({count} of {count} points dropped: {count} "
         r"with probabilities summing to zero\)", "no usable points")
    case(lambda t: cloud(t, **fields(labels=np.full(count, 7777, np.uint32))),
         rf"dropping cloud: all {count} label ids are unknown to the semantic_kitti label map \(e.g. 7777\)",
         "unknown labels")
    case(lambda t: cloud(t, **fields(points=POINTS[:0], labels=LABELS[:0])),
         r"dropping empty cloud stamped [\d.]+ s \(width 0 x height 1\)", "empty")
    # A frame TF has never heard of: it may still come, so the cloud waits transform_timeout.
    case(lambda t: cloud(t, frame="camera"), r"dropping cloud stamped [\d.]+ s in frame 'camera' after waiting "
         r"transform_timeout = 0\.3 s \(no mount\): no mount in TF \(frames 'velo_link' and 'camera' are unknown\); "
         r"publish it on /tf_static or set base_to_sensor", "no mount")
    assert rig_alive(rig)


def test_a_five_million_point_cloud_is_refused_without_exhausting_memory(rig):
    baseline = Baseline(rig)
    count = 5_000_000
    # 16 bytes a point as the node expects them (x, y, z float32, label uint32), built in one
    # go from numpy: 80 MB.
    layout = np.dtype({"names": ["x", "y", "z", "label"], "formats": ["<f4", "<f4", "<f4", "<u4"],
                       "offsets": [0, 4, 8, 12], "itemsize": 16})
    points = np.zeros(count, layout)
    points["x"] = np.linspace(-15.0, 15.0, count, dtype=np.float32)
    points["z"] = -1.6
    points["label"] = 40
    stamp = rig.next_stamp()
    msg = cloud(stamp)
    msg.width, msg.row_step = count, 16 * count
    msg.data = array.array("B", points.tobytes())
    del points
    peak_before = peak_memory_mib(rig.process.pid)
    expect_dropped(rig, baseline, [odometry(stamp), msg], rf"{count} points \(80 MB\), more than "
                   r"max_points_per_cloud = 2000000", "too large", copies=1)
    # DDS reassembles the 80 MB and rclpy copies it into the message (about 320 MB of peak
    # memory here); a cloud turned into Python objects (80 M ints) would cost gigabytes.
    growth = peak_memory_mib(rig.process.pid) - peak_before
    assert growth < 1024, f"the node's peak memory grew by {growth} MiB"


def peak_memory_mib(pid: int) -> int:
    """Peak resident memory of a process so far (VmHWM), MiB."""
    return int(re.search(r"VmHWM:\s+(\d+) kB", Path(f"/proc/{pid}/status").read_text()).group(1)) // 1024


def test_bad_odometry_is_ignored_and_its_clouds_are_not_placed(rig):
    baseline = Baseline(rig)

    def case(warning: str, **bad) -> None:
        # The only odometry at the cloud's stamp is the bad one: had the node used it, the
        # cloud would be integrated; ignored, the cloud times out waiting for a pose.
        before = rig.stats()
        stamp = rig.next_stamp()
        expect_dropped(rig, baseline, [odometry(stamp, **bad), cloud(stamp)], warning, "no pose", copies=1)
        after = rig.stats()
        assert after.odometry_rejected == before.odometry_rejected + 1, (before, after)

    case(r"ignoring odometry stamped [\d.]+ s: orientation quaternion \(0, 0, nan, 1\) is not finite",
         quaternion=[0.0, 0.0, np.nan, 1.0])
    case(r"orientation quaternion \(0, 0, 0, 2\) has norm 2, not 1", quaternion=[0.0, 0.0, 0.0, 2.0])
    case(r"position \(inf, 2, 0.5\) is not finite", translation=[np.inf, 2.0, 0.5])
    assert rig_alive(rig)


def test_a_pose_jump_is_warned_and_clouds_inside_it_are_dropped(rig):
    baseline = Baseline(rig)
    before = rig.stats()
    mark = rig.log.mark()
    rig.publish(odometry(rig.next_stamp()))
    jumped = rig.next_stamp()
    rig.publish(odometry(jumped, translation=TRANSLATION + [50.0, 0.0, 0.0]))
    rig.wait_log(r"\[WARN\].*odometry jumped 50.00 m in 1.00 s at [\d.]+ s \(after [\d.]+ s; max_pose_jump = 10.0 m\): "
                 r"map kept \(on_pose_jump keep\): the scans after it are added where the odometry now says; clouds "
                 r"stamped inside the jump are dropped", mark)
    now = rig.stats()
    assert now.odometry_in == before.odometry_in + 2 and now.odometry_rejected == before.odometry_rejected
    baseline.expect_untouched(now)
    # Half way between the two poses is 25 m from either: never a place the sensor was.
    expect_dropped(rig, baseline, [cloud(jumped - SECOND // 2)], "the odometry jumped between the poses around "
                   "its stamp", "pose jump")
    # Mapping goes on at the new pose.
    after = rig.integrate_good_cloud(translation=TRANSLATION + [50.0, 0.0, 0.0])
    assert after.voxels > baseline.stats.voxels


def test_time_going_backwards_keeps_the_map_and_mapping_resumes(rig):
    baseline = Baseline(rig)
    before = rig.stats()
    mark = rig.log.mark()
    rig.stamp -= 500 * SECOND  # the bag starts again
    rig.publish(odometry(rig.next_stamp()))
    rig.wait_log(r"\[WARN\].*time went backwards by 49\d\.\d+ s \(odometry stamped [\d.]+ s after input stamped "
                 r"[\d.]+ s; a restarted bag\?\): odometry history cleared, 0 waiting clouds dropped, map kept", mark)
    now = rig.stats()
    assert now.odometry_in == before.odometry_in + 1
    baseline.expect_untouched(now)
    after = rig.integrate_good_cloud()
    assert after.integrated == before.integrated + 1


def test_clouds_lagging_the_odometry_by_seconds_are_mapped(rig):
    """Segmentation keeps the capture stamp, so clouds may arrive after odometry 2 s newer:
    that is not time going backwards."""
    before = rig.stats()
    lagged = rig.next_stamp()
    for step in range(5):  # odometry up to 2 s past the cloud's stamp, all of it before the cloud
        rig.publish(odometry(lagged + step * SECOND // 2))
    rig.publish(cloud(lagged + SECOND // 4))
    after = rig.wait_stats(lambda s: s.integrated == before.integrated + 1)
    assert after.dropped == before.dropped and "time reset" not in after.reasons, after
    rig.stamp = lagged + 2 * SECOND


def test_clouds_with_some_bad_points_or_big_endian_bytes_map_like_their_good_points(nodes):
    """NaN/inf points, unknown label ids and probability rows that are negative, NaN or sum to
    zero are warned about and left out; a big-endian cloud is read as such. The map equals the
    offline mapper's for the good points alone, and it saves and loads."""
    rig = nodes["partial"].wait_ready()
    try:
        rig.integrate_good_cloud()
        count = len(POINTS)
        nan_points = np.concatenate([POINTS, np.full((60, 3), np.nan, np.float32), np.full((40, 3), -np.inf,
                                                                                         np.float32)])
        nan_labels = np.concatenate([LABELS, np.full(100, 40, np.uint32)])
        unknown_points = np.concatenate([POINTS, POINTS[:50]])
        unknown_labels = np.concatenate([LABELS, np.full(50, 7777, np.uint32)])
        expectations = [
            (cloud(0, **fields(points=nan_points, labels=nan_labels)),
             rf"100 of {count + 100} points dropped: 100 with NaN/inf coordinates; the rest are integrated"),
            (cloud(0, **fields(points=unknown_points, labels=unknown_labels)),
             rf"50 of {count + 50} points carry label ids unknown to the semantic_kitti label map \(e.g. 7777\)"),
            (big_endian_cloud(0), None),
            (probability_cloud_with_bad_rows(),
             rf"30 of {count + 30} points dropped: 10 with NaN/inf probabilities, 10 with negative probabilities, "
             r"10 with probabilities summing to zero; the rest are integrated"),
        ]
        for msg, warning in expectations:
            before = rig.stats()
            mark = rig.log.mark()
            stamp = rig.next_stamp()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, SECOND)
            rig.publish(odometry(stamp), msg)
            rig.wait_stats(lambda s, before=before: s.integrated == before.integrated + 1)
            if warning:
                rig.wait_log(r"\[WARN\].*" + warning, mark)
            else:
                assert "[WARN]" not in rig.log.text(mark), rig.log.text(mark)
        five_scans = offline_map(5)
        expected = five_scans.voxels()
        shown = expected.label != 0  # voxels the rays emptied are not shown
        got = decode_cloud(rig.map_message(int(shown.sum())), 20)
        order_got, order_expected = np.lexsort(got.points.T), np.lexsort(expected.centres[shown].T)
        np.testing.assert_array_equal(got.points[order_got], expected.centres[shown][order_expected])
        np.testing.assert_array_equal(got.labels[order_got], expected.label[shown][order_expected])
        from std_srvs.srv import Trigger

        saved = rig.probe.call(Trigger, "/convbki_mapper/save_map")
        assert saved.success, saved.message
        expect_file_holds(rig.map_file, five_scans)
    finally:
        output = rig.close()
    assert "Traceback" not in output, output


def probability_cloud_with_bad_rows():
    """The good cloud as one-hot class probabilities (the same evidence as its labels), and 30
    more points whose rows are NaN, negative or all zero."""
    learning = load_label_map("semantic_kitti").to_learning(LABELS)
    good = np.eye(20, dtype=np.float32)[learning]
    nan_row, negative_row, zero_row = np.full(20, 0.05, np.float32), np.full(20, 0.05, np.float32), np.zeros(20)
    nan_row[4], negative_row[2] = np.nan, -0.01
    rows = np.concatenate([good, np.tile(nan_row, (10, 1)), np.tile(negative_row, (10, 1)),
                           np.tile(zero_row, (10, 1))]).astype(np.float32)
    points = np.concatenate([POINTS, POINTS[:30]])
    return cloud(0, **{"x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
                       **{f"prob_{c}": rows[:, c] for c in range(20)}})


# ----------------------------------------------------------------------------- saving


def test_a_save_that_fails_answers_why_keeps_the_old_file_and_mapping_goes_on(rig):
    """A full disk, simulated with the node's file-size limit (RLIMIT_FSIZE, which binds root
    too): the write fails part way, like ENOSPC. The service says why; the file saved before is
    byte for byte the same; no temporary file is left; the node keeps mapping."""
    from std_srvs.srv import Trigger

    saved = rig.probe.call(Trigger, "/convbki_mapper/save_map")
    assert saved.success, saved.message
    before = rig.map_file.read_bytes()
    rig.integrate_good_cloud()
    _, hard = resource.prlimit(rig.process.pid, resource.RLIMIT_FSIZE)
    resource.prlimit(rig.process.pid, resource.RLIMIT_FSIZE, (len(before) // 2, hard))
    try:
        failed = rig.probe.call(Trigger, "/convbki_mapper/save_map")
    finally:
        resource.prlimit(rig.process.pid, resource.RLIMIT_FSIZE, (hard, hard))
    assert not failed.success
    assert failed.message == f"could not save {rig.map_file}: File too large", failed.message
    assert rig.map_file.read_bytes() == before
    assert sorted(p.name for p in rig.map_file.parent.iterdir()) == ["map.npz", "map.npz.scan_log"]
    # Until a save succeeds, /diagnostics says the map is not saved (ERROR, with the reason).
    unsaved = rig.wait_stats(lambda s: s.level == 2)
    assert failed.message in unsaved.message and unsaved.last_save == failed.message, unsaved
    stats = rig.integrate_good_cloud()
    saved = rig.probe.call(Trigger, "/convbki_mapper/save_map")
    assert saved.success and saved.message == f"saved {stats.voxels} voxels to {rig.map_file} (the file before kept " \
        "as map.npz.prev)", saved.message
    assert Path(f"{rig.map_file}.prev").read_bytes() == before  # the file it replaced
    assert rig.wait_stats(lambda s: s.level != 2 and s.last_save == saved.message).integrated == stats.integrated
    # After every kind of bad input this node has seen, its file still loads.
    reloaded = offline_map(0)
    reloaded.load(rig.map_file)
    assert len(reloaded) == stats.voxels


@pytest.mark.skipif(os.geteuid() == 0 and not WITHOUT_PERMISSION_OVERRIDE,
                    reason="root writes into read-only folders, and setpriv is not here to stop that")
def test_a_save_into_a_read_only_folder_answers_why(rig):
    from std_srvs.srv import Trigger

    saved = rig.probe.call(Trigger, "/convbki_mapper/save_map")
    assert saved.success, saved.message
    before = rig.map_file.read_bytes()
    rig.integrate_good_cloud()
    rig.map_file.parent.chmod(0o555)
    try:
        failed = rig.probe.call(Trigger, "/convbki_mapper/save_map")
    finally:
        rig.map_file.parent.chmod(0o755)
    assert not failed.success and failed.message == f"could not save {rig.map_file}: Permission denied"
    assert rig.map_file.read_bytes() == before
    assert rig.integrate_good_cloud().integrated > 0

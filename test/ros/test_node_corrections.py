"""A SLAM's corrections through the node, as a robot runs it: a drift drive's bag (odometry that
drifts, map -> odom jumping when the loop closes, the keyframes on /pose_corrections) replayed
by ``play_bag`` while the node maps; an outside subscriber of semantic_map and of
semantic_map/updates then holds the map built from scratch with the corrected poses. A map saved
with its log is corrected after a restart; a map file without one, and bad Paths, get one line
and change nothing."""

import numpy as np
import pytest
from mapper_rig import WAIT, Stats
from ros_helpers import NodeLog, Probe, domain_id, start, stop

from convbki_core.config import MapperConfig
from convbki_core.correction.replay import keyframe_corrections
from convbki_core.correction.scan_log import LoggedScan
from convbki_core.datasets.drift import read_loop_closure
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.poses import pose_from_translation_quaternion, pose_to_translation_quaternion
from convbki_core.io.labels import load_label_map
from convbki_core.io.map_file import MapSnapshot, read_map
from convbki_core.mapper import ConvBKIMapper
from convbki_core.outputs.records import RECORD, apply_records, packed_palette, records_from_alpha
from convbki_core.paths import config_dir
from convbki_core.tools import map_tool
from convbki_ros.inputs.transforms import poses_to_path
from convbki_ros.tools.kitti_to_bag import EPOCH_NS
from convbki_ros.tools.kitti_to_bag import main as kitti_to_bag

FRAMES, CLOSURE = 40, 25
# The paper set-up's log bound (see the drift test), the smallest of a 0.25 MB grid that still
# holds every scan 10 scans after the closure on the shared drift drive.
PAPER_LOG_MEGABYTES = 4.75
BOUNDS = [-20.0, -20.0, -3.0, 20.0, 20.0, 3.0]
LABELS = load_label_map("semantic_kitti")


@pytest.fixture(scope="module")
def drive(drift_drive, tmp_path_factory):
    """The small drift drive with moving traffic (``drift_drive``, test/conftest.py: 40 scans, the
    loop closed before scan 25, which test_correction.py maps too) as ``data`` and its bags: the
    whole drive, and the scans before the loop closes."""
    root = tmp_path_factory.mktemp("drift")
    (root / "data").symlink_to(drift_drive, target_is_directory=True)
    assert kitti_to_bag(["--dataset", str(root / "data"), "--sequence", "00", "--out", str(root / "bag")]) == 0
    assert kitti_to_bag(["--dataset", str(root / "data"), "--sequence", "00", "--frames", f"0:{CLOSURE}",
                         "--out", str(root / "before")]) == 0
    return root


def as_sent(pose: np.ndarray) -> np.ndarray:
    """A pose as it arrives in a message (a translation and a quaternion)."""
    return pose_from_translation_quaternion(*pose_to_translation_quaternion(pose))


def node_config(setup: str) -> MapperConfig:
    config = MapperConfig.from_params_file(config_dir() / "mapper.yaml").replace(
        device="cpu", local_bounds=(BOUNDS[:3], BOUNDS[3:]))
    return config.replace(free_space=False) if setup == "paper" else config


def expected_map(setup: str, dataset, closure, frames: int) -> ConvBKIMapper:
    """What the node should hold once the loop closed: every scan of ``frames`` mapped from
    scratch at its corrected pose (the odometry's pose as sent, before the closure moved by the
    keyframes' corrections as the Path carries them, after it behind the corrected map -> odom)."""
    robot = np.stack([as_sent(closure.correction_at(k)) @ as_sent(closure.odometry[k]) for k in range(frames)])
    stamps = EPOCH_NS + closure.stamps_ns
    logged = [(k, LoggedScan.of(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), robot[k], int(stamps[k])))
              for k in range(frames)]
    keyframes = closure.keyframes
    moved = keyframe_corrections(logged, stamps[keyframes], np.stack([as_sent(p) for p in closure.truth[keyframes]]))
    mapper = ConvBKIMapper(node_config(setup).replace(scan_log=False))
    for k in range(frames):
        frame = dataset[k]
        raw = frame.raw_input_labels
        moving = LABELS.is_moving(raw)
        mapper.integrate(frame.points, LABELS.to_learning(raw), moved.get(k, robot[k]),
                         moving if moving.any() else None)
    return mapper


def frozen_counts(dataset, closure, megabytes: float) -> list[int]:
    """Scans frozen out of the paper set-up's log of ``megabytes``, after each scan of the drive."""
    mapper = ConvBKIMapper(node_config("paper").replace(scan_log_megabytes=megabytes))
    robot, counts = closure.robot_poses(), []
    for k in range(FRAMES):
        frame = dataset[k]
        mapper.integrate(frame.points, frame.input_labels, robot[k], stamp_ns=k)
        counts.append(mapper.scan_log.frozen)
    return counts


def shown_records(mapper: ConvBKIMapper) -> dict:
    indices, alpha = mapper.items()
    records = records_from_alpha(indices, alpha, mapper.resolution, packed_palette(LABELS.colors))
    return {(float(r["x"]), float(r["y"]), float(r["z"])): r for r in records[records["label"] != 0]}


def records_of(msg) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), RECORD, count=msg.width)


def same_records(got: dict, want: dict) -> bool:
    return got.keys() == want.keys() and all(got[key].tobytes() == want[key].tobytes() for key in want)


def start_node(domain: int, tmp_path, setup: str, *parameters: str):
    # Updates every 0.2 s (the stream a subscriber rebuilds the map from, in many steps); the
    # whole map (some 200,000 records, which the node builds and the probe reads each time) once a
    # second: the last one comes at most a second after the map's last change.
    return start("convbki_ros.main", domain, "--ros-args", "--params-file", config_dir() / "mapper.yaml",
                 "-r", "cloud_in:=/kitti/velo/pointcloud", "-r", "odom:=/kitti/odom", "-p", "device:=cpu",
                 "-p", f"local_bounds:={BOUNDS}", "-p", "publish_period:=0.2", "-p", "map_period:=1.0",
                 "-p", "diagnostics_period:=0.2", "-p", "map_frame:=map", "-p", f"free_space:={setup != 'paper'}",
                 "-p", "correction_tolerance:=0.0", "-p", "correction_min_move:=0.0", *parameters)


def set_parameters(probe, **values) -> list:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    client = probe.node.create_client(SetParameters, "/convbki_mapper/set_parameters")
    assert probe.spin_until(client.service_is_ready, WAIT)
    future = client.call_async(SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()
                                                                 for name, value in values.items()]))
    assert probe.spin_until(future.done, WAIT)
    return future.result().results


def diagnostics(array) -> dict:
    return {item.key: item.value for item in array.status[0].values}


@pytest.mark.parametrize("setup", ["paper", "defaults"])
def test_a_drift_drive_through_the_node_is_corrected_to_the_map_built_from_scratch(drive, tmp_path, setup):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    dataset = SemanticKittiSequence(drive / "data", "00")
    closure = read_loop_closure(dataset)

    # A bounded log: it reaches back over the loop when it closes (scan 25), and the oldest scans
    # are frozen by the end of the drive (scan 40). In megabytes (the scans and the map as it was
    # where each segment begins), as the offline mapper counts them: nothing frozen until 10 scans
    # after the closure, at least 8 scans by the end. (Whenever the node's correction starts,
    # nothing falls out of the log between the Path's arrival and the log's copy.)
    if setup == "paper":
        megabytes = PAPER_LOG_MEGABYTES
        frozen_offline = frozen_counts(dataset, closure, megabytes)
        assert frozen_offline[CLOSURE + 10] == 0 and frozen_offline[-1] >= 8, \
            f"scans frozen after each scan with {megabytes} MB: {frozen_offline}; choose another bound"
        bound = ("-p", f"scan_log_megabytes:={megabytes}", "-p", "scan_log_disk_gigabytes:=0.0")  # in memory only
    else:
        bound = ("-p", "scan_log_scans:=32")  # in its folder, beside map_file by default
    domain = domain_id()
    node = start_node(domain, tmp_path, setup, "-p", f"map_file:={tmp_path / 'map.npz'}", *bound)
    log = NodeLog(node)
    probe = Probe(domain)
    try:
        maps = probe.subscribe(PointCloud2, "/semantic_map", latched=True)
        updates = probe.subscribe(PointCloud2, "/semantic_map/updates", depth=1000)
        reports = probe.subscribe(DiagnosticArray, "/diagnostics")
        # What the node should hold, worked out while it starts (imports, kernels) and DDS matches
        # the probe to it: nothing is played before the match below.
        want = shown_records(expected_map(setup, dataset, closure, FRAMES))
        uncorrected = ConvBKIMapper(node_config(setup).replace(scan_log=False))
        for k in range(FRAMES):
            frame = dataset[k]
            uncorrected.integrate(frame.points, frame.input_labels,
                                  as_sent(closure.correction_at(k)) @ as_sent(closure.odometry[k]))
        assert len(shown_records(uncorrected).keys() - want.keys()) > 1000  # without correction: streets twice
        # The node sends updates only to the listeners it has found: the probe must be matched to it
        # before the first scan, and spin while the bag plays (a reader keeps `depth` messages).
        assert probe.spin_until(lambda: probe.matched("/semantic_map", "/semantic_map/updates", "/diagnostics")
                                and reports, 60), log.text()
        rebuilt: dict = {}
        applied = 0
        compared: dict = {"map": None, "updates": -1}  # what was compared last, and the answers
        equal = {"map": False, "updates": False}

        def in_step() -> bool:
            # Each message compared once (some 260,000 records each): the whole map when a new one
            # came, the copy kept from the updates when more came.
            nonlocal applied
            for msg in updates[applied:]:
                apply_records(rebuilt, records_of(msg))
            applied = len(updates)
            if maps and maps[-1] is not compared["map"]:
                compared["map"] = maps[-1]
                equal["map"] = same_records({(float(r["x"]), float(r["y"]), float(r["z"])): r
                                             for r in records_of(maps[-1])}, want)
            if applied != compared["updates"]:
                compared["updates"] = applied
                equal["updates"] = same_records(rebuilt, want)
            return equal["map"] and equal["updates"]

        # The bag plays at its own pace: the scans after the closure arrive while the correction runs.
        player = start("convbki_ros.tools.play_bag", domain, drive / "bag", "--wait-for-node")
        assert probe.spin_while(player, 120) == 0, stop(player)
        # The player waited for the node's reader of the Path too, not only of the clouds and odometry.
        output = stop(player)
        assert "starting anyway" not in output, output
        assert probe.spin_until(in_step, 60), (len(maps), len(updates), len(rebuilt), len(want),
                                               "\n".join(line for line in log.text().splitlines() if "correct" in line))
        assert log.find(r"pose_corrections applied: (\d+) scans moved")
        seen = len(reports)
        assert probe.spin_until(lambda: len(reports) > seen, WAIT)
        counters, stats = diagnostics(reports[-1]), Stats.parse(reports[-1])
        # Every live scan integrated, none dropped, while the correction ran beside them.
        assert stats.integrated == FRAMES and stats.dropped == 0, stats
        assert counters["corrections_done"] == "1" and counters["corrections_pending"] == "0", counters
        assert int(counters["correction_last_scans"]) >= CLOSURE - 2 and float(counters["correction_last_s"]) > 0
        assert float(counters["correction_last_largest_move_m"]) > 0.1
        frozen = int(counters["scan_log_frozen"])
        assert int(counters["scan_log_scans"]) + frozen == FRAMES and frozen >= 8, counters
        if setup == "paper":
            assert frozen == frozen_offline[-1], counters
            assert float(counters["scan_log_megabytes"]) <= megabytes, counters
            assert counters["scan_log_folder"] == "" and counters["scan_log_disk_megabytes"] == "0.0", counters
        else:
            assert int(counters["scan_log_scans"]) <= 32, counters
            assert counters["scan_log_folder"] == f"{tmp_path / 'map.npz'}.scan_log", counters
        if frozen < FRAMES:  # corrections reach back to the oldest scan still logged
            assert float(counters["scan_log_reach_stamp"]) == pytest.approx(
                (EPOCH_NS + closure.stamps_ns[frozen]) / 1e9, abs=1e-3)
    finally:
        probe.close()
        output = stop(node)
    assert "Traceback" not in output and "[ERROR]" not in output, output


def test_a_saved_log_is_corrected_after_a_restart_and_bad_paths_change_nothing(drive, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Path
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    dataset = SemanticKittiSequence(drive / "data", "00")
    closure = read_loop_closure(dataset)
    map_file = tmp_path / "map.npz"
    domain = domain_id()
    # The log's folder; memory for 8 scans: a segment every 2, the older ones on disk only.
    frame = dataset[0]
    scan_megabytes = LoggedScan.of(frame.points, frame.input_values, np.eye(4), 0).nbytes / 1e6
    on_disk = ("-p", f"scan_log_folder:={tmp_path / 'logs'}", "-p", "scan_log_disk_gigabytes:=2.0",
               "-p", f"scan_log_megabytes:={8 * scan_megabytes}")
    # The first run maps the scans before the loop closes and saves them, with their log, on shutdown.
    first_run = NodeLog(start_node(domain, tmp_path, "defaults", "-p", f"map_file:={map_file}", *on_disk))
    player = start("convbki_ros.tools.play_bag", domain, drive / "before", "--wait-for-node")
    # The map the second run must end with (the same as a correction without the restart: the
    # scans at their corrected poses), worked out while the first run starts and maps.
    want = shown_records(expected_map("defaults", dataset, closure, CLOSURE))
    assert player.wait(timeout=120) == 0, stop(player)
    probe = Probe(domain)
    try:
        reports = probe.subscribe(DiagnosticArray, "/diagnostics")
        assert probe.spin_until(lambda: reports and Stats.parse(reports[-1]).integrated == CLOSURE, WAIT)
        status = diagnostics(reports[-1])
    finally:
        probe.close()
    assert status["scan_log_folder"] == str(tmp_path / "logs") and status["scan_log_write_error"] == "", status
    assert float(status["scan_log_write_backlog_megabytes"]) >= 0.0, status
    assert float(status["scan_log_megabytes"]) < 0.5 * float(status["scan_log_disk_megabytes"]), status
    assert "saved" in first_run.close()  # Ctrl-C: the node saves on shutdown
    metadata, _, _ = read_map(map_file, with_scan_log=True)
    # The map file names the folder's files: it holds none of the scans' bytes itself.
    scans = metadata["scan_log"].scans()
    assert len(scans) == CLOSURE and all(scan.data.place[0].path == tmp_path / "logs" for _, scan in scans)
    plain, indices, alpha = read_map(map_file)
    MapSnapshot(plain, indices, alpha).write(tmp_path / "no_log.npz")
    log_in_file = map_file.stat().st_size - (tmp_path / "no_log.npz").stat().st_size
    assert 0 < log_in_file < 0.1 * sum(scan.data.size for _, scan in scans)

    # The second run starts from that file; the SLAM's Path comes after the restart.
    node = start_node(domain, tmp_path, "defaults", "-p", f"map_file:={map_file}", *on_disk)
    log = NodeLog(node)
    probe = Probe(domain)
    try:
        reports = probe.subscribe(DiagnosticArray, "/diagnostics")
        publisher = probe.node.create_publisher(Path, "/pose_corrections",
                                                QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0 and log.find("mapper ready"), 60)
        stamps = EPOCH_NS + closure.stamps_ns[closure.keyframes]
        poses = closure.truth[closure.keyframes]

        def path(frame="map", keyframe_stamps=stamps, keyframe_poses=poses):
            return poses_to_path(keyframe_poses, keyframe_stamps, frame, int(stamps[-1]))

        def counters():
            seen = len(reports)
            assert probe.spin_until(lambda: len(reports) > seen, WAIT)
            return diagnostics(reports[-1])

        before = counters()
        nan = poses.copy()
        nan[2, 0, 3] = np.nan
        bad = [(path(frame="odom"), "its frame is 'odom', not the map's 'map'"),
               (path(keyframe_stamps=stamps[:0], keyframe_poses=poses[:0]), "it holds no pose"),
               (path(keyframe_poses=nan), "pose 2: position"),
               (path(keyframe_stamps=stamps[::-1].copy()), "not in ascending order"),
               (path(keyframe_stamps=stamps + 3600 * 10**9), "bracket no logged scan"),
               # RTAB-Map's periodic mapPath: every pose stamped with the update's time.
               (path(keyframe_stamps=np.full_like(stamps, stamps[-1])),
                "all share one stamp .* publish_map service publishes mapPath with each node's own stamp, e.g. "
                "ros2 service call /rtabmap/rtabmap/publish_map")]
        for msg, words in bad:
            mark = log.mark()
            publisher.publish(msg)
            assert log.wait_for(r"ignoring the Path on .*pose_corrections.*" + words.replace("(", r"\(")
                                .replace(")", r"\)") + ".*the map is unchanged", mark, WAIT), log.text(mark)
        # (A report made before the last refusal may still arrive after its line.)
        assert probe.spin_until(lambda: diagnostics(reports[-1])["corrections_refused"] == str(len(bad)), WAIT), \
            diagnostics(reports[-1])
        after = diagnostics(reports[-1])
        assert after["map_version"] == before["map_version"]
        assert after["corrections_done"] == "0"

        # A Path that moves no scan by correction_min_move (here 1000 m) is a look at the log's
        # poses: counted, no line (a SLAM re-sends its path many times a second).
        unchanged = int(after["corrections_unchanged"])
        (refused,) = set_parameters(probe, correction_min_move=-0.5)  # its only negative value is -1
        assert not refused.successful and "-1.0 (half a voxel)" in refused.reason, refused.reason
        assert all(r.successful for r in set_parameters(probe, correction_min_move=1000.0))
        mark = log.mark()
        publisher.publish(path())
        assert probe.spin_until(lambda: int(diagnostics(reports[-1])["corrections_unchanged"]) == unchanged + 1,
                                WAIT), diagnostics(reports[-1])
        assert "pose_corrections" not in log.text(mark) and diagnostics(reports[-1])["corrections_done"] == "0"
        # A map file without a log (an older version's): it loads, and a Path then says in one
        # line that its scans cannot move.
        bare = tmp_path / "bare.npz"
        metadata, indices, alpha = read_map(map_file)
        MapSnapshot(dict(metadata, version=2), indices, alpha).write(bare)
        assert all(r.successful for r in set_parameters(probe, map_file=str(bare)))
        assert probe.call(Trigger, "/convbki_mapper/load_map").success
        mark = log.mark()
        publisher.publish(path())
        assert log.wait_for(r"the \d+ scans before cannot move: they came from a map file without a scan log",
                            mark, WAIT), log.text(mark)
        # The saved map back, with its log; at half a voxel (every scan's move mapped again at a
        # tolerance of 0) the Path moves its scans, and Ctrl-C comes while the correction runs.
        assert all(r.successful for r in set_parameters(probe, map_file=str(map_file)))
        assert probe.call(Trigger, "/convbki_mapper/load_map").success
        assert all(r.successful for r in set_parameters(probe, correction_min_move=-1.0, correction_tolerance=0.0))
        publisher.publish(path())
        assert probe.spin_until(lambda: "correction_progress" in diagnostics(reports[-1]), WAIT)
    finally:
        probe.close()
        output = log.close()  # Ctrl-C (while the correction runs, when all went well)
    assert node.returncode == 0, output
    assert "terminate called" not in output and "Traceback" not in output and "[ERROR]" not in output, output
    assert "pose_corrections applied" not in output, "the correction ended before Ctrl-C: nothing was stopped"
    # The map saved then is the map as it was, with the Path in its log: map_tool correct finishes the job.
    metadata, _, _ = read_map(map_file, with_scan_log=True)
    assert metadata["scan_log"].pending is not None and len(metadata["scan_log"].pending[0]) == len(stamps)
    fixed = tmp_path / "fixed.npz"
    assert map_tool.main(["correct", str(map_file), "--out", str(fixed), "--quiet"]) == 0
    metadata, indices, alpha = read_map(fixed, with_scan_log=True)
    assert metadata["scan_log"].pending is None
    got = records_from_alpha(indices, alpha, metadata["resolution"], packed_palette(LABELS.colors))
    got = {(float(r["x"]), float(r["y"]), float(r["z"])): r for r in got[got["label"] != 0]}
    assert same_records(got, want)


"""A SLAM's correction moves the scans the map holds: the sum taken apart scan by scan, the
scan log (bounds, file), the keyframes' corrections, and re-placed scans equal to a map built
from scratch with the corrected poses, through the library, ``map_tool correct`` and
``evaluate`` on a drift drive."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from convbki_core import ConvBKIKernel, ConvBKIMapper
from convbki_core.config import MapperConfig
from convbki_core.correction.replay import keyframe_corrections
from convbki_core.correction.scan_log import LoggedScan
from convbki_core.datasets.drift import read_loop_closure
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.poses import interpolate_pose
from convbki_core.io.map_file import MapSnapshot, read_map
from convbki_core.tools import evaluate, map_tool

NUM_CLASSES = 6
CLOSURE = 25  # the SLAM closes the loop before this scan of the drift drive


def voxel_dict(mapper):
    indices, alpha = mapper.items()
    return {tuple(i): a for i, a in zip(indices.tolist(), alpha)}


def sorted_items(mapper):
    indices, alpha = mapper.items()
    order = np.lexsort(indices.T[::-1])
    return indices[order], alpha[order]


def pose_of(rng, spread: float = 1.0) -> np.ndarray:
    pose = np.eye(4)
    yaw = rng.uniform(-np.pi, np.pi)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = rng.uniform(-spread, spread, 3)
    return pose


# -- the sum, scan by scan -----------------------------------------------------------------------
@settings(max_examples=12)  # each example builds a mapper: a dozen keep every path and kernel drawn at CI cost
@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["single", "compound"]),
       path=st.sampled_from(["fast", "dense", "torch"]), probabilities=st.booleans())
def test_a_scan_added_then_withdrawn_leaves_the_map_as_it_was(seed, kind, path, probabilities):
    rng = np.random.default_rng(seed)
    lengths = rng.uniform(0.1, 0.6, NUM_CLASSES).tolist()
    kernel = (ConvBKIKernel(kind, NUM_CLASSES, 5, 0.2, ell=lengths[:1]) if kind == "single" else
              ConvBKIKernel(kind, NUM_CLASSES, 5, 0.2, ell_h=lengths, ell_z=lengths[::-1]))
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu",
                                              update_path=path, scan_log=False), kernel)

    def scan():
        points = rng.uniform(-2.5, 2.5, (200, 3))
        values = (rng.dirichlet(np.ones(NUM_CLASSES) * 0.3, 200).astype(np.float32) if probabilities
                  else rng.integers(0, NUM_CLASSES, 200))
        return points, values, pose_of(rng)

    for _ in range(3):
        mapper.integrate(*scan())
    before = voxel_dict(mapper)
    extra = scan()
    mapper.integrate(*extra)
    assert voxel_dict(mapper) != before
    mapper.withdraw(*extra)
    after = voxel_dict(mapper)
    prior = np.full(NUM_CLASSES, mapper.prior, np.float32)
    largest = max(float(np.max(a)) for a in after.values())
    # Every voxel either map holds (one only the withdrawn scan reached is back at the prior), in
    # one comparison: row k is the k-th voxel in x, y, z order.
    keys = sorted(set(before) | set(after))
    np.testing.assert_allclose(np.array([after.get(key, prior) for key in keys]),
                               np.array([before.get(key, prior) for key in keys]), rtol=1e-5, atol=2e-6 * largest)


def test_withdraw_refuses_a_map_that_is_not_a_sum():
    mapper = ConvBKIMapper(MapperConfig().replace(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu"))
    with pytest.raises(ValueError, match="not a sum"):
        mapper.withdraw(np.zeros((1, 3)), np.ones(1, np.int64), np.eye(4))


# -- the keyframes' corrections ------------------------------------------------------------------
def test_a_scan_between_two_keyframes_takes_their_correction_interpolated_by_time():
    straight = [(k, LoggedScan.of(np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                                  np.array([[1, 0, 0, k], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), k * 100))
                for k in range(11)]
    # The SLAM moves the keyframe at t = 0 not at all and the one at t = 1000 by 2 m sideways
    # and a quarter turn about its own position.
    new_last = np.eye(4)
    new_last[:2, :2] = [[0, -1], [1, 0]]
    new_last[:3, 3] = [10, 2, 0]
    moved = keyframe_corrections(straight, np.array([0, 1000]), np.stack([straight[0][1].pose, new_last]))
    assert sorted(moved) == list(range(11))
    np.testing.assert_allclose(moved[0], straight[0][1].pose, atol=1e-12)
    np.testing.assert_allclose(moved[10], new_last, atol=1e-12)
    change = new_last @ np.linalg.inv(straight[10][1].pose)
    np.testing.assert_allclose(moved[5], interpolate_pose(np.eye(4), change, 0.5) @ straight[5][1].pose,
                               atol=1e-12)
    half_turn = np.arctan2(moved[5][1, 0], moved[5][0, 0])
    assert half_turn == pytest.approx(np.pi / 4)
    # Scans after the last keyframe came with the SLAM's newer frame: they do not move.
    assert keyframe_corrections(straight, np.array([0, 500]), np.stack([straight[0][1].pose,
                                                                         straight[5][1].pose])).keys() == set(range(6))
    assert keyframe_corrections(straight, np.array([5000, 6000]), np.stack([new_last, new_last])) == {}


# -- the log -------------------------------------------------------------------------------------
def test_a_bounded_log_freezes_its_oldest_scans_and_a_map_file_keeps_it(tmp_path):
    rng = np.random.default_rng(3)
    mapper = ConvBKIMapper(MapperConfig.paper(local_bounds=((-3, -3, -2), (3, 3, 2)), device="cpu",
                                              scan_log_scans=6),
                           ConvBKIKernel("single", NUM_CLASSES, 5, 0.2, ell=[0.4]))
    scans = [(rng.uniform(-2, 2, (150, 3)).astype(np.float32), rng.integers(0, NUM_CLASSES, 150), pose_of(rng))
             for _ in range(10)]
    for number, scan in enumerate(scans):
        mapper.integrate(*scan, stamp_ns=1_000 + number)
    log = mapper.scan_log
    assert len(log) <= 6 and log.first_index == 10 - len(log) and log.frozen == log.first_index
    assert log.reach_ns == 1_000 + log.first_index and log.next_index == 10
    for index, logged in log.scans():  # bit for bit as integrated
        assert logged.points().tobytes() == scans[index][0].tobytes()
        assert np.array_equal(logged.values(), scans[index][1]) and np.array_equal(logged.pose, scans[index][2])
    mapper.save(tmp_path / "map.npz")
    metadata, _, _ = read_map(tmp_path / "map.npz", with_scan_log=True)
    again = metadata["scan_log"]
    assert [(i, s.stamp_ns, s.points_data, s.values_data) for i, s in again.scans()] == \
        [(i, s.stamp_ns, s.points_data, s.values_data) for i, s in log.scans()]
    assert again.frozen == log.frozen and "fell out" in again.frozen_why

    # A scan that fell out of the log cannot move; one still in it can, unless it moves by less
    # than the tolerance (a point at the window's edge, 3 m away, moves 3 mm by a milliradian).
    moves, skipped, _ = mapper.plan_correction({0: np.eye(4), 9: np.eye(4)})
    assert sorted(moves) == [9] and skipped == 0
    turned = np.eye(4)
    turned[:2, :2] = [[np.cos(1e-3), -np.sin(1e-3)], [np.sin(1e-3), np.cos(1e-3)]]
    nudged = {8: turned @ scans[8][2], 9: scans[9][2] + np.diag([0, 0, 0, 0]) + np.pad([[0.01]], ((0, 3), (3, 0)))}
    assert mapper.plan_correction(nudged, tolerance=0.002)[0].keys() == {8, 9}
    moves, skipped, largest = mapper.plan_correction(nudged, tolerance=0.005)
    assert moves.keys() == {9} and skipped == 1 and largest == pytest.approx(0.01)

    # A file without a log (saved by a version before logs) still loads: its map is where
    # corrections begin, and nothing before can move.
    indices, alpha = mapper.items()
    old = dict(metadata, version=2)
    old.pop("scan_log")
    MapSnapshot(old, indices, alpha).write(tmp_path / "old.npz")
    fresh = ConvBKIMapper(mapper.config, mapper.kernel)
    fresh.load(tmp_path / "old.npz")
    assert len(fresh.scan_log) == 0 and fresh.scan_log.frozen == 10 and "without a scan log" in \
        fresh.scan_log.frozen_why
    assert fresh.plan_correction({9: np.eye(4)})[0] == {}


# -- re-placed scans equal the map built from scratch -----------------------------------------------
# The drift drive (``drift_drive``, test/conftest.py, shared with the node's correction tests): 40
# scans, odometry 8 degrees per 100 m and 1 % off, the loop closed before scan 25, moving traffic.
# It is mapped in a 40 x 40 m window (the node tests' too): a fraction of the default window's
# cost, and voxels leave it for the store as the robot drives, so the replays go through the store.
WINDOW = ((-20.0, -20.0, -3.0), (20.0, 20.0, 3.0))


def map_drive(config, dataset, poses, count, stamps):
    mapper = ConvBKIMapper(config)
    for k in range(count):
        frame = dataset[k]
        mapper.integrate(frame.points, frame.input_values, poses[k], frame.input_moving, stamp_ns=int(stamps[k]))
    return mapper


@pytest.mark.parametrize("setup", ["paper", "defaults"])
def test_a_correction_equals_the_map_built_from_scratch_with_the_corrected_poses(drift_drive, setup):
    dataset = SemanticKittiSequence(drift_drive, "00")
    closure = read_loop_closure(dataset)
    robot = closure.robot_poses()
    base = (MapperConfig.paper(device="cpu", local_bounds=WINDOW) if setup == "paper" else
            MapperConfig().replace(device="cpu", local_bounds=WINDOW))
    # A log of 16 scans: it begins a segment every 8, so the correction maps again from the base
    # of a segment in the middle of the drive, and the oldest scans are frozen where they were.
    config = base.replace(scan_log_scans=16)
    live = map_drive(config, dataset, robot, CLOSURE, closure.stamps_ns)
    first = live.scan_log.first_index
    assert 0 < first < CLOSURE - 1 and len(live.scan_log.segments()) > 1
    wanted = keyframe_corrections(live.scan_log.scans(), closure.stamps_ns[closure.keyframes],
                                  closure.truth[closure.keyframes])
    assert sorted(wanted) == list(range(first, CLOSURE))
    before = sorted_items(live)
    fixed, result = live.corrected(wanted)
    assert result.scans > 0 and result.largest_move > 0.05 and result.replayed >= result.scans
    # Mapping goes on in the corrected map after the closure, at the robot's corrected poses.
    for k in range(CLOSURE, len(dataset)):
        frame = dataset[k]
        fixed.integrate(frame.points, frame.input_values, robot[k], frame.input_moving,
                        stamp_ns=int(closure.stamps_ns[k]))
    # From scratch: the frozen scans where the robot mapped them, the rest at their corrected poses.
    poses = [wanted.get(k, robot[k]) for k in range(len(dataset))]
    scratch = map_drive(config, dataset, poses, len(dataset), closure.stamps_ns)
    got, want = sorted_items(fixed), sorted_items(scratch)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])  # every concentration, bit for bit
    # The map it was made from is as it was.
    after = sorted_items(live)
    assert np.array_equal(after[0], before[0]) and np.array_equal(after[1], before[1])


def test_map_tool_correct_moves_a_saved_maps_scans_and_evaluate_measures_the_drift(drift_drive, tmp_path, capsys):
    dataset = SemanticKittiSequence(drift_drive, "00")
    closure = read_loop_closure(dataset)
    robot, corrected = closure.robot_poses(), closure.corrected_poses()
    # A window of the drive's street (the map file keeps its bounds, which the correction reads).
    config = MapperConfig().replace(device="cpu", local_bounds=WINDOW)
    saved = map_drive(config, dataset, robot, CLOSURE, closure.stamps_ns)
    saved.scan_log.calibration = dataset.calibration
    saved.save(tmp_path / "robot.npz")
    camera = [dataset.calibration @ corrected[k] @ np.linalg.inv(dataset.calibration) for k in range(CLOSURE)]
    poses_file = tmp_path / "corrected.txt"
    poses_file.write_text("".join(" ".join(f"{v:.17g}" for v in p[:3].ravel()) + "\n" for p in camera))
    assert map_tool.main(["correct", str(tmp_path / "robot.npz"), "--poses", str(poses_file), "--out",
                          str(tmp_path / "fixed.npz"), "--quiet"]) == 0
    assert f"{CLOSURE} of {CLOSURE} logged scans moved" in capsys.readouterr().out
    scratch = map_drive(config, dataset, corrected, CLOSURE, closure.stamps_ns)
    metadata, indices, alpha = read_map(tmp_path / "fixed.npz", with_scan_log=True)
    order = np.lexsort(indices.T[::-1])
    want = sorted_items(scratch)
    np.testing.assert_array_equal(indices[order], want[0])
    np.testing.assert_array_equal(alpha[order], want[1])
    assert len(metadata["scan_log"]) == CLOSURE  # the fixed map can be corrected again

    # A poses file that does not fit, a map without a log: one line each, nothing written.
    poses_file.write_text(poses_file.read_text().split("\n", 1)[1])
    assert map_tool.main(["correct", str(tmp_path / "robot.npz"), "--poses", str(poses_file), "--out",
                          str(tmp_path / "no.npz"), "--quiet"]) == 2
    assert f"{CLOSURE - 1} poses for the {CLOSURE} logged scans" in capsys.readouterr().err
    bare = map_drive(config.replace(scan_log=False), dataset, robot, 2, closure.stamps_ns)
    bare.save(tmp_path / "bare.npz")
    assert map_tool.main(["correct", str(tmp_path / "bare.npz"), "--poses", str(poses_file), "--out",
                          str(tmp_path / "no.npz"), "--quiet"]) == 2
    assert "holds no scan log" in capsys.readouterr().err and not (tmp_path / "no.npz").exists()

    # evaluate on the drift drive: without correction the street is mapped twice; corrected, the
    # map is the one built from scratch. The first 30 scans (5 after the closure; the default
    # window, where the double surfaces stand out most): a quarter less mapping than all 40, and
    # the drift shows more (fewer later scans, mapped where they belong, to outweigh the drifted ones).
    report = tmp_path / "report.json"
    assert evaluate.main(["--dataset", str(drift_drive), "--sequence", "00", "--report", str(report),
                          "--frames", "0:30", "--quiet"]) == 0
    import json

    drift = json.loads(report.read_text())["drift"]
    maps = drift["maps"]
    assert maps["corrected"] == maps["from scratch"]
    assert maps["corrected"]["labels_equal"] == 1.0 and maps["without correction"]["labels_equal"] < 0.99
    assert maps["without correction"]["double_surface"] > maps["corrected"]["double_surface"] + 0.01
    assert drift["correction"]["scans_moved"] >= CLOSURE - 1 and drift["closure_frame"] == CLOSURE
    assert (tmp_path / "report_drift.png").stat().st_size > 10_000


def test_the_quick_look_at_a_paths_moves_agrees_with_the_poses_it_makes():
    """correction_moves (what tells a Path that moves nothing, on the changes alone) gives each
    scan's pose_displacements from its logged pose to the pose the correction makes, and 0 for
    the scans the Path does not reach."""
    from convbki_core.correction.replay import correction_moves, keyframe_correction, pose_displacements
    from convbki_core.correction.scan_log import LogTable

    rng = np.random.default_rng(4)
    scans = [(k, LoggedScan.of(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), pose_of(rng, 40.0), 1000 + 100 * k))
             for k in range(60)]
    table = LogTable.of(scans)
    keyframes = np.array([1000 + 100 * k + 30 for k in range(5, 50, 7)])
    bodies = keyframe_correction(table, keyframes, np.stack([np.eye(4)] * len(keyframes)))
    def small_change():  # what a SLAM's optimisation does between neighbouring keyframes
        yaw = rng.uniform(-0.05, 0.05)
        change = np.eye(4)
        change[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        change[:3, 3] = rng.uniform(-1.0, 1.0, 3)
        return change

    new_poses = np.stack([small_change() for _ in keyframes]) @ np.stack(
        [interpolate_pose(scans[(s - 1000) // 100][1].pose, scans[(s - 1000) // 100 + 1][1].pose, 0.3)
         for s in keyframes])
    correction = keyframe_correction(table, keyframes, new_poses)
    assert bodies is not None and correction is not None
    poses, reached = correction.pose_array(table)
    quick = correction_moves(correction, table, 25.0)
    exact = pose_displacements(table.poses, poses, 25.0)
    assert reached.sum() == 42 and not quick[~reached].any()  # scans 6 .. 47: between the first and last keyframes
    np.testing.assert_allclose(quick[reached], exact[reached], atol=1e-3)  # (its rotation lerped, not slerped)

"""The SemanticKITTI reader and the scores (docs/file_formats.md, docs/evaluation.md)."""

import numpy as np
import pytest
from kitti_fixture import pose_about_z, write_sequence

from convbki_core.datasets import DatasetError, parse_frames
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import voxel_indices
from convbki_core.io.labels import load_label_map
from convbki_core.measures.metrics import ConfusionMatrix


def test_reader_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    raw_ids = np.array([10, 40, 48, 50, 70, 80, 252, 256, 259, 0, 1, 99, 777])  # incl. moving and unknown ids
    frames, poses = [], []
    for number in range(3):
        count = 50 + number
        points = rng.normal(size=(count, 3)).astype(np.float32)
        truth = rng.choice(raw_ids, count).astype(np.uint32) | (rng.integers(0, 5, count).astype(np.uint32) << 16)
        predicted = rng.choice(raw_ids, count).astype(np.uint32)
        frames.append((points, truth, predicted))
        poses.append(pose_about_z(0.3 * number + 1.0, [5.0 + number, -2.0, 0.3]))
    write_sequence(tmp_path, "04", frames, poses, times=[0.0, 0.1, 0.25])
    dataset = SemanticKittiSequence(tmp_path, "4")
    assert len(dataset) == 3 and dataset.sequence == "04"
    label_map = load_label_map()
    for number, frame in enumerate(dataset):
        points, truth, predicted = frames[number]
        np.testing.assert_array_equal(frame.points, points)
        np.testing.assert_allclose(frame.pose, poses[number], atol=1e-9)
        np.testing.assert_array_equal(frame.ground_truth, label_map.to_learning(truth))
        np.testing.assert_array_equal(frame.input_labels, label_map.to_learning(predicted))
        assert frame.name == f"{number:06d}"
    assert dataset[2].stamp == 0.25
    # Raw ids above 255 keep their classes: 252 moving car -> car, 256 and 259 -> other-vehicle.
    assert label_map.to_learning(np.array([252, 256, 259, 40 | (7 << 16), 777])).tolist() == [1, 5, 5, 9, 0]
    assert not np.allclose(dataset.poses[0], np.eye(4)), "the first pose is taken as written, not as identity"


def test_a_world_point_seen_from_two_poses_lands_in_one_voxel(tmp_path):
    world = np.array([[12.35, -5.67, 0.89], [3.05, 4.07, -1.13]])  # not on voxel faces
    poses = [pose_about_z(0.4, [10.0, -3.0, 0.5]), pose_about_z(-1.1, [14.0, 1.0, 0.7])]
    frames = []
    for pose in poses:
        sensor = (world - pose[:3, 3]) @ pose[:3, :3]  # world -> sensor
        frames.append((sensor.astype(np.float32), np.full(2, 40, np.uint32), np.full(2, 40, np.uint32)))
    write_sequence(tmp_path, "00", frames, poses)
    dataset = SemanticKittiSequence(tmp_path, "00")
    mapped = [frame.points.astype(np.float64) @ frame.pose[:3, :3].T + frame.pose[:3, 3] for frame in dataset]
    np.testing.assert_allclose(mapped[0], world, atol=1e-5)
    np.testing.assert_array_equal(voxel_indices(mapped[0], 0.2), voxel_indices(mapped[1], 0.2))


def make_valid(tmp_path, count=10):
    rng = np.random.default_rng(1)
    frames = [(rng.normal(size=(count, 3)), np.full(count, 40), np.full(count, 40)) for _ in range(2)]
    return write_sequence(tmp_path, "00", frames, [np.eye(4), pose_about_z(0.1, [1, 0, 0])])


@pytest.mark.parametrize("damage, message", [
    (lambda f: (f / "labels" / "000001.label").write_bytes(b"\0" * 4 * 9), "9 labels for 10 points"),
    (lambda f: (f / "predictions" / "000000.label").unlink(), "label file missing"),
    (lambda f: (f / "poses.txt").write_text((f / "poses.txt").read_text().splitlines()[0] + "\n"), "1 poses for 2"),
    (lambda f: (f / "poses.txt").write_text("1 2 3\n1 2 3\n"), "12 finite numbers"),
    (lambda f: (f / "calib.txt").write_text("P0: 1 2 3\n"), "no 'Tr:' line"),
    (lambda f: (f / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 nan 0\n"), "12 finite numbers"),
    (lambda f: (f / "calib.txt").write_text("Tr: 2 0 0 0 0 1 0 0 0 0 1 0\n"), "orthonormal"),
    (lambda f: (f / "velodyne" / "000000.bin").write_bytes(b"\0" * 10), "16-byte points"),
])
def test_broken_sequences_give_clear_errors(tmp_path, damage, message):
    folder = make_valid(tmp_path)
    damage(folder)
    with pytest.raises(DatasetError, match=message):
        dataset = SemanticKittiSequence(tmp_path, "00")
        [dataset[i] for i in range(len(dataset))]


def keep_only(folder, numbers) -> None:
    """Remove every scan (and its labels) of a sequence folder but those numbered ``numbers``:
    what a partial download of a sequence holds beside its whole poses.txt and times.txt."""
    for sub in ("velodyne", "labels", "predictions"):
        for path in (folder / sub).iterdir():
            if int(path.stem) not in numbers:
                path.unlink()


def test_numbered_scans_beside_the_whole_sequence_s_poses_take_pose_k_for_scan_k(tmp_path):
    rng = np.random.default_rng(2)
    poses = [pose_about_z(0.2 * k, [3.0 * k, 1.0 - k, 0.1 * k]) for k in range(6)]
    frames = [(rng.normal(size=(8, 3)), np.full(8, 40), np.full(8, 40)) for _ in poses]
    times = [0.0, 0.11, 0.19, 0.32, 0.41, 0.5]
    folder = write_sequence(tmp_path, "00", frames, poses, times=times)
    whole = SemanticKittiSequence(tmp_path, "00")
    assert whole.notices == []
    keep_only(folder, {1, 3, 4})
    partial = SemanticKittiSequence(tmp_path, "00")
    assert partial.names == ["000001", "000003", "000004"]
    np.testing.assert_allclose(partial.poses, whole.poses[[1, 3, 4]], atol=1e-12)
    np.testing.assert_array_equal(partial.times, [0.11, 0.32, 0.41])
    assert partial.notices == [f"{folder / name}: 6 {what} for 3 numbered scans: row k used for scan k, 3 not used"
                               for name, what in (("poses.txt", "poses"), ("times.txt", "times"))]
    np.testing.assert_allclose(partial[1].pose, poses[3], atol=1e-9)

    # A scan with no row of its own, names that are not numbers, fewer poses than scans: errors.
    (folder / "poses.txt").write_text("".join((folder / "poses.txt").read_text().splitlines(keepends=True)[:4]))
    with pytest.raises(DatasetError, match=r"4 poses, none for scan 000004 \(row 5\)"):
        SemanticKittiSequence(tmp_path, "00")
    (folder / "poses.txt").write_text("".join((folder / "poses.txt").read_text().splitlines(keepends=True)[:2]))
    with pytest.raises(DatasetError, match=r"2 poses for 3 scans$"):
        SemanticKittiSequence(tmp_path, "00")
    folder = write_sequence(tmp_path / "named", "00", frames[:2], poses)
    for sub in ("velodyne", "labels", "predictions"):
        for path in sorted((folder / sub).iterdir()):
            path.rename(path.with_name(f"scan_{path.name}"))
    with pytest.raises(DatasetError, match=r"6 poses for 2 scans, and the scans' names are not their numbers"):
        SemanticKittiSequence(tmp_path / "named", "00")


def test_missing_folders_are_named(tmp_path):
    with pytest.raises(DatasetError, match="dataset folder not found"):
        SemanticKittiSequence(tmp_path / "nowhere", "00")
    make_valid(tmp_path)
    with pytest.raises(DatasetError, match="sequence 07 not found"):
        SemanticKittiSequence(tmp_path, "07")
    with pytest.raises(DatasetError, match="predictions folder not found"):
        SemanticKittiSequence(tmp_path, "00", predictions_dir="rangenet")


def test_frame_ranges():
    assert list(parse_frames("2:5", 10)) == [2, 3, 4]
    assert list(parse_frames(":3", 10)) == [0, 1, 2] and list(parse_frames("8:", 10)) == [8, 9]
    assert list(parse_frames(None, 3)) == [0, 1, 2]
    with pytest.raises(ValueError, match="selects no frame"):
        parse_frames("20:30", 10)


def test_miou_against_a_hand_computed_confusion_matrix():
    # Classes 0 (ignored), 1, 2, 3. Ground truth / prediction pairs:
    truth = np.array([1, 1, 1, 2, 2, 3, 0, 0, 3, 1])
    guess = np.array([1, 1, 2, 2, 1, 3, 2, 1, 0, 3])
    matrix = ConfusionMatrix(4)
    matrix.add(truth[:5], guess[:5])
    matrix.add(truth[5:], guess[5:])  # accumulates over frames
    # Rows with ground truth 0 are dropped. Class 1: TP 2 (pts 0,1), FN 2 (pt 2 -> 2, pt 9 -> 3), FP 1 (pt 4).
    # Class 2: TP 1 (pt 3), FN 1 (pt 4), FP 1 (pt 2). Class 3: TP 1 (pt 5), FN 1 (pt 8 -> 0), FP 1 (pt 9).
    expected = [2 / (2 + 1 + 2), 1 / (1 + 1 + 1), 1 / (1 + 1 + 1)]
    np.testing.assert_allclose(matrix.iou()[1:], expected)
    assert np.isnan(matrix.iou()[0])
    assert matrix.miou() == pytest.approx(np.mean(expected))
    assert matrix.accuracy() == pytest.approx(4 / 8)
    summary = matrix.summary(["unlabeled", "a", "b", "c"])
    assert set(summary["iou"]) == {"a", "b", "c"}


def test_miou_averages_only_classes_present_in_ground_truth():
    matrix = ConfusionMatrix(4)
    matrix.add(np.array([1, 1, 2]), np.array([1, 3, 2]))  # class 3 predicted but never true
    assert matrix.present.tolist() == [False, True, True, False]
    assert matrix.miou() == pytest.approx((0.5 + 1.0) / 2)

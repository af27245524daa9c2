"""Real SemanticKITTI scans through the method: the reader and the poses, the offline mapper
with free space and the movers' rules against plain ConvBKI and the input, and the car's
costmap against the ground truth (skipped, with the reason, where the scans are absent).

The input segmentation is ``label_noise``'s (seed 0, mIoU 0.55): these are not a network's
predictions, and the figures asserted here are the ones measured for that input (docs/evaluation.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import real_sequence

from convbki_core.config import DEFAULTS
from convbki_core.costmap.profile import load_profile
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_calibration, read_poses
from convbki_core.geometry.grid import transform_points
from convbki_core.measures.costmap_eval import GroundTruthVoxels, grids_for, planning_check, road_cells, score_grid
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.paths import kernel_path, traversability_profile
from convbki_core.tools.evaluate_run import evaluate_kernel

STATIC = (13, 14, 15, 16, 18)  # building, fence, vegetation, trunk, pole: upright things that stand still


def static_voxels(frame, edge: float = 0.5, within: float = 40.0) -> set[tuple[int, int, int]]:
    """The ``edge``-metre voxels of a scan's static points within ``within`` m of its sensor, in the map frame."""
    near = np.linalg.norm(frame.points[:, :2], axis=1) < within
    keep = near & np.isin(frame.ground_truth, STATIC)
    points = transform_points(frame.points[keep], frame.pose)
    return set(map(tuple, np.floor(points / edge).astype(np.int64).tolist()))


@pytest.mark.parametrize("sequence", ["00", "01", "05"])
def test_real_scans_are_read_with_their_poses(sequence):
    """Ten scans of about 120,000 points, labels in the learning classes, and poses that put the
    same street in the same place: most of the last scan's static voxels were hit by the first
    scan too, metres behind, where the identity pose would put them elsewhere."""
    root = real_sequence(sequence)
    dataset = SemanticKittiSequence(root, sequence, predictions_dir=None)
    assert len(dataset) == 10 and dataset.notices == []
    first, last = dataset[0], dataset[9]
    assert 100_000 < len(first.points) < 140_000 and first.ground_truth.shape == (len(first.points),)
    assert len(np.unique(first.ground_truth)) >= 8 and first.ground_truth.max() < 20
    # inv(Tr) @ P @ Tr, P from poses.txt as written (not assumed to start at identity).
    calibration = read_calibration(dataset.folder / "calib.txt")
    np.testing.assert_allclose(dataset.poses, read_poses(dataset.folder / "poses.txt", calibration), atol=1e-12)
    travelled = np.linalg.norm(last.pose[:3, 3] - first.pose[:3, 3])
    assert 4.0 < travelled < 10.0, travelled
    early, late = static_voxels(first), static_voxels(last)
    shared = len(early & late) / len(late)
    last.pose = first.pose  # a control: the last scan placed where the first was taken
    misplaced = len(early & static_voxels(last)) / len(late)
    assert shared > 0.6 and misplaced < 0.2, (shared, misplaced)


@pytest.fixture(scope="module")
def noisy(real_noisy):
    """The three real sequences with ``label_noise``'s input segmentation (seed 0, mIoU 0.55):
    ``real_noisy`` (test/conftest.py) writes them once per run."""
    return real_noisy("00", "01", "05")


def mapped(root, sequence: str, **changes):
    """(input scores, the run) of the sequence mapped with the defaults changed by ``changes``."""
    dataset = SemanticKittiSequence(root, sequence)
    input_scores = ConfusionMatrix(dataset.label_map.num_classes, dataset.label_map.ignore_classes)
    truth = GroundTruthVoxels(dataset.label_map.num_classes, 0.2)
    run = evaluate_kernel(dataset, range(len(dataset)), kernel_path("semantic_kitti_compound"),
                          DEFAULTS.replace(device="cpu", **changes), input_scores, None, show_progress=False,
                          moving_labels=bool(changes.get("free_space", True)), truth_voxels=truth)
    return input_scores, run, truth


@pytest.fixture(scope="module")
def street_05(noisy):
    """Sequence 05 mapped with the defaults, once: the comparison with plain ConvBKI and the
    costmap check below both read this run (neither changes it)."""
    return mapped(noisy, "05")


@pytest.mark.parametrize("sequence", ["00", "01", "05"])
def test_the_defaults_map_real_scans_at_least_as_well_as_plain_convbki_and_better_than_the_input(noisy, sequence,
                                                                                                 request):
    """The shipped defaults (free space, clamping, the movers' rules) against plain ConvBKI
    (the paper's sum, no free space) with the same kernel: mIoU and every movable class's
    not-moving IoU at least plain's, mIoU above the input's; on sequence 01 (moving cars on a
    highway) free space leaves under a fifth of plain's trail voxels."""
    input_scores, plain, _ = mapped(noisy, sequence, free_space=False)
    _, defaults, _ = request.getfixturevalue("street_05") if sequence == "05" else mapped(noisy, sequence)
    assert abs(input_scores.miou() - 0.55) < 0.01
    assert defaults.map_scores.miou() >= plain.map_scores.miou() - 0.002, (defaults.map_scores.miou(),
                                                                          plain.map_scores.miou())
    assert defaults.map_scores.miou() >= input_scores.miou() + 0.02
    for c in np.flatnonzero(defaults.static_map_scores.present):
        if c in (1, 4, 5, 6, 7, 8):  # the movable classes, parked or standing
            assert defaults.static_map_scores.iou()[c] >= plain.static_map_scores.iou()[c] - 0.01, c
    if sequence == "01":
        assert plain.trail_voxels > 5000 and defaults.trail_voxels < 0.2 * plain.trail_voxels


def test_the_car_costmap_of_a_real_street_finds_its_obstacles_and_keeps_the_road_free(noisy, street_05):
    """Sequence 05 mapped with the defaults, the car profile's grid against the ground truth's
    (docs/costmap.md): the road is free where the truth says so and nothing a path crosses is
    an obstacle in the truth; the obstacles are found."""
    _, run, truth = street_05
    profile = load_profile(traversability_profile("car"), SemanticKittiSequence(noisy, "05").label_map.class_names)
    indices, alpha = run.mapper.items()
    grids = grids_for(indices, alpha, truth, 0.2, run.mapper.prior, profile)
    road = road_cells(truth, grids["truth"], 9)
    scores = score_grid(grids["map"].values, grids["truth"].values)
    check = planning_check(grids["map"].values, grids["truth"].values, road).summary()
    assert scores.precision["free"] > 0.9 and scores.recall["free"] > 0.9, scores
    assert scores.recall["lethal"] > 0.95, scores
    assert check["planned_on_both"] >= 15 and check["crossing_truth_lethal"] == 0, check

"""Scores and the planning check of costmap_eval on hand-made grids."""

import numpy as np

from convbki_core.measures.costmap_eval import GroundTruthVoxels, _dijkstra, group_of, planning_check, score_grid


def test_groups_free_up_to_25_lethal_from_90():
    assert group_of(np.array([-1, 0, 25, 26, 89, 90, 100])).tolist() == [-1, 0, 0, 1, 1, 2, 2]


def test_scores_count_cells_both_observed_and_the_unknown_share():
    truth = np.array([[0, 0, 100, 95], [0, -1, 100, 0]])
    grid = np.array([[0, 50, 100, -1], [100, 0, 100, 0]])
    scores = score_grid(grid, truth)
    # Both observed: (0,0) free/free, (0,1) costly/free, (0,2) lethal/lethal, (1,0) lethal/free,
    # (1,2) lethal/lethal, (1,3) free/free; (0,3) unknown in the grid: 1 of 7 truth cells.
    assert scores.observed_cells == 6 and abs(scores.unknown_share - 1 / 7) < 1e-12
    assert scores.precision == {"free": 1.0, "costly": 0.0, "lethal": 2 / 3}
    assert scores.recall == {"free": 2 / 4, "costly": None, "lethal": 1.0}


def test_the_planner_goes_round_lethal_and_unknown_cells_and_prefers_cheap_ones():
    grid = np.zeros((5, 7), np.int8)
    grid[0:4, 3] = 100  # a wall with a gap at the top row y = 4
    _, path = _dijkstra(grid, 0, 6, 25.0)  # (0, 0) -> (0, 6)
    ys = path // 7
    assert not np.any(grid.ravel()[path] == 100) and ys.max() == 4
    grid[4, 3] = -1  # the gap unknown: no way through
    assert not np.isfinite(_dijkstra(grid, 0, 6, 25.0)[0])
    costly = np.zeros((3, 5), np.int8)
    costly[1, 1:4] = 50  # the straight middle row is costly: the path takes the row above or below
    _, path = _dijkstra(costly, 5, 9, 25.0)
    assert not np.any(costly.ravel()[path[1:-1]] == 50)


def test_the_planning_check_counts_paths_that_cross_truth_lethal_cells():
    truth = np.zeros((30, 30), np.int8)
    truth[5:30, 15] = 100  # a wall the map does not know
    grid = np.zeros((30, 30), np.int8)
    road = np.zeros((30, 30), bool)
    road[25:30, :] = True
    check = planning_check(grid, truth, road, pairs=10, min_distance=20)
    crossing = check.summary()["crossing_truth_lethal"]
    assert check.pairs == 10 and 0 < crossing <= 10  # pairs on the two sides cross it
    assert planning_check(truth, truth, road, pairs=10, min_distance=20).crossing_lethal == 0


def test_ground_truth_voxels_count_static_points_per_class_inside_the_window():
    truth = GroundTruthVoxels(4, 0.5)
    points = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.1, 0.4], [10.0, 0.0, 0.0], [0.1, 0.3, 0.2]])
    labels = np.array([1, 1, 2, 1, 3])
    moving = np.array([False, False, False, False, True])
    truth.add(points, labels, moving, sensor=np.zeros(3), bounds=((-5, -5, -5), (5, 5, 5)))
    indices, alpha = truth.items()
    assert indices.tolist() == [[0, 0, 0]] and alpha.tolist() == [[0.0, 2.0, 1.0, 0.0]]

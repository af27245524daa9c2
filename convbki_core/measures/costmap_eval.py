"""Scoring a costmap against the ground truth, and the planning check.

* **The ground-truth grid** is made the same way as the map's (``costmap.column_costs``) from
  the ground-truth labels of every frame's points, counted per voxel (one point, one unit of
  evidence of its class), without the points of moving objects: a car that drove by is no
  obstacle where it once was. Its costs have no risk margin: the truth is not uncertain.
* **Class groups** of a cost, as a planner reads them: free (<= ``FREE_MAX``, map_server's
  free threshold), lethal (>= ``LETHAL_MIN``: what stands in the robot's way, 100 in a
  profile, less the doubt of a map that is not quite sure) and costly between (the
  profiles' 50-70 surfaces, a car's sidewalk).
  Per group, precision and recall over the cells observed in the ground truth; the share of
  those cells the map leaves unknown.
* **The input's grid**: the input segmentation's labels of the same static points, counted and
  costed as the ground truth's are. It is what the segmentation alone says of the scene, with
  nothing moving and no mapping: the map's scores against it tell the errors the map adds or
  removes from those it inherits (a sidewalk the network calls parking is free in both).
* **The baseline** users have today: octomap_server's projected occupancy, any non-empty
  evidence in the robot's height band lethal, observed ground free, no classes; computed by
  the same column rules with a profile whose every non-ground class is lethal.
* **The planning check**: shortest paths (Dijkstra, 8-connected, the robot as a point, each
  step's length weighted by 1 + cost / ``COST_WEIGHT``; lethal and unknown cells blocked)
  between pairs of ground-truth road cells, on the map's grid and on the ground truth's. A
  path on the map's grid must never cross a ground-truth lethal cell; its length is compared
  with the ground-truth path's.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field, replace

import numba
import numpy as np

from convbki_core.costmap.columns import UNKNOWN, column_costs
from convbki_core.costmap.grid import CostGrid, rasterise
from convbki_core.costmap.profile import FREE_MAX, LETHAL, LETHAL_MIN, TraversabilityProfile

COST_WEIGHT = 25.0
GROUPS = ("free", "costly", "lethal")


def group_of(values: np.ndarray) -> np.ndarray:
    """0 free, 1 costly, 2 lethal, -1 unknown, per cell."""
    values = np.asarray(values)
    return np.where(values < 0, -1, np.where(values <= FREE_MAX, 0, np.where(values >= LETHAL_MIN, 2, 1)))


class GroundTruthVoxels:
    """Labels of every frame's static points, counted per voxel: the ground truth's, or the
    input segmentation's for the input's grid."""

    def __init__(self, num_classes: int, resolution: float):
        self.num_classes = num_classes
        self.resolution = resolution
        self.counts: dict[int, np.ndarray] = {}
        self._keys: list[np.ndarray] = []

    def add(self, points_map: np.ndarray, labels: np.ndarray, moving: np.ndarray | None = None,
            sensor: np.ndarray | None = None, bounds=None) -> None:
        """One frame's points in the map frame and their labels; ``moving``: the movers' mask (left
        out); ``sensor`` and ``bounds`` ((min xyz), (max xyz) around it): only the points the
        mapper's window took in count."""
        keep = labels > 0
        if moving is not None:
            keep &= ~moving
        if sensor is not None and bounds is not None:
            relative = points_map - np.asarray(sensor)[:3]
            keep &= np.all((relative >= np.asarray(bounds[0])) & (relative < np.asarray(bounds[1])), axis=1)
        voxels = np.floor(np.asarray(points_map[keep], np.float64) / self.resolution).astype(np.int64)
        self._keys.append(np.column_stack([voxels, labels[keep].astype(np.int64)]))

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """(voxel indices (N, 3), counts per class (N, C) float64)."""
        if not self._keys:
            return np.zeros((0, 3), np.int64), np.zeros((0, self.num_classes))
        rows = np.concatenate(self._keys)
        voxels, where = np.unique(rows[:, :3], axis=0, return_inverse=True)
        alpha = np.zeros((len(voxels), self.num_classes))
        np.add.at(alpha, (where.reshape(-1), rows[:, 3]), 1.0)
        return voxels, alpha


def baseline_profile(profile: TraversabilityProfile) -> TraversabilityProfile:
    """Projected occupancy (octomap_server's projected_map) in the same height band: ground
    free, anything else lethal, no margin."""
    costs = np.full(len(profile.class_costs), float(LETHAL))
    costs[0] = 0.0
    costs[list(profile.ground_classes)] = 0.0
    return replace(profile, class_costs=costs, risk_sigma=0.0)


def truth_profile(profile: TraversabilityProfile) -> TraversabilityProfile:
    """The profile for ground-truth voxels: no margin, and one point is evidence."""
    return replace(profile, risk_sigma=0.0, min_evidence=1.0)


@dataclass
class GroupScores:
    precision: dict = field(default_factory=dict)
    recall: dict = field(default_factory=dict)
    unknown_share: float = 0.0
    observed_cells: int = 0


def score_grid(grid: np.ndarray, truth: np.ndarray) -> GroupScores:
    """Per class group, precision and recall of ``grid`` against ``truth`` (same shape) over the
    cells both observed; the share of the truth's observed cells ``grid`` leaves unknown."""
    mine, theirs = group_of(grid), group_of(truth)
    seen_by_truth = theirs >= 0
    observed = seen_by_truth & (mine >= 0)
    scores = GroupScores(observed_cells=int(observed.sum()))
    scores.unknown_share = float(np.mean(mine[seen_by_truth] < 0)) if seen_by_truth.any() else 0.0
    for number, name in enumerate(GROUPS):
        predicted = observed & (mine == number)
        actual = observed & (theirs == number)
        hits = int((predicted & actual).sum())
        scores.precision[name] = hits / int(predicted.sum()) if predicted.any() else None
        scores.recall[name] = hits / int(actual.sum()) if actual.any() else None
    return scores


@numba.njit(cache=True)
def _dijkstra(values: np.ndarray, start: int, goal: int, weight: float) -> tuple[float, np.ndarray]:
    """(weighted length, the path's cells as flat indices) from ``start`` to ``goal`` on an
    8-connected grid; lethal (>= LETHAL_MIN) and unknown (< 0) cells blocked; (inf, []) when
    no path exists."""
    height, width = values.shape
    flat = values.ravel()
    best = np.full(flat.size, np.inf)
    came = np.full(flat.size, -1, np.int64)
    best[start] = 0.0
    heap = [(0.0, start)]
    steps = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
    while heap:
        cost, cell = heapq.heappop(heap)
        if cell == goal:
            break
        if cost > best[cell]:
            continue
        y, x = cell // width, cell % width
        for dy, dx in steps:
            ny, nx = y + dy, x + dx
            if ny < 0 or nx < 0 or ny >= height or nx >= width:
                continue
            other = ny * width + nx
            value = flat[other]
            if value < 0 or value >= 90:  # LETHAL_MIN
                continue
            step = (1.4142135623730951 if dy and dx else 1.0) * (1.0 + value / weight)
            if cost + step < best[other]:
                best[other] = cost + step
                came[other] = cell
                heapq.heappush(heap, (cost + step, other))
    if not np.isfinite(best[goal]):
        return np.inf, np.zeros(0, np.int64)
    path = [goal]
    while path[-1] != start:
        path.append(came[path[-1]])
    return best[goal], np.array(path[::-1], np.int64)


def path_length(path: np.ndarray, width: int) -> float:
    """Geometric length of a path of flat cell indices, in cells."""
    if len(path) < 2:
        return 0.0
    y, x = np.divmod(path, width)
    return float(np.sum(np.hypot(np.diff(x), np.diff(y))))


@dataclass
class PlanningCheck:
    pairs: int = 0
    planned: int = 0  # pairs with a path on both grids
    crossing_lethal: int = 0  # map paths that cross a ground-truth lethal cell
    length_ratios: list = field(default_factory=list)  # map path length / ground-truth path length

    def summary(self) -> dict:
        ratios = np.asarray(self.length_ratios)
        return {"pairs": self.pairs, "planned_on_both": self.planned, "crossing_truth_lethal": self.crossing_lethal,
                "length_ratio_median": float(np.median(ratios)) if len(ratios) else None,
                "length_ratio_max": float(ratios.max()) if len(ratios) else None,
                "within_5_percent": float(np.mean(ratios <= 1.05)) if len(ratios) else None}


def planning_check(grid: np.ndarray, truth: np.ndarray, road: np.ndarray, pairs: int = 20,
                   seed: int = 0, min_distance: float = 20.0) -> PlanningCheck:
    """Plan between ``pairs`` random pairs of road cells (``road``: a mask, cells at least
    ``min_distance`` cells apart) on ``grid`` and on ``truth``; count crossings of truth-lethal."""
    check = PlanningCheck()
    candidates = np.flatnonzero(road.ravel() & (group_of(grid).ravel() == 0) & (group_of(truth).ravel() == 0))
    if len(candidates) < 2:
        return check
    rng = np.random.default_rng(seed)
    width = grid.shape[1]
    tries = 0
    while check.pairs < pairs and tries < 20 * pairs:
        tries += 1
        a, b = rng.choice(candidates, 2, replace=False)
        if np.hypot(*np.subtract(divmod(a, width), divmod(b, width))) < min_distance:
            continue
        check.pairs += 1
        _, on_truth = _dijkstra(truth, a, b, COST_WEIGHT)
        _, on_map = _dijkstra(grid, a, b, COST_WEIGHT)
        if len(on_map) and np.any(group_of(truth.ravel()[on_map]) == 2):
            check.crossing_lethal += 1
        if len(on_map) and len(on_truth):
            check.planned += 1
            check.length_ratios.append(path_length(on_map, width) / max(path_length(on_truth, width), 1e-9))
    return check


def grids_for(map_indices: np.ndarray, map_alpha: np.ndarray, truth: GroundTruthVoxels, resolution: float,
              prior: float, profile: TraversabilityProfile,
              input_labels: GroundTruthVoxels | None = None) -> dict[str, CostGrid]:
    """The map's, the baseline's and the ground truth's grids on the ground truth's extent, and
    the input's (``input_labels``: the input segmentation's labels of the same points) when given."""
    truth_columns = column_costs(*truth.items(), resolution, truth_profile(profile))
    truth_grid = rasterise(truth_columns, resolution)
    size = truth_grid.values.shape[::-1]
    grids = {"truth": truth_grid}
    if input_labels is not None:
        grids["input"] = rasterise(column_costs(*input_labels.items(), resolution, truth_profile(profile)), resolution,
                                   truth_grid.origin, size)
    for name, used in (("map", profile), ("baseline", baseline_profile(profile))):
        grids[name] = rasterise(column_costs(map_indices, map_alpha, resolution, used, prior), resolution,
                                truth_grid.origin, size)
    # Occupancy is binary: a cell whose band is more likely occupied than not is lethal.
    values = grids["baseline"].values
    grids["baseline"] = replace(grids["baseline"], values=np.where(values < 0, UNKNOWN, np.where(
        values >= LETHAL / 2, LETHAL, 0)).astype(np.int8))
    return grids


def road_cells(truth: GroundTruthVoxels, grid: CostGrid, road_class: int) -> np.ndarray:
    """Cells of ``grid`` whose highest ground-truth point voxel is road."""
    indices, alpha = truth.items()
    mask = np.zeros(grid.values.shape, bool)
    if not len(indices):
        return mask
    top = np.lexsort((indices[:, 2], indices[:, 1], indices[:, 0]))
    indices, alpha = indices[top], alpha[top]
    last = np.r_[np.any(np.diff(indices[:, :2], axis=0) != 0, axis=1), True]
    columns, labels = indices[last, :2], alpha[last].argmax(axis=1)
    local = columns - grid.origin
    inside = (local[:, 0] >= 0) & (local[:, 1] >= 0) & (local[:, 0] < mask.shape[1]) & (local[:, 1] < mask.shape[0])
    chosen = inside & (labels == road_class)
    mask[local[chosen, 1], local[chosen, 0]] = True
    return mask


__all__ = ["UNKNOWN", "GroundTruthVoxels", "grids_for", "planning_check", "road_cells", "score_grid"]

"""Points the input segmentation marks as moving: evidence for the scan that sees them only.

Multi-scan segmentation networks tell a moving car from a parked one (SemanticKITTI's raw ids
252-259: moving-car, moving-person, ...). Such a point says what occupies its voxel now, not
what the voxel is: the car will be elsewhere in the next scan. Fused into the map as every
other point is, it would leave a trail wherever no later ray crosses the space the car
swept (the space behind it, seen from a sensor that follows it, or a car that leaves the
sensor's view). So the mapper keeps moving points out of the map's concentrations and holds
them, for the present scan only, in a layer of their own:

    alpha_now[c, v] = sum over the scan's moving points p in voxel v of y_p[c]

(y_p: the point's one-hot label or its class probabilities). A query of that scan at a voxel
the layer holds reads the layer's most likely class instead of the map's: the voxel's
concentrations describe the space before the mover arrived (the road under it, the air it
now fills), and the mover is what is there now. The next scan replaces the layer. The map
that is saved, merged and published never holds it, so moving objects leave no trail in it,
and without moving labels the mapper is exactly what it was.

A network marks some of a mover's points as moving and not others: it gives a point of a
moving car the static id of its own class ("car" where the car's other points say
"moving-car") or of another movable class ("truck"). Mapped as static, those points leave
the trail the moving ones do not. A moving object moves whole, so ``whole_movers`` finds
every point of a movable class (car, truck, person, ...) that is connected to a moving point
through points of movable classes, each in a cell that touches the next one's (cells of
``JOIN_CELL``; faces, edges or corners), up to ``MOVER_REACH`` metres away, and the mapper
keeps those out of the map as well. A point of a static class next to a mover (the road
under it, a wall beside it) stays static, and so does a parked car that no moving point
touches. The layer holds the marked points only: the label of a point whose motion the
network missed is the less sure one (it often misses the class too), so this scan's query
of its voxel reads the layer where a marked point shares the voxel and the map elsewhere,
as for any other point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.geometry.grid import TOUCHING_OFFSETS, voxel_indices, voxel_keys

# How far (m) a mover's marking spreads through the touching points of movable classes: a
# car's length, so that a mover's mislabelled parts join it and a row of parked cars that
# touch one another is not marked from one end by a mover passing the other.
MOVER_REACH = 5.0
# Points are connected when their cells of this side (m) touch: wider than the gaps between
# a LiDAR's points on a surface seen at a grazing angle (the side of a car passing the sensor),
# narrower than the space between a lane's traffic and the cars parked beside it.
JOIN_CELL = 0.4
_TOUCHING_KEYS = voxel_keys(TOUCHING_OFFSETS) - voxel_keys(np.zeros((1, 3), np.int64))


@dataclass(frozen=True)
class PresentMovers:
    """The present scan's moving points by voxel: ``keys`` (K,) sorted ``voxel_keys``,
    ``alpha`` (K, C) float32 the evidence of each class there."""

    keys: np.ndarray
    alpha: np.ndarray


def present_movers(points_map: np.ndarray, values: np.ndarray, num_classes: int, resolution: float,
                   ignore_classes: tuple[int, ...]) -> PresentMovers:
    """The layer of one scan's moving points (map frame, metres) with their labels (N,) or
    probabilities (N, C); points that are not finite, labels outside 0..C-1, the ignored
    classes and rows that are not finite add nothing."""
    points_map = np.asarray(points_map, np.float64).reshape(-1, 3)
    values = np.asarray(values)
    if values.ndim == 1:
        usable = np.isfinite(points_map).all(axis=1) & (values >= 0) & (values < num_classes)
        evidence = np.zeros((int(usable.sum()), num_classes), np.float32)
        evidence[np.arange(len(evidence)), values[usable].astype(np.int64)] = 1.0
    else:
        usable = np.isfinite(points_map).all(axis=1) & np.isfinite(values).all(axis=1) & (values >= 0).all(axis=1)
        evidence = values[usable].astype(np.float32)
    evidence[:, list(ignore_classes)] = 0.0
    keys, slot = np.unique(voxel_keys(voxel_indices(points_map[usable], resolution)), return_inverse=True)
    alpha = np.zeros((len(keys), num_classes), np.float32)
    np.add.at(alpha, slot.reshape(-1), evidence)
    held = alpha.sum(axis=1) > 0
    return PresentMovers(keys[held], alpha[held])


def labels_now(movers: PresentMovers | None, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For global voxel ``indices`` (N, 3): (the layer's most likely class (N,) int64, -1 where
    the layer does not hold the voxel; whether it holds it (N,) bool)."""
    labels = np.full(len(indices), -1, np.int64)
    if movers is None or not len(movers.keys) or not len(indices):
        return labels, np.zeros(len(indices), bool)
    keys = voxel_keys(indices)
    slot = np.minimum(np.searchsorted(movers.keys, keys), len(movers.keys) - 1)
    held = movers.keys[slot] == keys
    labels[held] = movers.alpha[slot[held]].argmax(axis=1)
    return labels, held


def whole_movers(points: np.ndarray, labels: np.ndarray, moving: np.ndarray,
                 movable_classes: tuple[int, ...]) -> np.ndarray:
    """The points of moving objects: ``moving`` (N,) bool grown to every point (``points``
    (N, 3), one frame, metres; ``labels`` (N,) learning labels) of a movable class connected
    to a moving point through points of movable classes whose ``JOIN_CELL`` cells touch, at
    most ``MOVER_REACH`` away. Labels that are not one per point (probabilities) add none."""
    moving = np.asarray(moving, bool).copy()
    labels = np.asarray(labels)
    if not moving.any() or not movable_classes or labels.ndim != 1:
        return moving
    candidate = np.flatnonzero(np.isin(labels, movable_classes) & ~moving)
    candidate_points = np.asarray(points[candidate], np.float64)
    finite = np.isfinite(candidate_points).all(axis=1)
    candidate, candidate_points = candidate[finite], candidate_points[finite]
    if not len(candidate):
        return moving
    moving_points = np.asarray(points[moving], np.float64)
    moving_points = moving_points[np.isfinite(moving_points).all(axis=1)]
    # Cells, not points: the marking walks from the moving points' cells through the cells
    # holding candidate points, one ring of touching cells a step. A neighbour's key is the
    # cell's key plus the offset's (the key is linear in the index within its range).
    marked = np.unique(voxel_keys(voxel_indices(moving_points, JOIN_CELL)))
    candidate_keys = voxel_keys(voxel_indices(candidate_points, JOIN_CELL))
    waiting = np.unique(candidate_keys)
    joined = []
    for _ in range(int(np.ceil(MOVER_REACH / JOIN_CELL))):
        # Each waiting cell looks for a marked one among its neighbours.
        around = (waiting[:, None] + _TOUCHING_KEYS[None, :]).reshape(-1)
        slot = np.minimum(np.searchsorted(marked, around), len(marked) - 1)
        reached = (marked[slot] == around).reshape(len(waiting), -1).any(axis=1)
        if not reached.any():
            break
        joined.append(waiting[reached])
        marked = waiting[reached]  # sorted: the next ring grows from the cells just joined
        waiting = waiting[~reached]
        if not len(waiting):
            break
    if joined:
        moving[candidate[np.isin(candidate_keys, np.concatenate(joined))]] = True
    return moving

"""Trail voxels: what moving objects leave behind in a map.

A mover's points mark the space it swept, scan after scan. Once it has gone, a map that
still shows a movable class (car, person, ...) there shows a trail. Counted from the
ground truth alone, so any dataset whose labels mark moving objects can be scored
(SemanticKITTI's raw ids 252-259):

* swept: the voxels holding a moving point in any scan, grown by one voxel on every side
  (the kernel spreads a point's evidence to its neighbours);
* present at the end: the same, for the last scan's moving points;
* trail voxels: voxels of the map whose expected class is movable, in swept space and not
  in space a mover occupies at the end.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from convbki_core.geometry.grid import TOUCHING_OFFSETS, voxel_indices, voxel_keys


def _grown(indices: np.ndarray) -> np.ndarray:
    """Keys of the voxels and their 26 neighbours, unique."""
    if len(indices) == 0:
        return np.zeros(0, np.int64)
    return np.unique(voxel_keys((indices[:, None, :] + TOUCHING_OFFSETS[None]).reshape(-1, 3)))


class SweptSpace:
    """The space moving objects passed through during a drive, and where they are at its end."""

    def __init__(self, resolution: float):
        self.resolution = float(resolution)
        self._swept: list[np.ndarray] = []
        self._last = np.zeros((0, 3), np.int64)
        self.moving_points = 0

    def add(self, points_map: np.ndarray, moving: np.ndarray) -> None:
        """One scan: its points in the map frame and which of them belong to moving objects."""
        indices = np.unique(voxel_indices(points_map[moving], self.resolution), axis=0)
        self._swept.append(indices)
        self._last = indices
        self.moving_points += int(np.count_nonzero(moving))

    def trail_voxels(self, indices: np.ndarray, labels: np.ndarray, movable_classes: Sequence[int]) -> int:
        """How many of the map's voxels (global ``indices`` (N, 3) with expected class
        ``labels``) show a movable class where a mover was but is not at the end."""
        if not self._swept:
            return 0
        swept = _grown(np.concatenate(self._swept))
        present = _grown(self._last)
        candidates = np.isin(labels, np.asarray(movable_classes, np.int64))
        keys = voxel_keys(indices[candidates])
        return int(np.count_nonzero(np.isin(keys, swept) & ~np.isin(keys, present)))


class StaticCoverage:
    """What forgetting must not cost: the share of the static world the final map still shows.

    Every ``every``-th scan's static ground-truth points (labelled, not moving) are kept by
    voxel; at the end, the share of them whose voxel the map shows (its expected class is
    not class 0, the empty space of free space) is the static coverage. A rule that empties
    trails by also emptying walls and parked cars loses coverage; plain ConvBKI, which never
    empties anything, is the reference.
    """

    def __init__(self, resolution: float, every: int = 10):
        self.resolution = float(resolution)
        self.every = int(every)
        self._scans = 0
        self._keys: list[np.ndarray] = []

    def add(self, points_map: np.ndarray, ground_truth: np.ndarray, moving: np.ndarray | None) -> None:
        """One scan, in order: its points in the map frame, ground-truth learning labels and
        moving flags (None: the ground truth marks no movers)."""
        if self._scans % self.every == 0:
            static = ground_truth != 0
            if moving is not None:
                static &= ~moving
            static &= np.isfinite(points_map).all(axis=1)
            self._keys.append(voxel_keys(voxel_indices(points_map[static], self.resolution)))
        self._scans += 1

    @property
    def points(self) -> int:
        return int(sum(len(keys) for keys in self._keys))

    def coverage(self, indices: np.ndarray, labels: np.ndarray) -> float | None:
        """The share of the kept points in voxels of the map (global ``indices`` (N, 3),
        expected class ``labels``) that it shows; None before any point was kept."""
        if not self.points:
            return None
        shown = voxel_keys(indices[labels != 0])
        return float(np.isin(np.concatenate(self._keys), shown).mean())

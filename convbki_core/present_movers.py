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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from convbki_core.volume import voxel_indices, voxel_keys


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

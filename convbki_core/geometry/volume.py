"""The input volume F (paper Eq. 3): a labelled scan voxelised into the local window.

F[c, v] is the sum over the points inside voxel v of their class evidence y_c: a one-hot
label, or a probability vector. Probability vectors can first be calibrated by a temperature
T (Guo et al., 2017: p' = softmax(log p / T), the kernel file's ``temperature``; a row keeps
its sum): a network whose softmax is too soft (under-confident) gets T < 1, one too sharp
T > 1. T = 1 (or None) leaves the rows exactly as given and costs nothing.

The window's geometry and the voxel index helpers are in ``grid``; here the scan's checks,
the tempering of probabilities, and the voxeliser: a numpy reference (``voxelize``) and the
compiled pass that must equal it (``voxelize_scan``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.grid import linear_index, voxel_indices

if HAVE_NUMBA:
    from convbki_core.compiled import njit, prange
if TYPE_CHECKING:
    import torch


@dataclass
class VoxelizeStats:
    """What happened to the points of one scan."""

    points_in: int = 0
    used: int = 0
    non_finite: int = 0  # NaN or inf coordinates, or (coordinates finite) a NaN or inf probability
    bad_probabilities: int = 0  # finite probability rows with a negative value or summing to zero
    outside_window: int = 0
    ignored_class: int = 0  # labels in the ignore set (e.g. 0, unlabeled)
    unknown_label: int = 0  # labels outside 0 .. C-1

    @property
    def dropped(self) -> int:
        return self.points_in - self.used


@dataclass
class SparseVolume:
    """The input volume F in sparse form: occupied voxels of one window.

    ``linear`` (M,) int64 sorted unique window-linear indices; ``features`` (M, C) float32
    per-class evidence sums; ``point_linear`` (N,) int64 the voxel of every input point,
    -1 for points that were dropped.
    """

    origin: np.ndarray
    dims: np.ndarray
    linear: np.ndarray
    features: np.ndarray
    point_linear: np.ndarray
    stats: VoxelizeStats = field(default_factory=VoxelizeStats)
    # The occupied voxels' global indices (M, 3) and features (M, C) where the torch update sent
    # them (a GPU), for the free-space pass to walk its rays from without sending them again.
    on_device: tuple | None = None

    @property
    def num_voxels(self) -> int:
        return int(self.linear.shape[0])

    def to_dense(self, device: torch.device | str = "cpu", dtype: torch.dtype | None = None) -> torch.Tensor:
        """Dense F as a (C, X, Y, Z) tensor (float32 unless ``dtype``)."""
        import torch  # here, not at the top: the ROS side's cloud decoder imports this module without torch

        dtype = torch.float32 if dtype is None else dtype
        num_classes = self.features.shape[1]
        dense = torch.zeros(num_classes, int(np.prod(self.dims)), dtype=dtype, device=device)
        if self.num_voxels:
            index = torch.from_numpy(self.linear).to(device)
            dense[:, index] = torch.from_numpy(self.features).to(device=device, dtype=dtype).T
        return dense.view(num_classes, *(int(d) for d in self.dims))


def check_scan(points: np.ndarray, values: np.ndarray, num_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """Raise ``ValueError`` naming the problem unless points are (N, 3) and values (N,) integer
    labels or (N, C) probabilities; returns both as arrays, probabilities as float32.

    Float32 is the precision of the evidence on every path, so both voxelisers judge the
    same values: a probability beyond float32's range becomes inf (its row is then dropped),
    one below its smallest subnormal becomes 0."""
    points = np.asarray(points)
    values = np.asarray(values)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    count = points.shape[0]
    if values.shape[0] != count:
        raise ValueError(f"got {count} points but {values.shape[0]} labels/probabilities")
    if values.ndim == 2 and values.shape[1] != num_classes:
        raise ValueError(f"probabilities must have {num_classes} columns, got {values.shape[1]}")
    if values.ndim not in (1, 2):
        raise ValueError(f"labels must have shape (N,), got {values.shape}")
    if values.ndim == 1 and values.dtype.kind not in "iu":
        raise ValueError(f"labels must be integers, got dtype {values.dtype}")
    if values.ndim == 2 and values.dtype != np.float32:
        if values.dtype.kind not in "biuf":
            raise ValueError(f"probabilities must be numbers, got dtype {values.dtype}")
        with np.errstate(over="ignore"):
            values = values.astype(np.float32)
    return points, values


def tempers(temperature: float | None) -> bool:
    """Whether a temperature changes probability rows (None and 1 leave them as given)."""
    return temperature is not None and float(temperature) != 1.0


def check_temperature(temperature: float | None) -> float | None:
    """``temperature`` as a float (None stays None); ``ValueError`` unless positive and finite."""
    if temperature is None:
        return None
    value = float(temperature)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"temperature must be a positive finite number, got {temperature!r}")
    return value


def temper_probabilities(rows: np.ndarray, temperature: float) -> np.ndarray:
    """s softmax(log p / T) of (N, C) finite, non-negative rows p with a positive sum s, float32.

    The row keeps its total (a normalised row stays normalised, as a network's softmax is), so
    the temperature only reshapes a row and T = 1 is exactly the identity. Computed in float32
    as exp((log p - log max p) / T), normalised: the largest term is 1, so the sum never
    underflows (a row of tiny values sharpened by a small T), and a zero stays exactly zero.
    The compiled voxeliser computes the same formula.
    """
    values = np.asarray(rows, np.float32)
    if values.shape[0] == 0:
        return values.copy()
    inverse = np.float32(1.0 / float(temperature))
    top = np.log(values.max(axis=1, keepdims=True))
    with np.errstate(divide="ignore"):  # log 0 = -inf, and exp(-inf) = 0 exactly
        powered = np.exp((np.log(values) - top) * inverse)
    total = values.sum(axis=1, keepdims=True, dtype=np.float64).astype(np.float32)
    return (powered / powered.sum(axis=1, keepdims=True, dtype=np.float32) * total).astype(np.float32)


def voxelize(points: np.ndarray, values: np.ndarray, origin: np.ndarray, dims: np.ndarray,
             resolution: float, num_classes: int, ignore_classes: tuple[int, ...] = (0,),
             temperature: float | None = None) -> SparseVolume:
    """Build the input volume F of a window from map-frame points (paper Eq. 3).

    ``values`` is either (N,) integer learning labels or (N, C) class probabilities.
    Points with non-finite coordinates, points outside the window, labels in
    ``ignore_classes`` and labels outside 0..C-1 are dropped and counted. With
    probabilities, rows holding a NaN/inf (counted as ``non_finite``) and rows holding a
    negative value or summing to zero (``bad_probabilities``) are dropped, the remaining rows
    are calibrated by ``temperature`` (module docstring; over all C columns) and then the
    columns of ``ignore_classes`` are zeroed (they carry no evidence).
    """
    points, values = check_scan(points, values, num_classes)
    temperature = check_temperature(temperature)
    origin = np.asarray(origin, dtype=np.int64)
    dims = np.asarray(dims, dtype=np.int64)
    count = points.shape[0]
    with_probabilities = values.ndim == 2

    stats = VoxelizeStats(points_in=count)
    keep = np.isfinite(points).all(axis=1)
    if with_probabilities:
        non_finite, negative, zero_sum = bad_probability_rows(values)
        keep &= ~non_finite
        bad = keep & (negative | zero_sum)
        stats.bad_probabilities = int(bad.sum())
        stats.non_finite = int(count - keep.sum())
        keep &= ~bad
    else:
        stats.non_finite = int(count - keep.sum())

    if not with_probabilities:
        labels = values.astype(np.int64, copy=False)
        known = (labels >= 0) & (labels < num_classes)
        stats.unknown_label = int((keep & ~known).sum())
        keep &= known
        ignored = np.isin(labels, np.asarray(ignore_classes, dtype=np.int64))
        stats.ignored_class = int((keep & ignored).sum())
        keep &= ~ignored

    local = np.zeros((count, 3), np.int64)
    local[keep] = voxel_indices(points[keep], resolution) - origin
    inside = keep & (local >= 0).all(axis=1) & (local < dims).all(axis=1)
    stats.outside_window = int((keep & ~inside).sum())
    stats.used = int(inside.sum())

    point_linear = np.full(count, -1, np.int64)
    point_linear[inside] = linear_index(local[inside], dims)
    used_linear = point_linear[inside]
    linear, inverse = np.unique(used_linear, return_inverse=True)
    if with_probabilities:
        evidence = values[inside].astype(np.float32, copy=True)
        if tempers(temperature):
            evidence = temper_probabilities(evidence, temperature)
        evidence[:, list(ignore_classes)] = 0.0
        # Group the points of each voxel together and sum each group (much faster than np.add.at).
        order = np.argsort(inverse, kind="stable")
        starts = np.searchsorted(inverse[order], np.arange(linear.shape[0]))
        features = np.add.reduceat(evidence[order], starts, axis=0) if linear.size else evidence[:0]
    else:
        pairs = inverse * num_classes + labels[inside]
        features = np.bincount(pairs, minlength=linear.shape[0] * num_classes)
        features = features.reshape(linear.shape[0], num_classes).astype(np.float32)
    return SparseVolume(origin, dims, linear, features, point_linear, stats)


def bad_probability_rows(probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of (N, C) class ``probabilities`` that are no evidence, as three disjoint (N,) bool masks:
    rows holding a NaN/inf; finite rows holding a negative value; finite non-negative rows
    summing to zero (all zero)."""
    # Each row's minimum and maximum (with 0) find all three: NaN propagates through both,
    # -inf shows in the minimum and +inf in the maximum, and a non-negative row sums to zero
    # exactly when its maximum is zero. Column by column, because numpy reduces a short
    # inner axis (C classes) one row at a time, far slower than elementwise passes over N.
    lowest = np.zeros(probabilities.shape[0], probabilities.dtype)
    highest = np.zeros(probabilities.shape[0], probabilities.dtype)
    for column in probabilities.T:
        np.minimum(lowest, column, out=lowest)
        np.maximum(highest, column, out=highest)
    non_finite = ~(np.isfinite(lowest) & np.isfinite(highest))
    negative = ~non_finite & (lowest < 0)
    zero_sum = ~non_finite & ~negative & (highest <= 0)
    return non_finite, negative, zero_sum


if HAVE_NUMBA:

    @njit(nogil=True, parallel=True)
    def _point_voxels(points, pose, labels, probabilities, use_probabilities, origin, dims, resolution,
                      ignored):  # pragma: no cover - compiled; tested through voxelize_scan
        """Each point's window-linear voxel, or -1 - k when it is dropped for reason k of
        ``_voxelize_numba``'s stats. Points are independent here, so every core takes a share."""
        count = points.shape[0]
        num_classes = ignored.shape[0]
        code = np.empty(count, np.int64)
        for i in prange(count):
            x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                code[i] = -1
                continue
            if use_probabilities:
                # One pass over the row decides what bad_probability_rows decides. A
                # float64 sum of float32 values cannot overflow, so it is finite exactly when
                # every value is; with no negative value it is positive exactly when one value is.
                total = 0.0
                lowest = np.float32(0.0)
                for c in range(num_classes):
                    p = probabilities[i, c]
                    total += p
                    lowest = min(lowest, p)
                if not np.isfinite(total):
                    code[i] = -1
                    continue
                if lowest < 0 or not total > 0:
                    code[i] = -5
                    continue
            else:
                label = labels[i]
                if label < 0 or label >= num_classes:
                    code[i] = -2
                    continue
                if ignored[label]:
                    code[i] = -3
                    continue
            # Same operation order as grid.transform_points: identical rounding, identical voxels.
            vx = np.int64(np.floor((((x * pose[0, 0] + y * pose[0, 1]) + z * pose[0, 2]) + pose[0, 3]) / resolution))
            vy = np.int64(np.floor((((x * pose[1, 0] + y * pose[1, 1]) + z * pose[1, 2]) + pose[1, 3]) / resolution))
            vz = np.int64(np.floor((((x * pose[2, 0] + y * pose[2, 1]) + z * pose[2, 2]) + pose[2, 3]) / resolution))
            lx, ly, lz = vx - origin[0], vy - origin[1], vz - origin[2]
            if lx < 0 or ly < 0 or lz < 0 or lx >= dims[0] or ly >= dims[1] or lz >= dims[2]:
                code[i] = -4
                continue
            code[i] = (lx * dims[1] + ly) * dims[2] + lz
        return code

    @njit(nogil=True)
    def _radix_sort(values, bound):  # pragma: no cover - compiled; tested against np.sort
        """``values`` (distinct, 0 <= v < bound) sorted: least significant digit first, 11 bits a
        pass, so a window of up to 2^22 voxels takes two counting passes over the voxels instead
        of a comparison sort."""
        bits, passes = 11, 1
        while (1 << (bits * passes)) < bound:
            passes += 1
        source = values.copy()
        target = np.empty_like(values)
        counts = np.empty(1 << bits, np.int64)
        for number in range(passes):
            shift = bits * number
            counts[:] = 0
            for v in source:
                counts[(v >> shift) & ((1 << bits) - 1)] += 1
            start = 0
            for digit in range(counts.size):
                counts[digit], start = start, start + counts[digit]
            for v in source:
                digit = (v >> shift) & ((1 << bits) - 1)
                target[counts[digit]] = v
                counts[digit] += 1
            source, target = target, source
        return source

    @njit(nogil=True)
    def _voxelize_numba(points, pose, labels, probabilities, use_probabilities, origin, dims, resolution,
                        ignored, slot):  # pragma: no cover - compiled; tested through voxelize_scan
        """(occupied voxels in increasing window-linear order, their (M, C) features, each point's
        voxel or -1, dropped-point counts: non-finite, unknown label, ignored class, outside the
        window, bad probabilities). ``slot``: the caller's scratch table, left all -1."""
        count = points.shape[0]
        num_classes = ignored.shape[0]
        code = _point_voxels(points, pose, labels, probabilities, use_probabilities, origin, dims, resolution,
                             ignored)
        stats = np.zeros(5, np.int64)
        point_linear = np.full(count, -1, np.int64)
        occupied = np.empty(count, np.int64)
        used = 0
        for i in range(count):
            linear = code[i]
            if linear < 0:
                stats[-1 - linear] += 1
                continue
            point_linear[i] = linear
            if slot[linear] < 0:
                slot[linear] = 0
                occupied[used] = linear
                used += 1
        occupied = _radix_sort(occupied[:used], dims[0] * dims[1] * dims[2])
        for m in range(used):  # rows in voxel order: the features need no reordering
            slot[occupied[m]] = m
        features = np.zeros((used, num_classes), np.float32)
        for i in range(count):
            linear = point_linear[i]
            if linear < 0:
                continue
            s = slot[linear]
            if use_probabilities:
                for c in range(num_classes):
                    if not ignored[c]:
                        features[s, c] += probabilities[i, c]
            else:
                features[s, labels[i]] += 1.0
        for m in range(used):  # leave the scratch table clean for the next scan
            slot[occupied[m]] = -1
        return occupied, features, point_linear, stats


if HAVE_NUMBA:

    # Not "fastmath=True": the row check below relies on NaN and inf comparing as they should.
    @njit(nogil=True, parallel=True, fastmath={"afn", "arcp", "contract", "nsz"})
    def _temper_numba(probabilities, inverse_temperature):  # pragma: no cover - compiled; tested against numpy
        """``temper_probabilities`` of every row the voxeliser would keep (finite, no negative
        value, a positive sum), on every core; other rows are copied unchanged, so the
        voxeliser judges and counts them as it would without a temperature."""
        count, num_classes = probabilities.shape
        out = np.empty_like(probabilities)
        inverse = np.float32(inverse_temperature)
        for i in prange(count):
            total = 0.0
            lowest = np.float32(0.0)
            top = np.float32(0.0)
            for c in range(num_classes):
                p = probabilities[i, c]
                total += p
                lowest = min(lowest, p)
                top = max(top, p)
            if not np.isfinite(total) or lowest < 0 or not total > 0:
                for c in range(num_classes):
                    out[i, c] = probabilities[i, c]
                continue
            log_top = np.float32(math.log(top))
            powered_sum = np.float32(0.0)
            for c in range(num_classes):
                p = probabilities[i, c]
                powered = np.float32(math.exp((np.float32(math.log(p)) - log_top) * inverse)) if p > 0 else \
                    np.float32(0.0)
                out[i, c] = powered
                powered_sum += powered
            scale = np.float32(total)
            for c in range(num_classes):
                out[i, c] = out[i, c] / powered_sum * scale
        return out


def voxelize_scan(points: np.ndarray, values: np.ndarray, pose: np.ndarray, origin: np.ndarray, dims: np.ndarray,
                  resolution: float, num_classes: int, ignore_classes: tuple[int, ...], slot: np.ndarray,
                  temperature: float | None = None):
    """``voxelize(transform_points(points, pose), values, ...)`` in one compiled pass.

    ``slot`` is a scratch int32 table of the window's size, all -1 (left so on return): it
    finds each voxel's row without sorting the points. The points' voxels are computed on
    every core; the voxels found are put in window order by a radix sort (a few counting
    passes over the voxels, not the points), and the points are summed into their rows in
    point order. Probabilities are judged and summed
    in float32, as ``voxelize`` does; with a ``temperature`` other than 1 the kept rows are
    calibrated first (a compiled pass on every core). Returns a ``SparseVolume``
    equal to the numpy path's (same voxels, same sums, same counts).
    """
    temperature = check_temperature(temperature)
    with_probabilities = values.ndim == 2
    ignored = np.zeros(num_classes, np.bool_)
    ignored[[c for c in ignore_classes if 0 <= c < num_classes]] = True
    labels = np.zeros(0, np.int64) if with_probabilities else np.ascontiguousarray(values, np.int64)
    with np.errstate(over="ignore"):  # beyond float32: inf, then dropped (as check_scan does)
        probabilities = (np.ascontiguousarray(values, np.float32) if with_probabilities
                         else np.zeros((0, num_classes), np.float32))
    points = np.ascontiguousarray(points)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    with parallel_region():
        if with_probabilities and tempers(temperature):
            probabilities = _temper_numba(probabilities, 1.0 / temperature)
        occupied, features, point_linear, counts = _voxelize_numba(
            points, np.ascontiguousarray(pose, np.float64), labels, probabilities, with_probabilities,
            np.ascontiguousarray(origin, np.int64), np.ascontiguousarray(dims, np.int64), float(resolution), ignored,
            slot)
    stats = VoxelizeStats(points_in=len(points), non_finite=int(counts[0]), unknown_label=int(counts[1]),
                          ignored_class=int(counts[2]), outside_window=int(counts[3]),
                          bad_probabilities=int(counts[4]))
    stats.used = (stats.points_in - stats.non_finite - stats.bad_probabilities - stats.unknown_label
                  - stats.ignored_class - stats.outside_window)
    return SparseVolume(np.asarray(origin, np.int64), np.asarray(dims, np.int64), occupied, features,
                        point_linear, stats)

"""The ConvBKI update applied to the resident window: a compiled sparse scatter (the CPU path)
and the paper's dense convolution (the reference and the GPU path), with one signature.

The dense update convolves every voxel of the 400 x 400 x 26 x 20 window, but only about
1 % of the window holds points. Written as a scatter, Eq. 4 is: every occupied voxel v
adds F[v, c] * K[c, tap] to the voxel at v + half - tap, for each class c with evidence
and each tap whose weight is non-zero. That is what runs here, compiled with numba:

* the window is stored class-major (alpha[c, x, y, z]) and the scatter runs class by class,
  so the writes of one class stay in one 16 MB plane and neighbouring taps hit
  neighbouring cache lines;
* zero taps are skipped: each filter row along z is visited only between its first and
  last non-zero tap (a learned length of 0.3 m leaves 7 of the 125 taps of f = 5 in use);
* each voxel's target positions on the torus are computed once, not once per class;
* the window is a torus (global voxel g lives at g mod dims), so moving the window never
  copies it (``window.RollingWindow``);
* the two cores split the window's x range: each writes only its own half, so there are no
  races and no atomics;
* voxels that receive evidence are marked in a byte mask (the map's "stored" set).

The result equals the dense reference to float32 rounding (tested against the dense layer
and a brute-force sum). Without numba (no compiler wheel for the platform) the same scatter
runs as vectorised numpy, much slower, after one log line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from convbki_core.compiled import HAVE_NUMBA, parallel_region
from convbki_core.geometry.grid import unravel_linear
from convbki_core.geometry.volume import SparseVolume
from convbki_core.inference.layer import ConvBKILayer
from convbki_core.memory.window import CHANGED, EVIDENCE

if HAVE_NUMBA:
    import numba

    from convbki_core.compiled import njit, prange

@dataclass(frozen=True)
class FilterPlan:
    """The filters as the compiled scatter reads them, prepared once per kernel.

    ``k_lo``/``k_hi`` (C, f, f): the first and one-past-last non-zero tap of each filter row
    along z, so zero taps (a short class length leaves most of the 5^3 taps empty) cost
    nothing; a zero tap inside a row adds exactly 0. ``support`` (C, f^3) uint8: the taps
    whose weight is non-zero, from which the voxels that receive evidence are marked.
    """

    filters: np.ndarray
    k_lo: np.ndarray
    k_hi: np.ndarray
    support: np.ndarray

    @classmethod
    def from_filters(cls, filters: np.ndarray) -> FilterPlan:
        filters = np.ascontiguousarray(filters, np.float32)
        nonzero = filters > 0
        size = filters.shape[1]
        has_any = nonzero.any(axis=3)
        k_lo = np.where(has_any, nonzero.argmax(axis=3), size).astype(np.int64)
        k_hi = np.where(has_any, size - nonzero[..., ::-1].argmax(axis=3), 0).astype(np.int64)
        support = np.ascontiguousarray(nonzero.reshape(filters.shape[0], -1), np.uint8)
        return cls(filters, k_lo, k_hi, support)


if HAVE_NUMBA:

    @njit(nogil=True, inline="always")
    def _targets_in_part(target, m, x_begin, x_end, px):  # pragma: no cover - compiled
        """px[i]: voxel m's i-th x target if it lies in this thread's planes [x_begin, x_end), else -1.
        Returns whether any does (else the voxel is another thread's work)."""
        any_x = False
        for i in range(px.size):
            p = target[m, 0, i]
            px[i] = p if x_begin <= p < x_end else -1
            any_x = any_x or px[i] >= 0
        return any_x

    @njit(parallel=True, nogil=True)  # nogil: ROS callbacks keep running during an update
    def _scatter_numba(occupied, features, filters, k_lo, k_hi, support, origin, dims, alpha, mask,
                       parts, marks):  # pragma: no cover - compiled; tested through scatter_update
        num_voxels = occupied.shape[0]
        num_classes = features.shape[1]
        size = filters.shape[1]
        half = size // 2
        # Torus position of each voxel's f targets along each axis (-1: outside the window),
        # computed once: the class loop below would otherwise repeat these modulos C times.
        target = np.empty((num_voxels, 3, size), np.int32)
        for m in prange(num_voxels):
            for axis in range(3):
                for i in range(size):
                    t = occupied[m, axis] + half - i
                    target[m, axis, i] = t % dims[axis] if origin[axis] <= t < origin[axis] + dims[axis] else -1
        new_counts = np.zeros(parts, np.int64)
        for part in prange(parts):
            # This thread writes only physical x planes in [x_begin, x_end): no two threads share a voxel.
            x_begin = dims[0] * part // parts
            x_end = dims[0] * (part + 1) // parts
            created = 0
            px = np.empty(size, np.int64)
            union = np.empty(size * size * size, np.uint8)
            # Class by class: the writes of one class stay in its own plane of the window, and
            # each window voxel receives its additions in voxel order (the dense result's rounding).
            for c in range(num_classes):
                for m in range(num_voxels):
                    value = features[m, c]
                    if value == 0.0:
                        continue
                    if not _targets_in_part(target, m, x_begin, x_end, px):
                        continue
                    for i in range(size):
                        x = px[i]
                        if x < 0:
                            continue
                        for j in range(size):
                            y = target[m, 1, j]
                            if y < 0:
                                continue
                            for k in range(k_lo[c, i, j], k_hi[c, i, j]):
                                z = target[m, 2, k]
                                if z >= 0:
                                    alpha[c, x, y, z] += value * filters[c, i, j, k]
            # Mark the voxels that received evidence: the union of the present classes' supports.
            for m in range(num_voxels):
                if not _targets_in_part(target, m, x_begin, x_end, px):
                    continue
                union[:] = 0
                for c in range(num_classes):
                    if features[m, c] != 0.0:
                        for t in range(union.size):
                            union[t] |= support[c, t]
                for i in range(size):
                    x = px[i]
                    if x < 0:
                        continue
                    for j in range(size):
                        y = target[m, 1, j]
                        if y < 0:
                            continue
                        for k in range(size):
                            z = target[m, 2, k]
                            if z >= 0 and union[(i * size + j) * size + k] != 0:
                                current = mask[x, y, z]
                                if current & marks != marks:  # write only what changes: no dirty lines
                                    if current == 0:
                                        created += 1
                                    mask[x, y, z] = current | marks
            new_counts[part] = created
        return new_counts.sum()


def _scatter_numpy(occupied, features, filters, origin, dims, alpha, mask, marks=EVIDENCE | CHANGED) -> int:
    """The same scatter with numpy, one tap at a time (the fallback without numba)."""
    size = filters.shape[1]
    half = size // 2
    before = int(np.count_nonzero(mask))
    for i in range(size):
        for j in range(size):
            for k in range(size):
                weights = filters[:, i, j, k]
                if not (weights > 0).any():
                    continue
                target = occupied + np.array([half - i, half - j, half - k])
                inside = ((target >= origin) & (target < origin + dims)).all(axis=1)
                contribution = features[inside] * weights
                has = (contribution > 0).any(axis=1)
                physical = np.mod(target[inside][has], dims)
                flat = np.ravel_multi_index(physical.T, tuple(dims))
                plane = alpha.reshape(alpha.shape[0], -1)
                for c in np.flatnonzero(weights > 0):
                    np.add.at(plane[c], flat, contribution[has, c])
                mask.reshape(-1)[flat] |= np.uint8(marks)
    return int(np.count_nonzero(mask)) - before


def scatter_update(occupied: np.ndarray, features: np.ndarray, filters: np.ndarray | FilterPlan, origin: np.ndarray,
                   dims: np.ndarray, alpha: np.ndarray, mask: np.ndarray, marks: int = EVIDENCE | CHANGED) -> int:
    """Add conv3d(F, K) of the occupied voxels into the torus window, in place.

    ``occupied`` (M, 3) int64 global voxel indices with ``features`` (M, C) float32;
    ``filters`` (C, f, f, f) float32, or a ``FilterPlan`` of them (prepare it once per
    kernel); the window covers global indices origin .. origin + dims - 1 (zero padding
    beyond), stored at index mod dims in ``alpha`` (C, X, Y, Z) float32 and ``mask``
    (X, Y, Z) uint8, which gets the bits ``marks`` where evidence arrives.
    Returns the number of voxels that received evidence for the first time.
    """
    plan = filters if isinstance(filters, FilterPlan) else FilterPlan.from_filters(filters)
    occupied = np.ascontiguousarray(occupied, np.int64)
    features = np.ascontiguousarray(features, np.float32)
    origin = np.ascontiguousarray(origin, np.int64)
    dims = np.ascontiguousarray(dims, np.int64)
    if occupied.shape[0] == 0:
        return 0
    if HAVE_NUMBA:
        parts = max(1, min(numba.get_num_threads(), int(dims[0])))
        with parallel_region():
            return int(_scatter_numba(occupied, features, plan.filters, plan.k_lo, plan.k_hi, plan.support, origin,
                                      dims, alpha, mask, parts, np.uint8(marks)))
    return _scatter_numpy(occupied, features, plan.filters, origin, dims, alpha, mask, marks)


# Both ways to apply one scan's input volume F to the resident window share one signature:
# (volume, filters, alpha, mask, marks) -> the number of voxels that received their first evidence;
# ``marks``: the mask bits set where evidence arrives.


def scatter_volume(volume: SparseVolume, plan: FilterPlan, alpha: np.ndarray, mask: np.ndarray,
                   marks: int = EVIDENCE | CHANGED) -> int:
    """The sparse compiled scatter of ``volume`` into the torus window (``alpha``, ``mask``)."""
    occupied = unravel_linear(volume.linear, volume.dims) + volume.origin
    return scatter_update(occupied, volume.features, plan, volume.origin, volume.dims, alpha, mask, marks)


def dense_volume(volume: SparseVolume, layer: ConvBKILayer, alpha: np.ndarray, mask: np.ndarray,
                 marks: int = EVIDENCE | CHANGED) -> int:
    """The paper's dense depthwise convolution over the whole window, on the layer's device.

    Voxels are marked as the scatter marks them: where a class present in F has a non-zero
    tap (the presence of each class convolved with its filter's support), so the dense and
    the sparse paths keep the same voxels whatever the rounding of the convolution.
    """
    device = next(layer.kernel.parameters()).device
    with torch.no_grad():
        features = volume.to_dense(device)
        increment = layer.increment(features)
        support = (layer.kernel.filters() > 0).to(features.dtype)
        reach = torch.nn.functional.conv3d((features > 0).to(features.dtype)[None], support,
                                           padding=layer.kernel.filter_size // 2, groups=features.shape[0])[0]
        touched = (reach.amax(dim=0) > 0.5).cpu().numpy()
        # The convolution's rounding may leave tiny values of the wrong sign around the evidence
        # (negative evidence: a scan withdrawn, ``ConvBKIMapper.withdraw``).
        withdrawn = bool((volume.features < 0).any())
        increment = (increment.clamp_max_(0.0) if withdrawn else increment.clamp_min_(0.0)).cpu().numpy()
    # Window-local index i lives at (origin + i) mod dims on the torus.
    shift = tuple(int(v) for v in volume.origin % volume.dims)
    touched = np.roll(touched, shift, axis=(0, 1, 2))
    new = int(np.count_nonzero(touched & (mask == 0)))
    alpha += np.roll(increment, shift, axis=(1, 2, 3))
    mask |= touched.astype(np.uint8) * np.uint8(marks)
    return new


"""Plain, independent re-statements of the paper's formulas, used as test oracles.

Nothing here imports the implementation: the kernel is re-typed from Eq. 5 in numpy and
the update is a brute-force double loop over voxels and points (Eq. 1 discretised).
"""

import math

import numpy as np


def sparse_kernel_np(distance, ell):
    """Eq. 5 with sigma_0 = 1, float64."""
    d = np.asarray(distance, dtype=np.float64)
    r = d / ell
    value = (2 + np.cos(2 * math.pi * r)) * (1 - r) / 3 + np.sin(2 * math.pi * r) / (2 * math.pi)
    return np.where(d < ell, value, 0.0)


MIN_TAP_WEIGHT = 1e-6  # taps below one millionth of a point carry no evidence (kernels.MIN_TAP_WEIGHT)


def kernel_weight(kind, offset_m, c, ell=None, ell_h=None, ell_z=None):
    """Kernel value for class c at metric offset (3,) between two voxel centres."""
    if kind == "compound":
        horizontal = math.hypot(offset_m[0], offset_m[1])
        weight = float(sparse_kernel_np(horizontal, ell_h[c]) * sparse_kernel_np(abs(offset_m[2]), ell_z[c]))
    else:
        length = ell[0] if kind == "single" else ell[c]
        weight = float(sparse_kernel_np(np.linalg.norm(offset_m), length))
    return weight if weight >= MIN_TAP_WEIGHT else 0.0


def brute_force_alpha(points_map, labels, num_classes, resolution, origin, dims, filter_size, prior, kind,
                      ell=None, ell_h=None, ell_z=None, ignore=(0,)):
    """alpha for every window voxel: prior + sum over points of y_c * k(voxel centre - point's voxel centre).

    Points contribute to voxels whose index differs by at most (f - 1) / 2 on each axis
    (the filter's reach), and only voxels inside the window are updated (zero padding).
    Returns {global index tuple: alpha (C,) float64} for voxels that received evidence.
    """
    half = filter_size // 2
    result = {}
    for point, label in zip(points_map, labels):
        if not np.isfinite(point).all() or label in ignore or not 0 <= label < num_classes:
            continue
        voxel = np.floor(point / resolution).astype(np.int64)
        local = voxel - origin
        if (local < 0).any() or (local >= dims).any():
            continue
        for dx in range(-half, half + 1):
            for dy in range(-half, half + 1):
                for dz in range(-half, half + 1):
                    target = voxel + (dx, dy, dz)
                    target_local = target - origin
                    if (target_local < 0).any() or (target_local >= dims).any():
                        continue
                    weight = kernel_weight(kind, np.array([dx, dy, dz]) * resolution, label, ell, ell_h, ell_z)
                    if weight <= 0:
                        continue
                    key = tuple(int(t) for t in target)
                    if key not in result:
                        result[key] = np.full(num_classes, prior, np.float64)
                    result[key][label] += weight
    return result

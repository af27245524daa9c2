"""Plain, independent re-statements of the paper's formulas, used as test oracles.

Nothing here imports the implementation: the kernel is re-typed from Eq. 5 in numpy, the
window is re-derived from its definition (the local bounds around the sensor, rounded
outwards to whole voxels), and the update is the brute-force S-BKI sum over points
(Eqs. 1 and 4 discretised):

    alpha[v, c] = prior + sum over points p of k_c(centre(v) - centre(voxel(p))) * y[p, c]

where a point's evidence y[p] (one-hot label or probability row) counts in its voxel,
the kernel weighs taps by the distance between voxel centres, taps beyond the f x f x f
filter or below ``MIN_TAP_WEIGHT`` are zero, and only voxels inside the scan's window
are read or updated (zero padding).
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


def filter_table(kind, num_classes, resolution, filter_size, ell=None, ell_h=None, ell_z=None):
    """Weights (C, f, f, f) float64 of every tap, [c, i, j, m] at offset (i - h, j - h, m - h) voxels."""
    half = filter_size // 2
    table = np.zeros((num_classes, filter_size, filter_size, filter_size))
    for c in range(num_classes):
        for i in range(filter_size):
            for j in range(filter_size):
                for m in range(filter_size):
                    offset = np.array([i - half, j - half, m - half], np.float64) * resolution
                    table[c, i, j, m] = kernel_weight(kind, offset, c, ell, ell_h, ell_z)
    return table


def rotation(yaw, pitch, roll):
    """R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll),
                              math.sin(roll))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def pose_matrix(yaw, pitch, roll, translation):
    pose = np.eye(4)
    pose[:3, :3] = rotation(yaw, pitch, roll)
    pose[:3, 3] = translation
    return pose


def tempered(probabilities, temperature):
    """Temperature scaling (Guo et al., 2017), the textbook way: softmax(log p / T), float64,
    times the row's sum (rows keep their evidence; a probability of 0 stays 0)."""
    probabilities = np.asarray(probabilities, np.float64)
    with np.errstate(divide="ignore"):
        logits = np.log(probabilities) / temperature
    logits -= logits.max(axis=1, keepdims=True)
    exponentials = np.exp(logits)
    return exponentials / exponentials.sum(axis=1, keepdims=True) * probabilities.sum(axis=1, keepdims=True)


class BruteForceMap:
    """The map a sequence of scans should produce, by the brute-force sum above.

    ``bounds`` ((3,), (3,)) metres around the sensor, rounded outwards to whole voxels (give
    bounds off the grid, so that the rounding is unambiguous); ``lengths`` the kernel's
    lengths as keyword arguments of ``kernel_weight``. ``alpha`` maps global voxel index
    tuples to (C,) float64 concentrations for every voxel that ever received evidence;
    ``windows`` and ``touched`` record each scan's window and the voxels it gave evidence.
    A scan's window is the box of ``bounds`` around its sensor position (the pose's
    translation); only its points count and only its voxels change.
    """

    def __init__(self, kind, num_classes, resolution, filter_size, bounds, prior, ignore=(0,), temperature=None,
                 **lengths):
        self.num_classes, self.resolution, self.prior, self.ignore = num_classes, resolution, prior, tuple(ignore)
        self.temperature = temperature  # probability rows become softmax(log p / T); None: as given
        self.table = filter_table(kind, num_classes, resolution, filter_size, **lengths)
        self.half = filter_size // 2
        lo = np.floor(np.asarray(bounds[0], np.float64) / resolution).astype(np.int64)
        hi = np.ceil(np.asarray(bounds[1], np.float64) / resolution).astype(np.int64)
        self.offset, self.dims = lo, hi - lo
        self.alpha = {}
        self.windows = []  # (origin, dims) of every scan
        self.touched = []  # the set of voxels every scan gave evidence

    def window_of(self, pose):
        return np.floor(pose[:3, 3] / self.resolution).astype(np.int64) + self.offset

    def integrate(self, points_sensor, values, pose):
        """Add one scan; returns the counts of what happened to its points, as a dict."""
        C = self.num_classes
        points = np.asarray(points_sensor, np.float64) @ pose[:3, :3].T + pose[:3, 3]
        count = len(points)
        counts = dict.fromkeys(("non_finite", "bad_probabilities", "unknown_label", "ignored_class",
                                "outside_window"), 0)
        keep = np.isfinite(points).all(axis=1)
        counts["non_finite"] = int((~keep).sum())
        values = np.asarray(values)
        if values.ndim == 1:
            known = (values >= 0) & (values < C)
            counts["unknown_label"] = int((keep & ~known).sum())
            keep &= known
            ignored = np.isin(values, self.ignore)
            counts["ignored_class"] = int((keep & ignored).sum())
            keep &= ~ignored
            evidence = np.zeros((count, C))
            evidence[keep, values[keep]] = 1.0
        else:
            evidence = values.astype(np.float32).astype(np.float64)  # the evidence is float32 on every path
            finite = np.isfinite(evidence).all(axis=1)
            counts["non_finite"] += int((keep & ~finite).sum())
            keep &= finite
            bad = keep & (((evidence < 0).any(axis=1)) | (evidence.sum(axis=1) <= 0))
            counts["bad_probabilities"] = int(bad.sum())
            keep &= ~bad
            if self.temperature is not None:
                evidence[keep] = tempered(evidence[keep], self.temperature)
            evidence[:, list(self.ignore)] = 0.0  # ignored classes carry no evidence
        origin = self.window_of(pose)
        voxels = np.zeros((count, 3), np.int64)
        voxels[keep] = np.floor(points[keep] / self.resolution).astype(np.int64)
        inside = keep & ((voxels >= origin) & (voxels < origin + self.dims)).all(axis=1)
        counts["outside_window"] = int((keep & ~inside).sum())
        counts["used"] = int(inside.sum())
        voxels, evidence = voxels[inside], evidence[inside]

        increment = np.zeros((*self.dims.tolist(), C))
        touched = np.zeros(self.dims.tolist(), bool)
        span = range(-self.half, self.half + 1)
        for i in span:
            for j in span:
                for m in span:
                    weights = self.table[:, i + self.half, j + self.half, m + self.half]
                    local = voxels + (i, j, m) - origin
                    within = ((local >= 0) & (local < self.dims)).all(axis=1)
                    contribution = evidence[within] * weights
                    target = tuple(local[within].T)
                    np.add.at(increment, target, contribution)
                    np.logical_or.at(touched, target, (contribution > 0).any(axis=1))
        scan_touched = set()
        for local in np.argwhere(touched):
            key = tuple(int(v) for v in local + origin)
            self.alpha.setdefault(key, np.full(C, self.prior))
            self.alpha[key] = self.alpha[key] + increment[tuple(local)]
            scan_touched.add(key)
        self.windows.append((origin, self.dims.copy()))
        self.touched.append(scan_touched)
        return counts


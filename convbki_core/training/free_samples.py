"""Training the free-space length ``free_ell``: what a sample needs and the loss it adds.

Free space (``free_space`` module) adds, for each scan s, the evidence that the voxels its
rays cross are empty to class 0, spread by the free filter K_free(free_ell), into the voxels
that hold evidence and that s's own class evidence does not reach (the TOUCHED rule):

    alpha[0, v] += sum_s [v eligible for s] sum_tap K_free[tap] G_s[v + tap - h]

with G_s the ray counts of scan s. The paper's point loss cannot see this: scan t's points lie
in voxels scan t touches. So a training sample (scan t and its past scans t-T+1 .. t-1, all in
scan t's frame) gets two questions:

* surface: at the voxels of scan t's labelled points (the paper's loss), is class 0 low? The
  past scans' free evidence enters alpha[0] there, and the NLL over classes 0 .. C-1 (class 0
  in the denominator) penalises freeing real surface;
* free: at points on scan t's rays before their returns (``FREE_PER_RAY`` a ray, at random
  fractions of the range, at least ``FREE_MARGIN_VOXELS`` in front of the return, never in a
  voxel holding a return of scan t), is class 0 high? These points are empty at time t; the
  map they are read from is that of the past scans alone (their class evidence and free
  evidence), so scan t's own rays, which define the answer, are not part of it. Points in
  voxels without class evidence in that map take no free evidence in the mapper either: they
  carry no gradient and are dropped.

For a voxel v and past scan s, "eligible" follows the mapper in order: v holds evidence
(it is reached by the class evidence of an earlier scan of the sample) and s's class evidence
does not reach it. Which voxels a scan's class evidence reaches depends on the class lengths;
the sample fixes it with the filters of the kernel the trainer starts from (its supports: the
taps of at least ``kernels.MIN_TAP_WEIGHT``), as it fixes which voxels the loss reads.

Everything that does not depend on free_ell is precomputed per sample: H[q, tap] = sum of
G_s[q + tap - h] over the past scans s for which q is eligible (zero padding at the window's
faces, as the mapper). Then alpha[0, q] = prior + sum_tap K_free[tap] H[q, tap], differentiable
in free_ell. The free question teaches only free_ell (the class filters are detached there):
the class lengths keep the paper's objective.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from convbki_core.free_space.ray_walk import count_rays, scratch_counts
from convbki_core.free_space.scan_rays import scan_rays
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.geometry.grid import unravel_linear, voxel_indices
from convbki_core.geometry.volume import SparseVolume

FREE_PER_RAY = 2  # free points drawn on each sampled ray
FREE_RAYS = 20_000  # at most this many of scan t's returns give free points
FREE_MARGIN_VOXELS = 2.0  # a free point lies at least this far in front of its return (voxels)
FREE_NEAREST = 0.1  # ... and beyond this fraction of the range from the sensor


@dataclass
class FreeEvidence:
    """Precomputed free evidence at Q query voxels: H as sparse (row, tap, value) entries."""

    num_queries: int
    row: torch.Tensor  # (E,) int64
    tap: torch.Tensor  # (E,) int64 flat index into the (f, f, f) free filter
    value: torch.Tensor  # (E,) float32 ray counts

    def increment(self, free_filter: torch.Tensor) -> torch.Tensor:
        """sum_tap K_free[tap] H[q, tap] for every query voxel, (Q,), differentiable in ``free_filter``."""
        flat = free_filter.reshape(-1)
        contributions = self.value.to(flat.device, flat.dtype) * flat[self.tap.to(flat.device)]
        result = torch.zeros(self.num_queries, dtype=flat.dtype, device=flat.device)
        return result.index_add(0, self.row.to(flat.device), contributions)

    @property
    def nbytes(self) -> int:
        return 20 * int(self.value.numel())


def support_offsets(filters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The taps of class filters K (C, f, f, f) as (offsets (P, 3) int64, classes (P, C) bool):
    evidence of class c in voxel u reaches u + offset when classes[p, c]."""
    num_classes, size = filters.shape[0], filters.shape[1]
    half = size // 2
    reach = filters.reshape(num_classes, -1) > 0
    used = np.flatnonzero(reach.any(axis=0))
    grid = np.stack(np.unravel_index(used, (size, size, size)), axis=1)
    # conv3d's tap [i, j, k] carries F[u] to u + half - (i, j, k).
    return (half - grid).astype(np.int64), np.ascontiguousarray(reach[:, used].T)


def reached(volume: SparseVolume, offsets: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """Window-sized bool volume (X, Y, Z) of the voxels a scan's class evidence reaches (the
    mapper's TOUCHED marks): the union over its occupied voxels of the supports of their classes."""
    dims = volume.dims
    marks = np.zeros(tuple(int(d) for d in dims), bool)
    if volume.num_voxels == 0:
        return marks
    local = unravel_linear(volume.linear, dims)
    present = volume.features > 0
    for offset, reaching in zip(offsets, classes):
        rows = (present & reaching).any(axis=1)
        target = local[rows] + offset
        inside = ((target >= 0) & (target < dims)).all(axis=1)
        target = target[inside]
        marks[target[:, 0], target[:, 1], target[:, 2]] = True
    return marks


def free_points(returns: np.ndarray, occupied_marks: np.ndarray, origin: np.ndarray, dims: np.ndarray,
                resolution: float, rng: np.random.Generator) -> np.ndarray:
    """Global voxel indices (unique) of points on the rays from the sensor (the origin of the
    points' frame) to ``returns`` (N, 3): ``FREE_PER_RAY`` a ray for at most ``FREE_RAYS`` rays,
    at random fractions of the range, at least ``FREE_MARGIN_VOXELS`` in front of the return,
    inside the window and not in a voxel holding a return (``occupied_marks``, window-local)."""
    returns = returns[np.isfinite(returns).all(axis=1)]
    if len(returns) > FREE_RAYS:
        returns = returns[rng.choice(len(returns), FREE_RAYS, replace=False)]
    distance = np.linalg.norm(returns, axis=1)
    farthest = 1.0 - FREE_MARGIN_VOXELS * resolution / np.maximum(distance, 1e-9)
    usable = farthest > FREE_NEAREST
    returns, farthest = returns[usable], farthest[usable]
    fractions = FREE_NEAREST + rng.random((len(returns), FREE_PER_RAY)) * (farthest - FREE_NEAREST)[:, None]
    points = (returns[:, None, :] * fractions[:, :, None]).reshape(-1, 3)
    local = voxel_indices(points, resolution) - origin
    inside = ((local >= 0) & (local < dims)).all(axis=1)
    local = local[inside]
    local = local[~occupied_marks[local[:, 0], local[:, 1], local[:, 2]]]
    return np.unique(local, axis=0) + origin


def free_evidence(queries: np.ndarray, past: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                  reach: list[np.ndarray], origin: np.ndarray, dims: np.ndarray, filter_size: int,
                  ) -> tuple[FreeEvidence, np.ndarray]:
    """H at ``queries`` (Q, 3) global voxel indices, from the past scans in order: ``past`` holds
    per scan (sensor position in voxel units, ray ends, ray weights, through), ``reach`` its
    reached-voxel volume. Returns (H, held (Q,) bool: the voxel holds class evidence by the
    end of the past scans)."""
    half = filter_size // 2
    steps = np.arange(filter_size) - half
    taps = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    local = queries - origin
    held = np.zeros(len(queries), bool)
    dense = np.zeros((len(queries), len(taps)), np.float32)
    counts = scratch_counts(dims)
    for (sensor, ends, weights, through), marks in zip(past, reach):
        touched = marks[local[:, 0], local[:, 1], local[:, 2]]
        eligible = np.flatnonzero(held & ~touched)
        if eligible.size and len(ends):
            volume_counts = count_rays(sensor, ends, weights, through, dims, counts)
            chosen = local[eligible]
            for number, tap in enumerate(taps):
                source = chosen + tap  # window-local; zero padding outside, as the mapper
                inside = np.flatnonzero(((source >= 0) & (source < dims)).all(axis=1))
                physical = np.mod(source[inside] + origin, dims)  # the counts are in torus order
                dense[eligible[inside], number] += volume_counts[physical[:, 0], physical[:, 1], physical[:, 2]]
            volume_counts.fill(0.0)
            counts[1].fill(0.0)
        held |= touched
    rows, columns = np.nonzero(dense)
    evidence = FreeEvidence(len(queries), torch.from_numpy(rows.astype(np.int64)),
                            torch.from_numpy(columns.astype(np.int64)), torch.from_numpy(dense[rows, columns]))
    return evidence, held


def past_rays(points: np.ndarray, relative: np.ndarray, volume: SparseVolume, resolution: float):
    """One past scan's rays in the sample's frame: (sensor (voxel units), ends, weights, through);
    ``points`` in the scan's sensor frame, ``relative`` the sample frame <- scan pose, ``volume``
    the scan alone voxelised in the sample's window."""
    ends, weights, through = scan_rays(points, relative, volume, resolution)
    return relative[:3, 3] / resolution, ends, weights, through


def rows_of(evidence: FreeEvidence, keep: np.ndarray) -> FreeEvidence:
    """The entries of the query rows ``keep`` (bool (Q,)), renumbered in order."""
    number = np.cumsum(keep) - 1
    row = evidence.row.numpy()
    chosen = keep[row]
    return FreeEvidence(int(keep.sum()), torch.from_numpy(number[row[chosen]].astype(np.int64)),
                        evidence.tap[torch.from_numpy(chosen)], evidence.value[torch.from_numpy(chosen)])


def free_nll(alpha_classes: torch.Tensor, free: torch.Tensor, prior: float) -> torch.Tensor:
    """Mean -ln p(free) at free points: ``alpha_classes`` (Q, C) the class concentrations
    (class 0 holding only the prior), ``free`` (Q,) the free evidence."""
    free_alpha = alpha_classes[:, FREE_CLASS] + free
    total = alpha_classes.sum(dim=1) + free
    return -(torch.log(free_alpha) - torch.log(total)).mean()



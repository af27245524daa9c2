"""The training samples of the paper's recipe: (sequence, scan t) as a sparse problem.

For every scan t, the T = 10 scans t-T+1 .. t are moved into scan t's frame and voxelised
together (the update is a sum, so one convolution over all of them equals T sequential
updates); a sample is the update's plan at the voxels holding scan t's scored points and their
ground truth (``SampleBuilder``). With the free-space length learned, a sample also carries the
free-space questions of ``free_samples`` (``FreeQuestions``).

The convolution is evaluated only at the voxels the loss reads (``SparsePlan``), which
equals the dense layer there (tested) and keeps a training step cheap enough for a CPU.
A sample's plan does not depend on the kernel, so built samples are kept for later epochs (up
to ``PLAN_CACHE_BYTES``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from convbki_core.datasets import Frame
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import WindowGeometry, transform_points, unravel_linear, voxel_indices
from convbki_core.geometry.volume import voxelize
from convbki_core.training.free_samples import (
    FreeEvidence,
    free_evidence,
    free_points,
    past_rays,
    reached,
    rows_of,
    support_offsets,
)
from convbki_core.training.sparse_plan import SparsePlan

PLAN_CACHE_BYTES = 2 << 30  # built samples kept in memory for later epochs


class SampleBuilder:
    """Turns (sequence, scan t) into the sparse training problem of the paper's recipe."""

    def __init__(self, geometry: WindowGeometry, num_classes: int, frames_per_sample: int, filter_size: int,
                 ignore: Sequence[int], temperature: float | None = None, free_support: np.ndarray | None = None,
                 seed: int = 0):
        self.geometry = geometry
        self.temperature = temperature  # of probability inputs, as the mapper applies it
        # With the class filters (C, f, f, f) whose supports decide the TOUCHED rule, samples also
        # carry the free-space questions (``free_samples``); None: the paper's samples only.
        self.free_support = None if free_support is None else support_offsets(free_support)
        self.seed = seed
        self.num_classes = num_classes
        self.frames_per_sample = frames_per_sample
        self.filter_size = filter_size
        self.ignore = tuple(ignore)
        self._cache: dict[tuple[int, int], Frame] = {}
        self._plans: dict[tuple[int, int], tuple | None] = {}
        self._plan_bytes = 0

    def cached_build(self, dataset_number: int, dataset: SemanticKittiSequence, position: int):
        """``build``, kept in memory (up to ``PLAN_CACHE_BYTES``) for the next epochs: the plan does not
        depend on the kernel."""
        key = (dataset_number, position)
        if key in self._plans:
            return self._plans[key]
        built = self.build(dataset_number, dataset, position)
        size = 0 if built is None else 20 * built[0].value.numel() + 16 * len(built[1])
        if built is not None and len(built) > 3 and built[3] is not None:
            size += built[3].nbytes
        if self._plan_bytes + size <= PLAN_CACHE_BYTES:
            self._plans[key] = built
            self._plan_bytes += size
        return built

    def _frame(self, dataset_number: int, dataset: SemanticKittiSequence, position: int) -> Frame:
        key = (dataset_number, position)
        if key not in self._cache:
            if len(self._cache) > 4 * self.frames_per_sample:
                self._cache.clear()  # samples are visited in runs of neighbours; keep memory bounded
            self._cache[key] = dataset[position]
        return self._cache[key]

    def build(self, dataset_number: int, dataset: SemanticKittiSequence, position: int):
        """(plan, query index per scored point, ground truth per scored point) or None if nothing to
        score; with ``free_support``, a fourth entry: the sample's ``FreeQuestions`` (None when
        it has none)."""
        current = self._frame(dataset_number, dataset, position)
        to_current = np.linalg.inv(current.pose)
        points, values, scans = [], [], []
        for past in range(max(0, position - self.frames_per_sample + 1), position + 1):
            frame = self._frame(dataset_number, dataset, past)
            relative = to_current @ frame.pose
            points.append(transform_points(frame.points, relative))
            values.append(frame.input_values)
            scans.append((frame.points, relative))
        origin = self.geometry.origin_for(np.zeros(3))
        dims = self.geometry.dims
        volume = voxelize(np.concatenate(points), np.concatenate(values), origin, dims, self.geometry.resolution,
                          self.num_classes, self.ignore, self.temperature)
        truth = current.ground_truth
        scored = volume.point_linear[-len(truth):] >= 0  # the current scan's points are the last block
        scored &= ~np.isin(truth, self.ignore)
        if not scored.any() or volume.num_voxels == 0:
            return None
        # Voxels of the current scan's scored points, relative to the window.
        point_voxels = voxel_indices(points[-1][scored], self.geometry.resolution)
        query, point_query = np.unique(point_voxels, axis=0, return_inverse=True)
        source = unravel_linear(volume.linear, dims) + origin
        plan = SparsePlan.build(query, source, volume.features, self.filter_size, window=(origin, dims))
        if self.free_support is None:
            return plan, point_query.reshape(-1), truth[scored]
        rng = np.random.default_rng([self.seed, dataset_number, position])
        free = self._free_questions(query, points, values, scans, origin, dims, rng)
        return plan, point_query.reshape(-1), truth[scored], free

    def _free_questions(self, query: np.ndarray, points: list, values: list, scans: list, origin: np.ndarray,
                        dims: np.ndarray, rng: np.random.Generator) -> FreeQuestions | None:
        """The free-space part of a sample (``free_samples`` module docstring); None without past scans."""
        if len(points) < 2:
            return None
        resolution = self.geometry.resolution

        def alone(index: int):
            return voxelize(points[index], values[index], origin, dims, resolution, self.num_classes, self.ignore,
                            self.temperature)

        past_volumes = [alone(index) for index in range(len(points) - 1)]
        reach = [reached(volume, *self.free_support) for volume in past_volumes]
        rays = [past_rays(*scans[index], past_volumes[index], resolution) for index in range(len(past_volumes))]
        current = alone(len(points) - 1)
        returns = np.zeros(tuple(int(d) for d in dims), bool)
        local = unravel_linear(current.linear, dims)
        returns[local[:, 0], local[:, 1], local[:, 2]] = True
        free = free_points(points[-1], returns, origin, dims, resolution, rng)
        evidence, held = free_evidence(np.concatenate([query, free]), rays, reach, origin, dims, self.filter_size)
        at_points = np.arange(len(query) + len(free)) < len(query)
        kept = held & ~at_points  # free points in voxels without class evidence carry no gradient
        past = voxelize(np.concatenate(points[:-1]), np.concatenate(values[:-1]), origin, dims, resolution,
                        self.num_classes, self.ignore, self.temperature)
        free_plan = SparsePlan.build(np.concatenate([query, free])[kept], unravel_linear(past.linear, dims) + origin,
                                     past.features, self.filter_size, window=(origin, dims))
        return FreeQuestions(rows_of(evidence, at_points), free_plan, rows_of(evidence, kept))


@dataclass
class FreeQuestions:
    """A sample's free-space part: the past scans' free evidence at its labelled voxels, and its
    free points (the past scans' class evidence there, and their free evidence)."""

    at_points: FreeEvidence
    free_plan: SparsePlan
    at_free: FreeEvidence

    @property
    def nbytes(self) -> int:
        return self.at_points.nbytes + self.at_free.nbytes + 20 * int(self.free_plan.value.numel())

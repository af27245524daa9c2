"""The trainer: learn ConvBKI kernel lengths on SemanticKITTI-format sequences.

The paper's recipe (section "Training"): for every scan t, the T scans t-T+1 .. t are moved
into scan t's frame and voxelised together (the update is a sum, so one convolution over
all of them equals T sequential updates); the posterior at the voxels holding scan t's
points is alpha = prior + conv3d(F, K); the loss is the class-weighted negative log
likelihood of scan t's ground truth under the expected probabilities alpha / sum(alpha);
Adam (lr 0.007), one epoch, lengths initialised at 0.5 m and kept positive.

The convolution is evaluated only at the voxels the loss reads (``SparsePlan``), which
equals the dense layer there (tested) and keeps a training step cheap enough for a CPU.
Class weights are 1 / sqrt(frequency) of the training ground truth, normalised to mean 1
over the classes present (rare classes count more without letting a handful of points
dominate); ignored classes (0) weigh nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import torch

from convbki_core.datasets import DatasetError, Frame
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_label_words
from convbki_core.kernels import ConvBKIKernel
from convbki_core.training.sparse_plan import SparsePlan
from convbki_core.volume import WindowGeometry, transform_points, unravel_linear, voxel_indices, voxelize

# progress(items, total, description) -> the same items, shown as they are consumed.
Progress = Callable[[Iterable, int, str], Iterable]

INITIAL_ELL = 0.5
DEFAULT_PRIOR = 1e-3


def class_weights(datasets: Sequence[SemanticKittiSequence], positions: Sequence[Sequence[int]],
                  num_classes: int, ignore: Sequence[int]) -> np.ndarray:
    """1 / sqrt(frequency) of the ground-truth classes, mean 1 over present classes, 0 for absent/ignored."""
    counts = np.zeros(num_classes, np.int64)
    for dataset, chosen in zip(datasets, positions):
        if not dataset.has_ground_truth:
            raise DatasetError(f"{dataset.folder}: no labels/ folder: training needs ground truth")
        for position in chosen:
            words = read_label_words(dataset.labels_folder / f"{dataset.names[position]}.label")
            counts += np.bincount(dataset.label_map.to_learning(words), minlength=num_classes)[:num_classes]
    counts[list(ignore)] = 0
    weights = np.zeros(num_classes)
    present = counts > 0
    weights[present] = 1.0 / np.sqrt(counts[present] / counts.sum())
    weights[present] /= weights[present].mean()
    return weights


class SampleBuilder:
    """Turns (sequence, scan t) into the sparse training problem of the paper's recipe."""

    def __init__(self, geometry: WindowGeometry, num_classes: int, frames_per_sample: int, filter_size: int,
                 ignore: Sequence[int]):
        self.geometry = geometry
        self.num_classes = num_classes
        self.frames_per_sample = frames_per_sample
        self.filter_size = filter_size
        self.ignore = tuple(ignore)
        self._cache: dict[tuple[int, int], Frame] = {}

    def _frame(self, dataset_number: int, dataset: SemanticKittiSequence, position: int) -> Frame:
        key = (dataset_number, position)
        if key not in self._cache:
            if len(self._cache) > 4 * self.frames_per_sample:
                self._cache.clear()  # samples are visited in runs of neighbours; keep memory bounded
            self._cache[key] = dataset[position]
        return self._cache[key]

    def build(self, dataset_number: int, dataset: SemanticKittiSequence, position: int):
        """(plan, query index per scored point, ground truth per scored point) or None if nothing to score."""
        current = self._frame(dataset_number, dataset, position)
        to_current = np.linalg.inv(current.pose)
        points, values = [], []
        for past in range(max(0, position - self.frames_per_sample + 1), position + 1):
            frame = self._frame(dataset_number, dataset, past)
            relative = to_current @ frame.pose
            points.append(transform_points(frame.points, relative))
            values.append(frame.input_values)
        origin = self.geometry.origin_for(np.zeros(3))
        dims = self.geometry.dims
        volume = voxelize(np.concatenate(points), np.concatenate(values), origin, dims, self.geometry.resolution,
                          self.num_classes, self.ignore)
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
        return plan, point_query.reshape(-1), truth[scored]


def weighted_nll(plan: SparsePlan, filters: torch.Tensor, point_query: torch.Tensor, truth: torch.Tensor,
                 weights: torch.Tensor, prior: float) -> torch.Tensor:
    """Class-weighted NLL of the ground truth under E[theta] = alpha / sum(alpha) at each point's voxel."""
    alpha = prior + plan.increment(filters)
    log_probability = torch.log(alpha) - torch.log(alpha.sum(dim=1, keepdim=True))
    point_weights = weights[truth]
    return -(point_weights * log_probability[point_query, truth]).sum() / point_weights.sum()


def train_kernel(datasets: Sequence[SemanticKittiSequence], positions: Sequence[Sequence[int]], kind: str,
                 frames_per_sample: int, epochs: int, lr: float, resolution: float = 0.2, filter_size: int = 5,
                 prior: float = DEFAULT_PRIOR, seed: int = 0, progress: Progress | None = None,
                 log: Callable[[str], None] | None = None, log_every: int = 25,
                 device: str | torch.device = "cpu") -> tuple[ConvBKIKernel, list[float]]:
    """Learn the kernel lengths on ``device``; returns the kernel (on the CPU) and the loss of every step."""
    label_map = datasets[0].label_map
    num_classes = label_map.num_classes
    torch.manual_seed(seed)
    device = torch.device(device)
    kernel = ConvBKIKernel(kind, num_classes, filter_size, resolution, ell=INITIAL_ELL).to(device)
    weights = torch.from_numpy(class_weights(datasets, positions, num_classes, label_map.ignore_classes)).float()
    weights = weights.to(device)
    optimiser = torch.optim.Adam(kernel.parameters(), lr=lr)
    builder = SampleBuilder(WindowGeometry(resolution), num_classes, frames_per_sample, filter_size,
                            label_map.ignore_classes)
    samples = [(number, position) for number, chosen in enumerate(positions) for position in chosen]
    rng = np.random.default_rng(seed)
    losses: list[float] = []
    for epoch in range(epochs):
        # Consecutive scans share T - 1 frames: shuffle blocks of neighbours, not single scans,
        # so the frame cache stays useful while the order is still mixed.
        blocks = [samples[i:i + frames_per_sample] for i in range(0, len(samples), frames_per_sample)]
        order = [sample for block in rng.permutation(len(blocks)) for sample in blocks[block]]
        steps = progress(order, len(order), f"epoch {epoch + 1}/{epochs}") if progress else order
        for number, position in steps:
            built = builder.build(number, datasets[number], position)
            if built is None:
                continue
            plan, point_query, truth = built
            loss = weighted_nll(plan, kernel.filters(), torch.from_numpy(point_query).to(device),
                                torch.from_numpy(truth).to(device), weights, prior)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            kernel.clamp_lengths_()
            losses.append(float(loss.detach()))
            if log and log_every and len(losses) % log_every == 0:
                recent = np.mean(losses[-log_every:])
                log(f"step {len(losses)}: loss {recent:.4f} (mean of the last {log_every})")
    return kernel.cpu(), losses

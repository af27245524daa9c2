"""The training loss: the class-weighted negative log likelihood of the paper's recipe.

The posterior at the voxels holding scan t's points is alpha = prior + conv3d(F, K); the loss
is the class-weighted negative log likelihood of scan t's ground truth under the expected
probabilities alpha / sum(alpha) (``weighted_nll``). Class weights are 1 / sqrt(frequency) of
the training ground truth, normalised to mean 1 over the classes present (rare classes count
more without letting a handful of points dominate); ignored classes (0) weigh nothing
(``class_counts``, ``class_weights``). With the free-space questions, one sample's loss adds
the free points' NLL of "free" (``sample_loss``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from convbki_core.datasets import DatasetError
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_label_words
from convbki_core.free_space.update import FREE_CLASS
from convbki_core.inference.kernels import ConvBKIKernel
from convbki_core.training.free_samples import free_nll
from convbki_core.training.sparse_plan import SparsePlan

FREE_WEIGHT = 1.0  # the free points' mean NLL against the labelled points' (sample_loss)


def class_counts(datasets: Sequence[SemanticKittiSequence], positions: Sequence[Sequence[int]],
                 num_classes: int, ignore: Sequence[int]) -> np.ndarray:
    """Ground-truth points of each class over the chosen frames; 0 for the ignored classes."""
    counts = np.zeros(num_classes, np.int64)
    for dataset, chosen in zip(datasets, positions):
        if not dataset.has_ground_truth:
            raise DatasetError(f"{dataset.folder}: no labels/ folder: training needs ground truth")
        for position in chosen:
            words = read_label_words(dataset.labels_folder / f"{dataset.names[position]}.label")
            counts += np.bincount(dataset.label_map.to_learning(words), minlength=num_classes)[:num_classes]
    counts[list(ignore)] = 0
    return counts


def class_weights(counts: np.ndarray) -> np.ndarray:
    """1 / sqrt(frequency) of the ground-truth classes, mean 1 over present classes, 0 for absent ones."""
    weights = np.zeros(counts.size)
    present = counts > 0
    weights[present] = 1.0 / np.sqrt(counts[present] / counts.sum())
    weights[present] /= weights[present].mean()
    return weights


def weighted_nll(plan: SparsePlan, filters: torch.Tensor, point_query: torch.Tensor, truth: torch.Tensor,
                 weights: torch.Tensor, prior: float, free: torch.Tensor | None = None) -> torch.Tensor:
    """Class-weighted NLL of the ground truth under E[theta] = alpha / sum(alpha) at each point's voxel;
    ``free`` (Q,): free evidence added to class 0 of the query voxels."""
    alpha = prior + plan.increment(filters)
    if free is not None:
        alpha = torch.cat([alpha[:, :FREE_CLASS + 1] + free[:, None], alpha[:, FREE_CLASS + 1:]], dim=1)
    log_probability = torch.log(alpha) - torch.log(alpha.sum(dim=1, keepdim=True))
    point_weights = weights[truth]
    return -(point_weights * log_probability[point_query, truth]).sum() / point_weights.sum()


def sample_loss(built: tuple, kernel: ConvBKIKernel, weights: torch.Tensor, prior: float,
                device: torch.device, free_weight: float = FREE_WEIGHT) -> torch.Tensor:
    """The loss of one built sample: the paper's weighted point NLL; with free-space questions,
    class 0 there holds the past scans' free evidence, plus ``free_weight`` times the mean NLL
    of "free" at the free points. Two means, so that the balance does not depend on how many
    free points a ray gives: by default they weigh the same (what a surface is, and whether
    space the scan saw through is empty)."""
    plan, point_query, truth = built[:3]
    free = built[3] if len(built) > 3 else None
    filters = kernel.filters()
    point_query = torch.from_numpy(point_query).to(device)
    truth = torch.from_numpy(truth).to(device)
    if free is None:
        return weighted_nll(plan, filters, point_query, truth, weights, prior)
    free_filter = kernel.free_filter()
    loss = weighted_nll(plan, filters, point_query, truth, weights, prior, free.at_points.increment(free_filter))
    if free.at_free.num_queries:
        # Only free_ell learns from the free points: the class lengths keep the paper's objective.
        alpha = prior + free.free_plan.increment(filters.detach())
        loss = loss + free_weight * free_nll(alpha, free.at_free.increment(free_filter), prior)
    return loss

"""Semantic segmentation scores: one confusion matrix over all points of all frames.

IoU_c = TP / (TP + FP + FN); points whose ground truth is an ignored class (0, unlabeled)
are left out entirely; the mean IoU is over the classes present in the ground truth
(docs/evaluation.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class ConfusionMatrix:
    """Accumulates counts[ground truth, prediction] over learning classes."""

    def __init__(self, num_classes: int, ignore_classes: Sequence[int] = (0,)):
        self.num_classes = int(num_classes)
        self.ignore_classes = tuple(int(c) for c in ignore_classes)
        self.counts = np.zeros((self.num_classes, self.num_classes), np.int64)

    def add(self, ground_truth: np.ndarray, prediction: np.ndarray) -> None:
        """Count one frame; both are (N,) learning ids."""
        ground_truth = np.asarray(ground_truth, np.int64).reshape(-1)
        prediction = np.asarray(prediction, np.int64).reshape(-1)
        if ground_truth.shape != prediction.shape:
            raise ValueError(f"{ground_truth.size} ground-truth labels but {prediction.size} predictions")
        valid = (ground_truth >= 0) & (ground_truth < self.num_classes)
        valid &= ~np.isin(ground_truth, self.ignore_classes)
        prediction = np.where((prediction >= 0) & (prediction < self.num_classes), prediction, 0)
        pairs = ground_truth[valid] * self.num_classes + prediction[valid]
        self.counts += np.bincount(pairs, minlength=self.num_classes ** 2).reshape(self.num_classes, -1)

    def __iadd__(self, other: ConfusionMatrix) -> ConfusionMatrix:
        self.counts += other.counts
        return self

    @property
    def present(self) -> np.ndarray:
        """Classes that occur in the ground truth (and are not ignored), (C,) bool."""
        present = self.counts.sum(axis=1) > 0
        present[list(self.ignore_classes)] = False
        return present

    def iou(self) -> np.ndarray:
        """Per-class IoU (C,), NaN for classes absent from the ground truth or ignored."""
        true_positive = np.diag(self.counts).astype(np.float64)
        # Predictions of a class on points whose ground truth is ignored were never counted,
        # as in the official evaluator (their column entries are dropped with the row).
        false_positive = self.counts.sum(axis=0) - true_positive
        false_negative = self.counts.sum(axis=1) - true_positive
        union = true_positive + false_positive + false_negative
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = true_positive / union
        iou[~self.present] = np.nan
        return iou

    def miou(self) -> float:
        values = self.iou()[self.present]
        return float(values.mean()) if values.size else float("nan")

    def accuracy(self) -> float:
        total = self.counts.sum()
        return float(np.trace(self.counts) / total) if total else float("nan")

    def summary(self, class_names: Sequence[str]) -> dict:
        """{"miou", "iou": {name: value for present classes}, "accuracy"} (fractions in [0, 1])."""
        iou = self.iou()
        return {"miou": self.miou(),
                "iou": {class_names[c]: float(iou[c]) for c in range(self.num_classes) if self.present[c]},
                "accuracy": self.accuracy()}

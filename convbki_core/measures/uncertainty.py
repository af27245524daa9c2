"""Measured uncertainty: calibration of class distributions and the paper's variance filter.

Everything is accumulated per point in streaming form (fixed-size counters, whatever the
number of frames), over the points ``evaluate`` scores (docs/evaluation.md, "Uncertainty"):

- expected calibration error (ECE): the points' confidences (expected probability of the
  arg-max class) fall in ``BINS`` equal-width bins of [0, 1]; ECE = sum_b (n_b / N)
  |acc_b - conf_b|, acc_b the share of bin b's points whose arg-max is the ground truth and
  conf_b their mean confidence;
- negative log-likelihood (NLL): mean over points of -ln max(p_truth, ``PROBABILITY_FLOOR``);
- Brier score: mean over points of sum_c (p_c - [c = truth])^2 (0 is perfect, 2 the worst);
- the variance-filter curve (the paper drops voxels whose variance exceeds 0.01): for each
  threshold, the points whose chosen class has variance <= threshold are kept; the curve
  gives the mIoU (and accuracy) of the kept points and the share kept. Each point is counted once, in the
  first threshold that keeps it, and the confusion matrix of a threshold is the running sum
  of those counts, so the share kept cannot decrease with the threshold.

The map's distribution at a point is the expected probability p_c = alpha_c / sum(alpha) of
the voxel the point falls in (``map_concentrations``); with free space, class 0 (free) is
left out and the rest renormalised (``map_distribution``): a return asks what the surface
there is, not whether the voxel is empty. The result is again a Dirichlet (that of the
other classes' concentrations), whose variance is p (1 - p) / (1 + sum of those alphas).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from convbki_core.free_space.update import FREE_CLASS
from convbki_core.measures.metrics import ConfusionMatrix

BINS = 15
PROBABILITY_FLOOR = 1e-12  # NLL: probabilities below are raised to it (-ln 1e-12 ~ 27.6 at most per point)
# The variance-filter thresholds: 13 log-spaced values from 1e-4 to 0.1 (10^(-4 + k/4)); the
# paper's 0.01 is one of them. A last "no filter" entry keeps every point.
VARIANCE_THRESHOLDS = np.logspace(-4.0, -1.0, 13)


def evidence_rows(mapper, points_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points whose voxel is in the current window and holds evidence, as
    ``ConvBKIMapper.labels_at`` finds them: (their positions (M,) int64, alpha (M, C) float32)."""
    alpha, has_evidence = mapper.concentrations_at(points_map)
    positions = np.flatnonzero(has_evidence)
    return positions, alpha[positions]


def map_concentrations(mapper, points_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concentrations of the voxels under map-frame points: (alpha (N, C) float32, has_evidence
    (N,) bool), as ``ConvBKIMapper.concentrations_at`` gives them within the window."""
    return mapper.concentrations_at(points_map)


def map_distribution(alpha: np.ndarray, free_space: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Class distribution of concentration rows, its arg-max and that class's variance.

    ``alpha`` (N, C), every row with a positive sum. With ``free_space`` class 0 is dropped
    (probability 0) and the others renormalised. Returns (probabilities (N, C) float64,
    chosen class (N,) int64, variance of the chosen class's probability (N,) float64). The
    arg-max is taken on the float32 concentrations as ``ConvBKIMapper.labels_at`` does
    (first class on ties), so it is the map label the protocol scores.
    """
    alpha = np.asarray(alpha, np.float32)
    if free_space:
        alpha = alpha.copy()
        alpha[:, FREE_CLASS] = 0.0
    chosen = alpha.argmax(axis=1).astype(np.int64) if alpha.shape[0] else np.zeros(0, np.int64)
    values = alpha.astype(np.float64)
    total = values.sum(axis=1)
    probabilities = values / total[:, None]
    top = probabilities[np.arange(len(chosen)), chosen]
    return probabilities, chosen, top * (1.0 - top) / (1.0 + total)


def input_distribution(probabilities: np.ndarray) -> np.ndarray:
    """An input's per-point class probabilities as given, rows renormalised to sum to 1
    (files are float16/float32); a row summing to 0 becomes uniform."""
    values = np.clip(np.asarray(probabilities, np.float64), 0.0, None)
    total = values.sum(axis=1, keepdims=True)
    uniform = np.full_like(values, 1.0 / max(values.shape[1], 1))
    return np.divide(values, total, out=uniform, where=total > 0)


def tempered_distribution(probabilities: np.ndarray, temperature: float | None) -> np.ndarray:
    """An input's class distribution after temperature scaling, (N, C) float64: the rows of
    ``input_distribution``, then softmax(log p / T) (the mapper's calibration of probability
    inputs); T None or 1 leaves them as they are."""
    values = input_distribution(probabilities)
    if temperature is None or float(temperature) == 1.0 or values.shape[0] == 0:
        return values
    with np.errstate(divide="ignore"):  # log 0 = -inf: a class the network ruled out stays out
        logits = np.log(values) / float(temperature)
    logits -= logits.max(axis=1, keepdims=True)
    powered = np.exp(logits)
    return powered / powered.sum(axis=1, keepdims=True)


def _finite(value: float) -> float | None:
    """JSON-safe: None for NaN (nothing accumulated)."""
    return float(value) if np.isfinite(value) else None


@dataclass
class Reliability:
    """Per bin of confidence: edges (B + 1,), points (B,), accuracy and mean confidence (B,)
    (NaN in empty bins)."""

    edges: np.ndarray
    count: np.ndarray
    accuracy: np.ndarray
    confidence: np.ndarray


class CalibrationStats:
    """Streaming ECE / NLL / Brier (and, given variances, the variance-filter curve).

    ``add`` takes one frame's scored points; points whose ground truth is an ignored class
    (or outside 0 .. C-1) are left out, as in ``ConfusionMatrix``.
    """

    def __init__(self, num_classes: int, ignore_classes: Sequence[int] = (0,), bins: int = BINS,
                 thresholds: Sequence[float] | None = VARIANCE_THRESHOLDS):
        self.num_classes = int(num_classes)
        self.ignore_classes = tuple(int(c) for c in ignore_classes)
        self.bins = int(bins)
        self.bin_count = np.zeros(self.bins, np.int64)
        self.bin_correct = np.zeros(self.bins, np.int64)
        self.bin_confidence = np.zeros(self.bins, np.float64)
        self.nll_sum = 0.0
        self.brier_sum = 0.0
        self.points = 0
        self.thresholds = None if thresholds is None else np.asarray(thresholds, np.float64)
        if self.thresholds is not None:
            if np.any(np.diff(self.thresholds) <= 0):
                raise ValueError("variance thresholds must increase")
            # counts[k, truth, prediction] for the points first kept at threshold k (the last
            # entry: kept only without a filter).
            self.curve_counts = np.zeros((len(self.thresholds) + 1, self.num_classes, self.num_classes), np.int64)

    def _scored(self, ground_truth: np.ndarray) -> np.ndarray:
        ground_truth = np.asarray(ground_truth, np.int64).reshape(-1)
        valid = (ground_truth >= 0) & (ground_truth < self.num_classes)
        return valid & ~np.isin(ground_truth, self.ignore_classes)

    def add(self, ground_truth: np.ndarray, probabilities: np.ndarray, chosen: np.ndarray | None = None,
            variance: np.ndarray | None = None) -> None:
        """One frame: ground truth (N,), class probabilities (N, C) summing to 1, the chosen
        class (N,) (default: the arg-max) and, for the curve, its variance (N,)."""
        ground_truth = np.asarray(ground_truth, np.int64).reshape(-1)
        probabilities = np.asarray(probabilities, np.float64).reshape(ground_truth.size, self.num_classes)
        valid = self._scored(ground_truth)
        truth, probabilities = ground_truth[valid], probabilities[valid]
        chosen = probabilities.argmax(axis=1) if chosen is None else np.asarray(chosen, np.int64).reshape(-1)[valid]
        rows = np.arange(truth.size)
        self.add_points(truth, chosen, probabilities[rows, chosen], probabilities[rows, truth],
                        np.einsum("ij,ij->i", probabilities, probabilities),
                        None if variance is None else np.asarray(variance, np.float64).reshape(-1)[valid])

    def add_points(self, truth: np.ndarray, chosen: np.ndarray, confidence: np.ndarray,
                   truth_probability: np.ndarray, squares: np.ndarray, variance: np.ndarray | None = None) -> None:
        """Scored points (ground truth not ignored) as per-point summaries, all (n,): ground truth,
        chosen class, its probability, the ground truth's probability, sum_c p_c^2, and (for the
        curve) the chosen class's variance."""
        correct = chosen == truth
        bins = np.clip((confidence * self.bins).astype(np.int64), 0, self.bins - 1)
        self.bin_count += np.bincount(bins, minlength=self.bins)
        self.bin_correct += np.bincount(bins[correct], minlength=self.bins)
        self.bin_confidence += np.bincount(bins, weights=confidence, minlength=self.bins)
        self.nll_sum += float(-np.log(np.maximum(truth_probability, PROBABILITY_FLOOR)).sum())
        # sum_c (p_c - onehot_c)^2 = sum_c p_c^2 - 2 p_truth + 1
        self.brier_sum += float((squares - 2.0 * truth_probability + 1.0).sum())
        self.points += int(truth.size)
        if self.thresholds is not None and variance is not None:
            first = np.searchsorted(self.thresholds, variance, side="left")  # first threshold >= variance
            first[~np.isfinite(variance)] = len(self.thresholds)
            cells = (first * self.num_classes + truth) * self.num_classes + chosen
            self.curve_counts += np.bincount(cells, minlength=self.curve_counts.size).reshape(self.curve_counts.shape)

    def ece(self) -> float:
        if not self.points:
            return float("nan")
        return float(np.abs(self.bin_correct - self.bin_confidence).sum() / self.points)

    def nll(self) -> float:
        return self.nll_sum / self.points if self.points else float("nan")

    def brier(self) -> float:
        return self.brier_sum / self.points if self.points else float("nan")

    def reliability(self) -> Reliability:
        with np.errstate(invalid="ignore", divide="ignore"):
            accuracy = self.bin_correct / self.bin_count
            confidence = self.bin_confidence / self.bin_count
        return Reliability(np.linspace(0.0, 1.0, self.bins + 1), self.bin_count.copy(), accuracy, confidence)

    def variance_curve(self) -> list[dict]:
        """[{"threshold", "miou", "kept", "accuracy"}] per threshold, then {"threshold": None} (no
        filter); ``kept`` is the share of this accumulator's points kept, ``miou`` and ``accuracy``
        those of the kept points (None when none is kept)."""
        if self.thresholds is None:
            return []
        cumulative = np.cumsum(self.curve_counts, axis=0)
        total = cumulative[-1].sum()
        curve = []
        for number, counts in enumerate(cumulative):
            matrix = ConfusionMatrix(self.num_classes, self.ignore_classes)
            matrix.counts = counts
            threshold = float(self.thresholds[number]) if number < len(self.thresholds) else None
            curve.append({"threshold": threshold, "miou": _finite(matrix.miou()),
                          "kept": float(counts.sum() / total) if total else None,
                          "accuracy": _finite(matrix.accuracy())})
        return curve

    def summary(self, with_curve: bool = True) -> dict:
        """{"ece", "nll", "brier"} (None when no point was accumulated), plus "variance_curve"."""
        result = {"ece": _finite(self.ece()), "nll": _finite(self.nll()), "brier": _finite(self.brier())}
        if with_curve and self.thresholds is not None:
            result["variance_curve"] = self.variance_curve()
        return result


class MapCalibration:
    """The map's uncertainty over the protocol's scored points of every frame.

    Points whose voxel is outside the window or holds no evidence have no map distribution:
    they are left out of the map's calibration and counted in ``without_evidence``.
    """

    def __init__(self, num_classes: int, ignore_classes: Sequence[int] = (0,), free_space: bool = True):
        self.stats = CalibrationStats(num_classes, ignore_classes)
        self.free_space = bool(free_space)
        self.without_evidence = 0

    def add(self, mapper, points_map: np.ndarray, ground_truth: np.ndarray) -> None:
        """One frame, right after its update: its points in the map frame and their ground truth."""
        ground_truth = np.asarray(ground_truth, np.int64).reshape(-1)
        scored = self.stats._scored(ground_truth)
        positions, alpha = evidence_rows(mapper, points_map)
        keep = scored[positions]
        self.without_evidence += int(scored.sum() - keep.sum())
        positions, alpha = positions[keep], alpha[keep]  # a copy: class 0 may be zeroed below
        truth = ground_truth[positions]
        # As map_distribution, without the (n, C) float64 probabilities: per point only the
        # chosen class's, the ground truth's and the sum of squares are needed.
        if self.free_space:
            alpha[:, FREE_CLASS] = 0.0
        chosen = alpha.argmax(axis=1) if alpha.shape[0] else np.zeros(0, np.int64)
        total = alpha.sum(axis=1, dtype=np.float64)
        rows = np.arange(truth.size)
        confidence = alpha[rows, chosen] / total
        squares = np.einsum("ij,ij->i", alpha, alpha, dtype=np.float64) / (total * total)
        self.stats.add_points(truth, chosen, confidence, alpha[rows, truth] / total, squares,
                              confidence * (1.0 - confidence) / (1.0 + total))

    def summary(self) -> dict:
        return {**self.stats.summary(), "calibration_points": self.stats.points,
                "points_without_evidence": self.without_evidence}

"""The label-noise model's calibration: the bisection on ``strength`` that meets a target input
mIoU (within ``TOLERANCE``), and the weighted per-class sample of the draws that a sequence too
long to hold whole is calibrated on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from convbki_core.datasets.label_noise import LabelNoiseModel, ScanDraws
from convbki_core.io.labels import LabelMap
from convbki_core.measures.metrics import ConfusionMatrix

MAX_STRENGTH = 40.0
TOLERANCE = 0.002  # bisection stops this close to the target mIoU


def confusion_of(truth: np.ndarray, predicted: np.ndarray, label_map: LabelMap) -> ConfusionMatrix:
    matrix = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
    matrix.add(truth, predicted)
    return matrix


@dataclass
class Calibration:
    strength: float
    miou: float  # of the draws calibrated on, at ``strength``
    reachable: bool
    evaluations: int


def calibrate(model: LabelNoiseModel, draws: ScanDraws, target: float, weight: np.ndarray | None = None,
              max_iterations: int = 60, on_step: Callable[[float, float], None] | None = None) -> Calibration:
    """The strength whose input mIoU over ``draws`` is ``target`` (bisection: the mIoU falls with
    the strength). ``weight``: how many points each draw stands for (a sample), None: 1 each.
    ``reachable`` is False when even MAX_STRENGTH keeps the mIoU above the target, or the
    bisection ends further than 0.01 from it (a jump of the mIoU there)."""
    labels = model.label_map
    truth = draws.truth.astype(np.int64)
    scored = truth > 0
    evaluations = 0

    def miou(strength: float) -> float:
        nonlocal evaluations
        evaluations += 1
        predicted = model.predict(draws, strength)[0]
        if weight is None:
            value = confusion_of(truth, predicted, labels).miou()
        else:
            c = labels.num_classes
            counts = np.bincount(truth[scored] * c + predicted[scored], weights=weight[scored],
                                 minlength=c * c).reshape(c, c)
            tp = np.diag(counts)
            union = counts.sum(0) + counts.sum(1) - tp
            present = counts.sum(1) > 0
            present[list(labels.ignore_classes)] = False
            value = float(np.mean(tp[present] / union[present])) if present.any() else math.nan
        if on_step is not None:
            on_step(strength, value)
        return value

    low, high = 0.0, MAX_STRENGTH
    value_low = miou(low)
    if value_low <= target:
        return Calibration(0.0, value_low, abs(value_low - target) <= 0.01, evaluations)
    value_high = miou(high)
    if value_high > target + 0.01:
        return Calibration(high, value_high, False, evaluations)
    best = (abs(value_high - target), high, value_high)
    # Bisection on log-strength first decade by decade would also do; plain bisection converges in ~25 steps.
    for _ in range(max_iterations):
        middle = 0.5 * (low + high)
        value = miou(middle)
        if abs(value - target) < best[0]:
            best = (abs(value - target), middle, value)
        if abs(value - target) <= TOLERANCE or high - low < 1e-7:
            break
        if value > target:
            low = middle
        else:
            high = middle
    return Calibration(best[1], best[2], best[0] <= 0.01, evaluations)


def sample_draws(draws: ScanDraws, per_class: int, rng: np.random.Generator) -> tuple[ScanDraws, np.ndarray]:
    """At most about ``per_class`` scored points of each true class (all of a rare one), weighted:
    what a calibration of a sequence too long to hold whole uses."""
    truth = draws.truth.astype(np.int64)
    counts = np.bincount(truth, minlength=32)
    rate = np.minimum(1.0, per_class / np.maximum(counts, 1))[truth]
    keep = (rng.random(len(truth)) < rate) & (truth > 0)
    return draws.subset(keep), (1.0 / rate[keep]).astype(np.float32)

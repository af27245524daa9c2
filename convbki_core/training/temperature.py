"""Temperature scaling of a segmentation network's class probabilities (Guo et al., 2017).

A network's softmax p is often mis-calibrated: too soft (under-confident) or too sharp
(over-confident). One scalar T fixes the shape without changing the arg-max:

    p' = softmax(log p / T)       (T < 1 sharpens, T > 1 softens; each row keeps its sum)

The mapper applies the kernel file's ``temperature`` to probability inputs before they are
voxelised (``volume.temper_probabilities``). ``train`` fits T on its held-out validation
frames, with the learned lengths fixed, by minimising a negative log-likelihood (NLL) of the
ground truth over a bounded range of log T:

* the map's NLL (``"map"``, what is written): the paper's protocol on the validation frames
  with tempered inputs, each frame's scored points read from the map right after its update
  (``calibration.MapCalibration``, the measure ``evaluate`` reports). Fusing many soft votes
  changes the calibration the map ends up with, so this targets what a user of the map sees;
* the input's NLL (``"input"``, reported beside it): the tempered input distribution at the
  same points. Cheap (no mapping), and the classic recipe, but blind to the fusion.

The search: the objective on a grid of log-spaced temperatures, then a golden-section search
between the grid neighbours of the best one (the NLL is smooth in log T and, for the input,
convex in 1 / T).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from convbki_core.measures.uncertainty import PROBABILITY_FLOOR, tempered_distribution

# The searched range: wide enough for any network seen in practice (a softmax sharpened or
# softened several times over), inside the kernel file's limits.
LOW_TEMPERATURE = 0.05
HIGH_TEMPERATURE = 5.0
GRID_POINTS = 7
GOLDEN_STEPS = 8
INVERSE_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass
class TemperatureSearch:
    """The temperature that minimised an objective, and every (T, value) tried."""

    temperature: float
    value: float
    tried: list[tuple[float, float]] = field(default_factory=list)


def minimise_temperature(objective: Callable[[float], float], low: float = LOW_TEMPERATURE,
                         high: float = HIGH_TEMPERATURE, grid: int = GRID_POINTS,
                         golden_steps: int = GOLDEN_STEPS) -> TemperatureSearch:
    """Minimise ``objective(T)`` over [low, high]: a log-spaced grid of ``grid`` temperatures,
    then ``golden_steps`` golden-section steps in log T between the best one's neighbours."""
    tried: list[tuple[float, float]] = []

    def value_at(log_t: float) -> float:
        temperature = float(math.exp(log_t))
        value = float(objective(temperature))
        tried.append((temperature, value))
        return value

    points = np.linspace(math.log(low), math.log(high), grid)
    values = [value_at(float(x)) for x in points]
    best = int(np.nanargmin(values))
    left, right = float(points[max(best - 1, 0)]), float(points[min(best + 1, grid - 1)])
    inner_left = right - INVERSE_GOLDEN * (right - left)
    inner_right = left + INVERSE_GOLDEN * (right - left)
    value_left, value_right = value_at(inner_left), value_at(inner_right)
    for _ in range(max(0, golden_steps - 2)):
        if value_left <= value_right:
            right, inner_right, value_right = inner_right, inner_left, value_left
            inner_left = right - INVERSE_GOLDEN * (right - left)
            value_left = value_at(inner_left)
        else:
            left, inner_left, value_left = inner_left, inner_right, value_right
            inner_right = left + INVERSE_GOLDEN * (right - left)
            value_right = value_at(inner_right)
    temperature, value = min(tried, key=lambda pair: (pair[1], abs(math.log(pair[0]))))
    return TemperatureSearch(temperature, value, tried)


def input_nll(probabilities: np.ndarray, truth: np.ndarray, temperature: float | None) -> float:
    """Mean -ln p'_truth of the tempered inputs (floored as ``calibration``), over the given points."""
    if len(truth) == 0:
        return float("nan")
    distribution = tempered_distribution(probabilities, temperature)
    chosen = distribution[np.arange(len(truth)), np.asarray(truth, np.int64)]
    return float(-np.log(np.maximum(chosen, PROBABILITY_FLOOR)).mean())


def fit_input_temperature(probabilities: np.ndarray, truth: np.ndarray) -> TemperatureSearch:
    """The temperature minimising the inputs' own NLL at the given points."""
    return minimise_temperature(lambda t: input_nll(probabilities, truth, t), golden_steps=20)

"""Fitting the temperature of probability inputs on the validation frames, the lengths fixed.

Probability inputs are tempered by the start kernel's ``temperature`` (none: as given) in
the samples and the validation maps alike. With the lengths chosen, ``fit_temperature``
fits the temperature on the validation frames (``training.temperature``): the one whose
map has the lowest NLL of the ground truth under the protocol (``validation.Validator``),
among those that cost at most ``TEMPERATURE_MIOU_LOSS`` of validation mIoU.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

from convbki_core.inference.kernels import KernelConfig
from convbki_core.measures.uncertainty import MapCalibration
from convbki_core.training.temperature import TemperatureSearch, fit_input_temperature, input_nll, minimise_temperature
from convbki_core.training.validation import Validator

TEMPERATURE_MIOU_LOSS = 0.01  # the validation mIoU a fitted temperature may cost (fit_temperature)
BOUNDARY_STEPS = 5  # bisections of the allowed temperatures' boundary


@dataclass
class TemperatureFit:
    """What ``fit_temperature`` found on the validation frames (NLLs are means over points)."""

    temperature: float  # the fitted temperature: the lowest map NLL
    start_temperature: float  # the kernel's before the fit (1: probabilities as given)
    map_nll_before: float
    map_nll_after: float
    map_ece_before: float
    map_ece_after: float
    miou_before: float
    miou_after: float
    input_nll_before: float  # the tempered input's own NLL, at the start and the fitted temperature
    input_nll_after: float
    input_temperature: float  # the temperature the input's NLL alone would pick
    input_nll_best: float
    search: TemperatureSearch  # the lowest map NLL without the mIoU bound: search.temperature, search.value
    unbounded_miou: float = float("nan")  # the validation mIoU and ECE there
    unbounded_ece: float = float("nan")
    miou_loss: float | None = None  # the mIoU the fit was allowed to cost (None: no bound)


def fit_temperature(validator: Validator, config: KernelConfig, log: Callable[[str], None] | None = None,
                    miou_loss: float | None = TEMPERATURE_MIOU_LOSS, boundary_steps: int = BOUNDARY_STEPS,
                    **search) -> TemperatureFit:
    """Fit the temperature of probability inputs for ``config`` (its lengths fixed) on the
    validation frames: the lowest map NLL under the protocol (``training.temperature``) among
    the temperatures whose validation mIoU is at most ``miou_loss`` below that of the start
    temperature (None: no bound). A temperature reshapes each point's vote before the votes
    are summed, so it can change the fused map's labels: sharpening a network's soft
    probabilities throws away what their second choices know. When the lowest NLL costs more
    mIoU than allowed, the boundary between it and the best allowed temperature is bisected
    in log T (``boundary_steps``). ``search``: options of ``minimise_temperature``."""
    measured: dict[float, tuple[float, MapCalibration]] = {}

    def run(temperature: float) -> tuple[float, MapCalibration]:
        if temperature not in measured:
            candidate = copy.deepcopy(config)
            candidate.temperature = None if temperature == 1.0 else float(temperature)
            miou, calibration = validator.measure(candidate)
            measured[temperature] = (miou, calibration)
            if log:
                log(f"fitting the temperature: T {temperature:.4f}: validation map NLL {calibration.stats.nll():.4f}, "
                    f"ECE {calibration.stats.ece():.4f}, mIoU {miou:.4f}")
        return measured[temperature]

    def nll(temperature: float) -> float:
        return run(temperature)[1].stats.nll()

    start = 1.0 if config.temperature is None else float(config.temperature)
    before_miou, before = run(start)
    floor = -math.inf if miou_loss is None else before_miou - miou_loss

    def allowed(temperature: float) -> bool:
        return run(temperature)[0] >= floor

    unbounded = minimise_temperature(nll, **search)
    best = min((t for t in measured if allowed(t)), key=lambda t: (nll(t), abs(math.log(t))))
    if not allowed(unbounded.temperature):
        inside, outside = math.log(best), math.log(unbounded.temperature)
        for _ in range(boundary_steps):
            middle = math.exp(0.5 * (inside + outside))
            if allowed(middle):
                inside = math.log(middle)
                best = min(best, middle, key=nll)
            else:
                outside = math.log(middle)
    if nll(best) >= nll(start):  # never worse than where it started
        best = start
    after_miou, after = run(best)
    probabilities, truth = validator.input_points()
    by_input = fit_input_temperature(probabilities, truth) if len(truth) else None
    return TemperatureFit(
        temperature=best, start_temperature=start,
        map_nll_before=before.stats.nll(), map_nll_after=after.stats.nll(),
        map_ece_before=before.stats.ece(), map_ece_after=after.stats.ece(),
        miou_before=before_miou, miou_after=after_miou,
        input_nll_before=input_nll(probabilities, truth, start),
        input_nll_after=input_nll(probabilities, truth, best),
        input_temperature=by_input.temperature if by_input else float("nan"),
        input_nll_best=by_input.value if by_input else float("nan"), search=unbounded,
        unbounded_miou=run(unbounded.temperature)[0], unbounded_ece=run(unbounded.temperature)[1].stats.ece(),
        miou_loss=miou_loss)

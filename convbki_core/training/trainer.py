"""The trainer: learn ConvBKI kernel lengths on SemanticKITTI-format sequences.

The paper's recipe (section "Training"): for every scan t, the T = 10 scans t-T+1 .. t are
moved into scan t's frame and voxelised together (the update is a sum, so one convolution
over all of them equals T sequential updates; ``samples``); the posterior at the voxels holding
scan t's points is alpha = prior + conv3d(F, K); the loss is the class-weighted negative log
likelihood of scan t's ground truth under the expected probabilities alpha / sum(alpha)
(``objective``); Adam, lengths kept positive.

Around that recipe (``train_kernel``, this module: the loop):

* Held-out validation frames (``validation.split_validation``) and their score under the
  paper's protocol (``validation.Validator``): the start kernel, then every ``validate_every``
  steps and after the last step.
* The kernel written is the one with the best validation mIoU; the start kernel unless a
  trained one beats it (strictly).
* Samples are shuffled (one permutation per epoch); the learning rate follows a cosine decay
  from ``lr`` at the first step to ``MIN_LR_FRACTION`` * ``lr`` at the last (``learning_rate``).
* Epochs are sized to the data: ``ceil(TARGET_UPDATES / training samples)`` unless given.
* The free-space length ``free_ell``: neither the paper's point loss nor the protocol's mIoU
  can see it (scan t's points lie in voxels reached by scan t's own class evidence, which
  take no free evidence from scan t, and the map labels a point by the most likely class
  other than free). With ``learn_free_ell`` each sample also asks the free-space questions
  of ``training.free_samples`` and ``free_ell`` is optimised with the lengths; its value
  after the last step is written. Otherwise the start kernel's value is kept.
* Probability inputs are tempered by the start kernel's ``temperature``; with the lengths
  chosen, ``temperature_fit`` fits it on the validation frames.

A class with fewer than ``MIN_CLASS_POINTS`` ground-truth points in the training frames keeps
its start lengths (``kept_classes``). Its points come from a handful of objects, each seen in
many scans with the same persistent input errors, so the lengths the loss finds for it fit those
objects rather than the class, while each Adam step still moves them as far as a common
class's; the validation mIoU cannot catch that when the class is rare there too. That is
measured with labels as input; with probabilities every point's row trains every class, and
``train`` learns every class by default.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from convbki_core.config import DEFAULTS
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import WindowGeometry
from convbki_core.inference.kernels import ConvBKIKernel, KernelConfig
from convbki_core.training.objective import FREE_WEIGHT, class_counts, class_weights, sample_loss
from convbki_core.training.samples import SampleBuilder
from convbki_core.training.validation import Validator

# progress(items, total, description) -> the same items, shown as they are consumed.
Progress = Callable[[Iterable, int, str], Iterable]

INITIAL_ELL = 0.5
TARGET_UPDATES = 300  # default epochs: enough passes for about this many optimiser steps
MIN_LR_FRACTION = 0.05  # the cosine schedule ends at this fraction of the initial rate
VALIDATIONS = 10  # default: validate about this many times over a run (plus the start)
FREE_ELL_START_VOXELS = 1.25  # learning free_ell starts at least this many voxels long
MIN_CLASS_POINTS = 25_000  # a class with fewer training ground-truth points keeps its start lengths


def kept_classes(counts: np.ndarray, min_points: int, ignore: Sequence[int]) -> np.ndarray:
    """The classes whose lengths stay at the start: fewer than ``min_points`` ground-truth points
    in the training frames (module docstring), the ignored classes excepted (they carry no evidence)."""
    kept = counts < min_points
    kept[list(ignore)] = False
    return np.flatnonzero(kept)


def learning_rate(step: int, total: int, lr: float, min_fraction: float = MIN_LR_FRACTION) -> float:
    """The rate of step ``step`` (0-based) of ``total``: a cosine decay from ``lr`` at the first step to
    ``min_fraction * lr`` at the last, never increasing."""
    if total <= 1:
        return lr
    done = min(max(step, 0), total - 1) / (total - 1)
    return lr * (min_fraction + (1.0 - min_fraction) * 0.5 * (1.0 + math.cos(math.pi * done)))


def default_epochs(training_samples: int, target_updates: int = TARGET_UPDATES) -> int:
    """Passes over the training samples that make about ``target_updates`` optimiser steps."""
    return max(1, math.ceil(target_updates / max(1, training_samples)))


@dataclass
class TrainResult:
    """What ``train_kernel`` found: the kernel to write and how it got there."""

    config: KernelConfig  # the kernel to write: the best on validation (the start unless beaten)
    start: KernelConfig
    losses: list[float] = field(default_factory=list)
    validation: list[tuple[int, float]] = field(default_factory=list)  # (step, mIoU); step 0 is the start
    best_step: int = 0  # 0: the start kernel
    epochs: int = 0
    total_steps: int = 0
    free_ells: list[float] = field(default_factory=list)  # free_ell after each step, when learned
    kept_classes: list[int] = field(default_factory=list)  # classes whose lengths stayed at the start

    @property
    def start_miou(self) -> float | None:
        return self.validation[0][1] if self.validation else None

    @property
    def best_miou(self) -> float | None:
        return max(m for _, m in self.validation) if self.validation else None

    @property
    def improved(self) -> bool:
        return self.best_step > 0


def train_kernel(datasets: Sequence[SemanticKittiSequence], positions: Sequence[Sequence[int]], kind: str,
                 frames_per_sample: int = 10, epochs: int | None = None, lr: float = 0.007, resolution: float = 0.2,
                 filter_size: int = 5, prior: float = DEFAULTS.window.prior, seed: int = 0,
                 progress: Progress | None = None, log: Callable[[str], None] | None = None, log_every: int = 25,
                 device: str | torch.device = "cpu", start: KernelConfig | None = None,
                 validator: Validator | None = None, validate_every: int | None = None,
                 learn_free_ell: bool = False, free_weight: float = FREE_WEIGHT,
                 min_class_points: int = MIN_CLASS_POINTS) -> TrainResult:
    """Learn the kernel lengths on ``device`` from ``start`` (default: every length ``INITIAL_ELL``).

    With a ``validator``, the start and every ``validate_every`` steps (default: about
    ``VALIDATIONS`` times a run) and the last step are scored, and the best kernel is returned;
    without one, the last. ``learn_free_ell``: samples also ask the free-space questions
    (``free_samples``) and ``free_ell`` is learned from at least ``FREE_ELL_START_VOXELS``
    voxels; the kernel written carries its value after the last step (the protocol's mIoU
    cannot rank it: a return asks for a class other than free). Otherwise ``free_ell`` is not
    optimised and the start's value is kept. ``free_weight``: see ``sample_loss``. The lengths of
    a class with fewer than ``min_class_points`` training ground-truth points stay at the start
    (``kept_classes``; the single kernel's one length is shared and always learned).
    """
    label_map = datasets[0].label_map
    num_classes = label_map.num_classes
    torch.manual_seed(seed)
    device = torch.device(device)
    if start is None:
        start = ConvBKIKernel(kind, num_classes, filter_size, resolution, ell=INITIAL_ELL).to_config()
    start = copy.deepcopy(start)
    kernel = ConvBKIKernel.from_config(start).to(device)
    lengths = [parameter for name, parameter in kernel.named_parameters() if name != "free_ell"]
    support = None
    if learn_free_ell:
        # A free filter of one voxel has no gradient (the taps beyond the centre are zero for
        # every length below a voxel): learning starts where the next taps are non-zero.
        with torch.no_grad():
            kernel.free_ell.clamp_(min=FREE_ELL_START_VOXELS * start.resolution)
        lengths.append(kernel.free_ell)
        with torch.no_grad():
            support = kernel.filters().cpu().numpy()[:, 0]
    counts = class_counts(datasets, positions, num_classes, label_map.ignore_classes)
    weights = torch.from_numpy(class_weights(counts)).float().to(device)
    kept = torch.from_numpy(kept_classes(counts, min_class_points, label_map.ignore_classes)).to(device)
    # The per-class lengths (not the single kernel's shared one, nor free_ell) whose kept classes
    # never move: their gradient is zeroed, so Adam's moments stay zero and its steps too.
    per_class = [parameter for parameter in lengths if parameter.numel() == num_classes] if kind != "single" else []
    optimiser = torch.optim.Adam(lengths, lr=lr)
    builder = SampleBuilder(WindowGeometry(start.resolution), num_classes, frames_per_sample, start.filter_size,
                            label_map.ignore_classes, start.temperature, free_support=support, seed=seed)
    samples = [(number, position) for number, chosen in enumerate(positions) for position in chosen]
    epochs = epochs or default_epochs(len(samples))
    rng = np.random.default_rng(seed)
    order = [samples[i] for _ in range(epochs) for i in rng.permutation(len(samples))]
    total = len(order)
    validate_every = validate_every or max(1, math.ceil(total / VALIDATIONS))
    result = TrainResult(config=start, start=start, epochs=epochs, total_steps=total,
                         kept_classes=[int(c) for c in kept] if per_class else [])

    def written(config: KernelConfig) -> KernelConfig:
        if not learn_free_ell:
            config.free_ell = start.free_ell  # not learned (module docstring)
        return config

    bar = None

    def validate(step: int) -> None:
        miou = validator.score(written(kernel.to_config()) if step else start)
        best = result.best_miou
        result.validation.append((step, miou))
        if step and miou > best:
            result.config, result.best_step = written(kernel.to_config()), step
        text = f"val mIoU {miou:.4f} (best {result.best_miou:.4f})"
        if bar is not None and hasattr(bar, "set_postfix_str"):
            bar.set_postfix_str(text)
        if log:
            log(f"step {step}/{total}: {text}")

    if validator is not None:
        validate(0)
    steps = progress(order, total, "training") if progress else order
    bar = steps if steps is not order else None
    if bar is not None and validator is not None and hasattr(bar, "set_postfix_str"):
        bar.set_postfix_str(f"val mIoU {result.start_miou:.4f} (start)")
    for step, (number, position) in enumerate(steps, start=1):
        built = builder.cached_build(number, datasets[number], position)
        if built is not None:
            for group in optimiser.param_groups:
                group["lr"] = learning_rate(step - 1, total, lr)
            loss = sample_loss(built, kernel, weights, prior, device, free_weight)
            optimiser.zero_grad()
            loss.backward()
            if len(kept):
                for parameter in per_class:
                    parameter.grad[kept] = 0.0
            optimiser.step()
            kernel.clamp_lengths_()
            result.losses.append(float(loss.detach()))
            if learn_free_ell:
                result.free_ells.append(float(kernel.free_ell.detach()))
            if log and log_every and len(result.losses) % log_every == 0:
                recent = np.mean(result.losses[-log_every:])
                log(f"step {step}/{total}: loss {recent:.4f} (mean of the last {log_every}), "
                    f"lr {learning_rate(step - 1, total, lr):.5f}"
                    + (f", free_ell {result.free_ells[-1]:.4f} m" if learn_free_ell else ""))
        if validator is not None and (step % validate_every == 0 or step == total):
            validate(step)
    if validator is None:
        result.config, result.best_step = written(kernel.to_config()), total
    if learn_free_ell:
        result.config = copy.deepcopy(result.config)
        result.config.free_ell = kernel.to_config().free_ell
    return result

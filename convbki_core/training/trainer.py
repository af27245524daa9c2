"""The trainer: learn ConvBKI kernel lengths on SemanticKITTI-format sequences.

The paper's recipe (section "Training"): for every scan t, the T = 10 scans t-T+1 .. t are
moved into scan t's frame and voxelised together (the update is a sum, so one convolution
over all of them equals T sequential updates); the posterior at the voxels holding scan t's
points is alpha = prior + conv3d(F, K); the loss is the class-weighted negative log
likelihood of scan t's ground truth under the expected probabilities alpha / sum(alpha);
Adam, lengths kept positive.

Around that recipe (``train_kernel``):

* Held-out validation (``split_validation``): each training sequence is cut into blocks of
  ``block`` consecutive frames (10); every ``every``-th block (4th: blocks 3, 7, ...; the last
  block when a sequence has fewer) is a validation block, at most ``max_frames`` validation
  frames in all (blocks picked evenly, the others train). Training samples exclude the
  validation frames and ``gap`` frames (2) on either side of each validation block, so no
  training scan is a direct neighbour of a validation scan (drives under two blocks: blocks of
  len / every frames and a gap of at most half a block). Or whole validation
  sequences are given (``--val-sequences``).
* Validation score (``Validator``): the paper's protocol (``tools.evaluate``): a fresh map per
  sequence, updated frame by frame over the validation frames with the candidate kernel (free
  space on, as ``evaluate``), every point labelled from its voxel (input label where the map
  has no evidence), mIoU over the classes present. Scored for the start kernel, then every
  ``validate_every`` steps and after the last step.
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
* Probability inputs are tempered by the start kernel's ``temperature`` (none: as given) in
  the samples and the validation maps alike. With the lengths chosen, ``fit_temperature``
  fits the temperature on the validation frames (``training.temperature``): the one whose
  map has the lowest NLL of the ground truth under the protocol, among those that cost at
  most ``TEMPERATURE_MIOU_LOSS`` of validation mIoU.

The convolution is evaluated only at the voxels the loss reads (``SparsePlan``), which
equals the dense layer there (tested) and keeps a training step cheap enough for a CPU.
Class weights are 1 / sqrt(frequency) of the training ground truth, normalised to mean 1
over the classes present (rare classes count more without letting a handful of points
dominate); ignored classes (0) weigh nothing.

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

from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.datasets import DatasetError, Frame
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence, read_label_words
from convbki_core.free_space.rays import FREE_CLASS
from convbki_core.geometry.volume import WindowGeometry, transform_points, unravel_linear, voxel_indices, voxelize
from convbki_core.inference.kernels import ConvBKIKernel, KernelConfig
from convbki_core.mapper import ConvBKIMapper
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.uncertainty import MapCalibration
from convbki_core.offline import map_frame_labels
from convbki_core.training.free_samples import (
    FreeEvidence,
    free_evidence,
    free_nll,
    free_points,
    past_rays,
    reached,
    rows_of,
    support_offsets,
)
from convbki_core.training.sparse_plan import SparsePlan
from convbki_core.training.temperature import TemperatureSearch, fit_input_temperature, input_nll, minimise_temperature

# progress(items, total, description) -> the same items, shown as they are consumed.
Progress = Callable[[Iterable, int, str], Iterable]

INITIAL_ELL = 0.5
TARGET_UPDATES = 300  # default epochs: enough passes for about this many optimiser steps
MIN_LR_FRACTION = 0.05  # the cosine schedule ends at this fraction of the initial rate
VALIDATION_BLOCK = 10
VALIDATION_EVERY = 4
VALIDATION_GAP = 2
VALIDATION_FRAMES = 20
VALIDATIONS = 10  # default: validate about this many times over a run (plus the start)
PLAN_CACHE_BYTES = 2 << 30  # built samples kept in memory for later epochs
FREE_ELL_START_VOXELS = 1.25  # learning free_ell starts at least this many voxels long
TEMPERATURE_MIOU_LOSS = 0.01  # the validation mIoU a fitted temperature may cost (fit_temperature)
BOUNDARY_STEPS = 5  # bisections of the allowed temperatures' boundary
FREE_WEIGHT = 1.0  # the free points' mean NLL against the labelled points' (sample_loss)
MIN_CLASS_POINTS = 25_000  # a class with fewer training ground-truth points keeps its start lengths


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


def kept_classes(counts: np.ndarray, min_points: int, ignore: Sequence[int]) -> np.ndarray:
    """The classes whose lengths stay at the start: fewer than ``min_points`` ground-truth points
    in the training frames (module docstring), the ignored classes excepted (they carry no evidence)."""
    kept = counts < min_points
    kept[list(ignore)] = False
    return np.flatnonzero(kept)


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


def split_validation(positions: Sequence[Sequence[int]], block: int = VALIDATION_BLOCK,
                     every: int = VALIDATION_EVERY, gap: int = VALIDATION_GAP,
                     max_frames: int = VALIDATION_FRAMES) -> tuple[list[list[int]], list[list[int]]]:
    """(training positions, validation positions) per sequence, disjoint (module docstring).

    Each sequence's frames are cut into blocks of ``block`` consecutive frames; blocks
    every-1, 2 every-1, ... (or the last block, when there are fewer than ``every`` blocks
    and more than one) hold out (a sequence shorter than two blocks is cut into blocks of
    len / ``every`` frames, with a gap of at most half of one), at most ``max_frames`` frames over all sequences (picked
    evenly; the blocks not picked train). Training drops the frames within ``gap`` of a
    validation frame.
    """
    per_sequence = max(1, max_frames // max(1, len(positions)))
    training, validation = [], []
    for chosen in positions:
        chosen = sorted(int(p) for p in chosen)
        size, near_gap = block, gap
        if len(chosen) < 2 * block:  # a short drive: shorter blocks, and a gap of at most half a block
            size = max(1, len(chosen) // every)
            near_gap = min(gap, size // 2)
        blocks = [chosen[i:i + size] for i in range(0, len(chosen), size)]
        candidates = [b for b in range(len(blocks)) if b % every == every - 1]
        if not candidates and len(blocks) > 1:
            candidates = [len(blocks) - 1]
        wanted = max(1, per_sequence // size) if candidates else 0
        if len(candidates) > wanted:
            picks = np.unique(np.round(np.linspace(0, len(candidates) - 1, wanted)).astype(int))
            candidates = [candidates[i] for i in picks]
        held = sorted(p for b in candidates for p in blocks[b])[:per_sequence]
        held_array = np.asarray(held, np.int64)
        if held:
            near = np.abs(np.asarray(chosen)[:, None] - held_array[None, :]).min(axis=1) <= near_gap
            training.append([p for p, close in zip(chosen, near) if not close])
        else:
            training.append(chosen)
        validation.append(held)
    return training, validation


class Validator:
    """The paper's protocol (``tools.evaluate``) on the validation frames, for a candidate kernel."""

    def __init__(self, datasets: Sequence[SemanticKittiSequence], positions: Sequence[Sequence[int]],
                 mapper_config: MapperConfig | None = None):
        """``mapper_config``: how the validation maps are made (default: the product's free space
        and clamping on the CPU, without the movers' rules, which a kernel's lengths do not
        meet); the datasets' label map decides the ignored classes."""
        self.datasets = list(datasets)
        self.positions = [list(chosen) for chosen in positions]
        label_map = self.datasets[0].label_map if self.datasets else None
        config = mapper_config or DEFAULTS.replace(device="cpu", forget_movers=False)
        self.mapper_config = config.replace(ignore_classes=label_map.ignore_classes) if label_map else config
        self.free_space = self.mapper_config.free_space.enabled
        self._frames: dict[tuple[int, int], Frame] = {}
        if not any(self.positions):
            raise DatasetError("no validation frames")

    @property
    def frame_count(self) -> int:
        return sum(len(chosen) for chosen in self.positions)

    def _frame(self, number: int, position: int) -> Frame:
        key = (number, position)
        if key not in self._frames:
            self._frames[key] = self.datasets[number][position]
        return self._frames[key]

    def score(self, config: KernelConfig) -> float:
        """mIoU of the map's point labels over the validation frames (one fresh map per sequence)."""
        return self.measure(config, calibration=False)[0]

    def measure(self, config: KernelConfig, calibration: bool = True) -> tuple[float, MapCalibration | None]:
        """The protocol on the validation frames: (mIoU, and with ``calibration`` the map's
        uncertainty at the scored points, as ``evaluate`` measures it)."""
        label_map = self.datasets[0].label_map
        scores = ConfusionMatrix(label_map.num_classes, label_map.ignore_classes)
        measured = (MapCalibration(label_map.num_classes, label_map.ignore_classes, self.free_space)
                    if calibration else None)
        for number, chosen in enumerate(self.positions):
            if not chosen:
                continue
            mapper = ConvBKIMapper(self.mapper_config, config)
            for position in chosen:
                frame = self._frame(number, position)
                if frame.ground_truth is None:
                    raise DatasetError(f"{self.datasets[number].folder}: no labels/ folder: validation needs them")
                input_labels = (frame.input_labels if frame.input_labels is not None
                                else frame.probabilities.argmax(axis=1))
                mapper.integrate(frame.points, frame.input_values, frame.pose)
                scores.add(frame.ground_truth, map_frame_labels(mapper, frame.points, frame.pose, input_labels))
                if measured is not None:
                    measured.add(mapper, transform_points(frame.points, frame.pose), frame.ground_truth)
        return float(scores.miou()), measured

    def input_points(self, max_points: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The validation frames' scored points with input probabilities: (probabilities (n, C)
        float32, ground truth (n,)), an even random sample of at most ``max_points``."""
        ignore = np.asarray(self.datasets[0].label_map.ignore_classes, np.int64)
        rows, truths = [], []
        for number, chosen in enumerate(self.positions):
            for position in chosen:
                frame = self._frame(number, position)
                if frame.probabilities is None or frame.ground_truth is None:
                    continue
                scored = ~np.isin(frame.ground_truth, ignore)
                rows.append(frame.probabilities[scored])
                truths.append(frame.ground_truth[scored])
        if not rows:
            return np.zeros((0, 0), np.float32), np.zeros(0, np.int64)
        probabilities, truth = np.concatenate(rows), np.concatenate(truths)
        if len(truth) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(truth), max_points, replace=False))
            probabilities, truth = probabilities[keep], truth[keep]
        return probabilities, truth


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

"""Held-out validation: which frames validate, and their score under the paper's protocol.

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
  has no evidence), mIoU over the classes present. The trainer scores the start kernel, then
  every ``validate_every`` steps and after the last step.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from convbki_core.config import DEFAULTS, MapperConfig
from convbki_core.datasets import DatasetError, Frame
from convbki_core.datasets.semantic_kitti import SemanticKittiSequence
from convbki_core.geometry.grid import transform_points
from convbki_core.inference.kernels import KernelConfig
from convbki_core.mapper import ConvBKIMapper
from convbki_core.measures.metrics import ConfusionMatrix
from convbki_core.measures.uncertainty import MapCalibration
from convbki_core.offline import map_frame_labels

VALIDATION_BLOCK = 10
VALIDATION_EVERY = 4
VALIDATION_GAP = 2
VALIDATION_FRAMES = 20


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

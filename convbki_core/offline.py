"""Mapping recorded frames offline, as ``evaluate``, ``train``'s validation, ``bench`` and
``soak`` do: a mapper with the paper's set-up, a sequence read frame by frame into it, and
the protocol's per-point labels. Nothing here writes to a terminal.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from convbki_core.config import MapperConfig
from convbki_core.datasets import Frame, SequenceDataset
from convbki_core.geometry.grid import transform_points
from convbki_core.io.kernel_file import KernelConfig
from convbki_core.mapper import ConvBKIMapper, IntegrationResult


def paper_mapper(kernel: str | Path | KernelConfig | None = None, **options) -> ConvBKIMapper:
    """A mapper with the paper's set-up (``MapperConfig.paper``) on the CPU unless ``device``
    says otherwise, and its kernel unless ``kernel`` names another; ``options`` change settings
    by their flat names. With ``free_space=True`` and the paper's kernel, the movers' rules and
    the ground classes of the label map apply, as in the product."""
    options = {"device": "cpu", **options}
    if kernel is None and options.get("free_space"):
        for classes in ("movable_classes", "ground_classes"):
            options.setdefault(classes, None)  # the label map's
    return ConvBKIMapper(MapperConfig.paper(**options), kernel)


def read_frames(dataset: SequenceDataset, positions: Iterable[int]) -> Iterator[Frame]:
    """The frames at ``positions`` of a sequence, read one at a time (a drive never sits in memory)."""
    for position in positions:
        yield dataset[position]


def drive_frames(dataset: SequenceDataset,
                 positions: Iterable[int]) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points, input labels or probabilities, pose) of the frames at ``positions``: what
    ``ConvBKIMapper.integrate`` takes."""
    for frame in read_frames(dataset, positions):
        yield frame.points, frame.input_values, frame.pose


def integrate_frames(mapper: ConvBKIMapper, frames: Iterable[Frame]) -> Iterator[tuple[Frame, IntegrationResult]]:
    """Integrate each frame's input (labels or probabilities) at its pose; yield it with the result."""
    for frame in frames:
        yield frame, mapper.integrate(frame.points, frame.input_values, frame.pose)


def update_ms(result: IntegrationResult) -> float:
    """The update's time for one scan as the benchmarks count it: voxelise + ConvBKI update
    (+ free space when the mapper has it on)."""
    return result.timing_ms["voxelize"] + result.timing_ms["update"] + result.timing_ms["free"]


def query_ms(result: IntegrationResult) -> float:
    """The window move's time for one scan (write-back of the slabs that leave, fetch of those that enter)."""
    return result.timing_ms["query"]


def map_frame_labels(mapper: ConvBKIMapper, points: np.ndarray, pose: np.ndarray,
                     input_labels: np.ndarray) -> np.ndarray:
    """The protocol's per-point labels after the frame was integrated: map label, else input
    label (``evaluate`` scores these; ``train`` validates with them)."""
    map_labels, has_evidence = mapper.labels_at(transform_points(points, pose))
    return np.where(has_evidence, map_labels, input_labels)

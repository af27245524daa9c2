"""Dataset loaders: one module per dataset, one interface (``SequenceDataset``).

A loader turns a recorded sequence into ``Frame`` objects in the order they were taken:
points in the sensor frame, the input segmentation as learning-class ids (or class
probabilities), the ground truth when there is one, and the sensor's pose in the map frame.
Everything downstream (``evaluate``, ``train``, ``kitti_to_bag``, ``bench``) sees only this.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from convbki_core.io.labels import LabelMap


class DatasetError(Exception):
    """A dataset that cannot be read as asked; the message names the file and the problem."""


@dataclass
class Frame:
    """One LiDAR scan of a sequence."""

    index: int  # position in the sequence (the file number)
    name: str  # file stem, e.g. "000042"
    points: np.ndarray  # (N, 3) float32, sensor frame, m
    remission: np.ndarray  # (N,) float32
    pose: np.ndarray  # (4, 4) float64, map <- sensor
    stamp: float  # seconds
    input_labels: np.ndarray | None = None  # (N,) int64 learning ids of the input segmentation
    probabilities: np.ndarray | None = None  # (N, C) float32 input class probabilities
    ground_truth: np.ndarray | None = None  # (N,) int64 learning ids
    raw_input_labels: np.ndarray | None = None  # (N,) uint32 label words as stored
    moving: np.ndarray | None = None  # (N,) bool: the ground truth marks the point as a moving object
    moving_raw_ids: np.ndarray | None = None  # (65536,) bool: the label map's moving raw ids (None: none)

    @property
    def input_moving(self) -> np.ndarray | None:
        """(N,) bool: the input segmentation marks the point as a moving object (a moving raw
        id, e.g. SemanticKITTI's 252-259); None when the input is not raw labels or marks none."""
        if self.raw_input_labels is None or self.moving_raw_ids is None:
            return None
        moving = self.moving_raw_ids[self.raw_input_labels.astype(np.int64) & 0xFFFF]
        return moving if moving.any() else None

    @property
    def input_values(self) -> np.ndarray:
        """What the mapper integrates: probabilities when present, else labels."""
        if self.probabilities is not None:
            return self.probabilities
        if self.input_labels is None:
            raise DatasetError(f"frame {self.name} has no input segmentation")
        return self.input_labels


class SequenceDataset(Protocol):
    """The loader interface every dataset follows."""

    label_map: LabelMap
    sequence: str

    def __len__(self) -> int: ...

    def __getitem__(self, position: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...


def parse_frames(spec: str | None, count: int) -> range:
    """``A:B`` (Python slice semantics, either side optional) -> positions in a sequence of ``count``."""
    if spec in (None, "", ":"):
        return range(count)
    parts = spec.split(":")
    if len(parts) != 2:
        raise ValueError(f"--frames must look like A:B, got {spec!r}")
    try:
        start = int(parts[0]) if parts[0] else None
        stop = int(parts[1]) if parts[1] else None
    except ValueError:
        raise ValueError(f"--frames must look like A:B with integers, got {spec!r}") from None
    selected = range(count)[slice(start, stop)]
    if len(selected) == 0:
        raise ValueError(f"--frames {spec} selects no frame of a sequence of {count}")
    return selected

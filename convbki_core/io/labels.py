"""Dataset label maps: raw ids <-> learning classes, class names and colours.

Label maps live as YAML in the package's config folder (``config/<name>.yaml``), so a new
dataset is a new file, not new code.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import yaml

from convbki_core.paths import config_dir


@dataclass(frozen=True)
class LabelMap:
    """Learning-class facts of one dataset. Arrays are indexed by id."""

    name: str
    learning_map: np.ndarray  # (65536,) uint16: raw semantic id -> learning class (0 for unknown)
    learning_map_inv: np.ndarray  # (C,) uint32: learning class -> raw id written back
    class_names: tuple[str, ...]
    colors: np.ndarray  # (C, 3) uint8 RGB
    ignore_classes: tuple[int, ...]
    known_raw: np.ndarray  # (65536,) bool: raw ids listed in the learning map
    moving_raw: np.ndarray | None = None  # (65536,) bool: raw ids of moving objects (None: not marked)
    ground_classes: tuple[int, ...] = ()  # learning classes of the ground (road, sidewalk, ...)

    @property
    def movable_classes(self) -> tuple[int, ...]:
        """Learning classes that moving objects map to (car, person, ...); empty when the label
        map marks no moving ids."""
        if self.moving_raw is None:
            return ()
        return tuple(sorted({int(c) for c in self.learning_map[np.flatnonzero(self.moving_raw)]} - {0}))

    def is_moving(self, raw_labels: np.ndarray) -> np.ndarray:
        """(N,) bool: label words of moving objects (all False when none are marked)."""
        if self.moving_raw is None:
            return np.zeros(np.shape(raw_labels), bool)
        return self.moving_raw[np.asarray(raw_labels).astype(np.int64) & 0xFFFF]

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def to_learning(self, raw_labels: np.ndarray) -> np.ndarray:
        """Raw label words (uint32, instance in the high 16 bits) -> learning ids (int64)."""
        raw = np.asarray(raw_labels)
        if raw.dtype.kind not in "iu":
            raise TypeError(f"labels must be integers, got {raw.dtype}")
        semantic = raw.astype(np.int64) & 0xFFFF
        return self.learning_map[semantic].astype(np.int64)

    def unknown_raw(self, raw_labels: np.ndarray) -> np.ndarray:
        """(N,) bool: label words whose semantic id is not in the learning map."""
        return ~self.known_raw[np.asarray(raw_labels).astype(np.int64) & 0xFFFF]

    def to_raw(self, learning_labels: np.ndarray) -> np.ndarray:
        """Learning ids -> raw ids (uint32) as written in submission files."""
        return self.learning_map_inv[np.asarray(learning_labels, dtype=np.int64)]


def load_label_map_file(path: str | Path) -> LabelMap:
    """Read a label-map YAML (see config/semantic_kitti.yaml for the layout)."""
    path = Path(path)
    data = yaml.safe_load(path.read_text())
    classes = data["classes"]
    num_classes = len(classes)
    if sorted(int(k) for k in classes) != list(range(num_classes)):
        raise ValueError(f"{path}: classes must be numbered 0..{num_classes - 1}")
    names, inverse, colors = [], np.zeros(num_classes, np.uint32), np.zeros((num_classes, 3), np.uint8)
    for class_id in range(num_classes):
        name, raw_id, rgb = classes[class_id]
        names.append(str(name))
        inverse[class_id] = int(raw_id)
        colors[class_id] = rgb
    forward = np.zeros(0x10000, np.uint16)
    known = np.zeros(0x10000, bool)
    for raw_id, class_id in data["learning_map"].items():
        if not 0 <= int(class_id) < num_classes:
            raise ValueError(f"{path}: learning_map sends {raw_id} to unknown class {class_id}")
        forward[int(raw_id)] = int(class_id)
        known[int(raw_id)] = True
    moving = None
    if data.get("moving_raw_ids"):
        moving = np.zeros(0x10000, bool)
        moving[[int(raw_id) for raw_id in data["moving_raw_ids"]]] = True
    ground = tuple(int(c) for c in data.get("ground_classes", []))
    if any(not 0 < c < num_classes for c in ground):
        raise ValueError(f"{path}: ground_classes must be learning classes 1..{num_classes - 1}, got {list(ground)}")
    return LabelMap(str(data.get("name", path.stem)), forward, inverse, tuple(names), colors,
                    tuple(int(c) for c in data.get("ignore_classes", [0])), known, moving, ground)


@cache
def load_label_map(name: str = "semantic_kitti") -> LabelMap:
    """The label map shipped as ``config/<name>.yaml``."""
    return load_label_map_file(config_dir() / f"{name}.yaml")

"""The bag tests' data (test/ros/test_bags_*.py): the 4-frame sequence 08 that their ``dataset``
fixture (test/ros/conftest.py) writes, its stamps and cloud sizes, and kitti_to_bag called as a
function."""

from pathlib import Path

import numpy as np
from kitti_fixture import pose_about_z, write_sequence

from convbki_ros.tools import kitti_to_bag

EPOCH_NS = 1_700_000_000_000_000_000
TIMES = [0.0, 0.1037, 0.2071, 0.3109]
FRAME_SIZES = [300, 301, 280, 333]


def convert(*argv: str) -> int:
    return kitti_to_bag.main([str(a) for a in argv])


def write_dataset(root: Path) -> tuple[Path, list, list]:
    """A 4-frame sequence 08 under ``root``: first pose not identity, raw ids with instance bits,
    probabilities. (root, frames (points, truth, predicted), probabilities)."""
    rng = np.random.default_rng(8)
    frames, poses, probabilities = [], [], []
    for number, size in enumerate(FRAME_SIZES):
        points = rng.normal(scale=8.0, size=(size, 3)).astype(np.float32)
        truth = rng.choice([10, 40, 50, 70], size).astype(np.uint32)
        predicted = rng.choice([10, 40, 48, 50, 252], size).astype(np.uint32) | (rng.integers(0, 9, size) << 16).astype(
            np.uint32)
        frames.append((points, truth, predicted))
        poses.append(pose_about_z(0.3 + 0.05 * number, [5.0 + number, -2.0 + 0.5 * number, 0.25]))
        p = rng.random((size, 20))
        probabilities.append(p / p.sum(axis=1, keepdims=True))
    write_sequence(root, "08", frames, poses, times=TIMES, probabilities=probabilities)
    return root, frames, probabilities

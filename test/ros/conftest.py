"""Fixtures of the ROS-side tests."""

from pathlib import Path

import numpy as np
import pytest
from bag_fixture import FRAME_SIZES, TIMES
from kitti_fixture import pose_about_z, write_drive, write_sequence
from ros_helpers import require_current_install


@pytest.fixture(scope="module")
def current_install():
    """For the tests that run the installed package (install/): one line, and a failure, when it
    is older than the tree (run `make setup`), rather than an old node compared with new code."""
    require_current_install()


@pytest.fixture(scope="package")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    """A 4-frame sequence 08: first pose not identity, raw ids with instance bits, probabilities."""
    root = tmp_path_factory.mktemp("kitti")
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


@pytest.fixture(scope="package")
def clean_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-frame sequence 00 with ground truth, predictions and probabilities, which the CLI error
    tests (test_cli_errors*.py) damage copies of."""
    root = tmp_path_factory.mktemp("clean") / "data"
    write_drive(root, "00", frames=3)
    folder = root / "sequences" / "00"
    (folder / "probabilities").mkdir()
    for scan in sorted((folder / "velodyne").iterdir()):
        count = scan.stat().st_size // 16
        np.save(folder / "probabilities" / f"{scan.stem}.npy", np.full((count, 20), 0.05, np.float16))
    return root

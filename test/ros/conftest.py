"""Fixtures of the ROS-side tests."""

from pathlib import Path

import numpy as np
import pytest
from bag_fixture import write_dataset
from kitti_fixture import write_drive
from ros_helpers import require_current_install


@pytest.fixture(scope="module")
def current_install():
    """For the tests that run the installed package (install/): one line, and a failure, when it
    is older than the tree (run `make setup`), rather than an old node compared with new code."""
    require_current_install()


@pytest.fixture(scope="package")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    """A 4-frame sequence 08: first pose not identity, raw ids with instance bits, probabilities
    (``bag_fixture.write_dataset``)."""
    return write_dataset(tmp_path_factory.mktemp("kitti"))


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

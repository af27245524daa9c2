"""play_bag on what is not a bag, or on a bag whose index is damaged: one line naming the path and
the problem, exit code 2, no traceback, and nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_line_error, tree

from convbki_ros.tools import kitti_to_bag, play_bag


def _bag_from(root: Path, folder: Path) -> Path:
    bag = folder / "bag"
    assert kitti_to_bag.main(["--dataset", str(root), "--sequence", "0", "--out", str(bag), "--frames", "0:2"]) == 0
    return bag


@pytest.fixture(scope="module")
def good_bag(clean_root, tmp_path_factory) -> Path:
    return _bag_from(clean_root, tmp_path_factory.mktemp("bag"))


def _not_bags(folder: Path, good: Path) -> dict[str, tuple[Path, str]]:
    """Things given to play_bag as a bag, and what its one line must say."""
    cases = {}
    (folder / "empty").mkdir()
    cases["empty folder"] = (folder / "empty", "no such bag")
    (folder / "text.mcap").write_text("hello")
    cases["text as mcap"] = (folder / "text.mcap", "cannot read the bag")
    (folder / "text.db3").write_text("hello")
    cases["text as sqlite"] = (folder / "text.db3", "cannot read the bag")
    (folder / "notes.txt").write_text("hello")
    cases["other file"] = (folder / "notes.txt", "cannot read the bag")
    (folder / "yaml").mkdir()
    (folder / "yaml" / "metadata.yaml").write_text("rosbag2_bagfile_information: [1\n")
    cases["broken metadata"] = (folder / "yaml", "cannot read the bag")
    no_storage = folder / "no_storage"
    shutil.copytree(good, no_storage)
    (no_storage / "bag.mcap").unlink()
    cases["storage file missing"] = (no_storage, "cannot read the bag")
    truncated = folder / "truncated"
    shutil.copytree(good, truncated)
    blob = (truncated / "bag.mcap").read_bytes()
    (truncated / "bag.mcap").write_bytes(blob[: len(blob) // 2])
    cases["truncated mcap"] = (truncated, "cannot read the bag")
    return cases


def test_play_bag_refuses_what_is_not_a_bag(good_bag, tmp_path, capsys):
    for name, (path, message) in _not_bags(tmp_path, good_bag).items():
        before = tree(tmp_path)
        code = play_bag.main([str(path), "--wait-subscribers", "0"])
        line = one_line_error(capsys, code, "play_bag", str(path), message)
        assert tree(tmp_path) == before, name  # reading a bag writes nothing
        assert len(line) < 400, line


def test_play_bag_damaged_index_never_gives_a_traceback(good_bag, tmp_path, capsys):
    """Bytes overwritten in the mcap's summary (its index): exit 2 with one line, or a clean replay.

    rosbags trips over such damage with UnicodeDecodeError, OverflowError or MemoryError, at
    open or while reading; play_bag must turn each into its one-line error.
    """
    blob = (good_bag / "bag.mcap").read_bytes()
    rng = np.random.default_rng(3)
    refused = 0
    for trial in range(24):
        damaged = tmp_path / f"d{trial}"
        shutil.copytree(good_bag, damaged)
        data = bytearray(blob)
        at = int(rng.integers(len(data) - 1500, len(data) - 8))
        data[at:at + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
        (damaged / "bag.mcap").write_bytes(bytes(data))
        code = play_bag.main([str(damaged), "--wait-subscribers", "0", "--rate", "1000"])
        err = capsys.readouterr().err
        assert "Traceback" not in err and code in (0, 2), err
        if code == 2:
            last = err.strip().splitlines()[-1]
            assert last.startswith(f"play_bag: error: {damaged}: ") and "bag" in last, last
            refused += 1
        shutil.rmtree(damaged)
    assert refused >= 3, refused  # the damage was real: some bags were refused

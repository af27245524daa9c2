"""Every CLI on bad arguments and bad output targets: a bad flag value, a --device this machine
lacks (refused while the arguments are parsed, before any work), an output root that is a file, a
dataset bench did not write, a dataset demo cannot find: one line, exit code 2, no traceback, and
nothing made or overwritten."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from cli_helpers import one_line_error, tree

from convbki_core.tools import bench, evaluate, train
from convbki_core.tools import synth as synthetic
from convbki_ros.tools import demo, kitti_to_bag, play_bag


def test_synth_refuses_a_file_as_root_and_leaves_it(tmp_path, capsys):
    target = tmp_path / "a_file"
    target.write_text("mine")
    code = synthetic.main(["--out", str(target), "--frames", "1", "--azimuth-steps", "64", "--quiet"])
    one_line_error(capsys, code, "synth", "a_file", "not a folder")
    code = synthetic.main(["--out", str(target / "inner"), "--frames", "1", "--azimuth-steps", "64", "--quiet"])
    one_line_error(capsys, code, "synth", "a_file", "not a folder")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_synth_write_failure_is_one_line_exit_2_without_temp_files(tmp_path, capsys):
    """A scan path taken by a folder makes the write fail part-way (after scan 0 was written)."""
    seq_folder = tmp_path / "sequences" / "00"
    (seq_folder / "velodyne" / "000001.bin").mkdir(parents=True)
    code = synthetic.main(["--out", str(tmp_path), "--frames", "2", "--azimuth-steps", "64", "--beams", "8",
                           "--noise-strength", "0.3", "--force", "--quiet"])
    one_line_error(capsys, code, "synth", "000001.bin", after_progress=True)
    assert not [p for p in tmp_path.rglob("*.tmp")]


def test_bench_drive_folder_that_is_a_file(tmp_path, capsys):
    target = tmp_path / "a_file"
    target.write_text("mine")
    code = bench.main(["--drive-dir", str(target), "--scans", "3", "--skip-ablation"])
    one_line_error(capsys, code, "bench", "a_file", "not a folder")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_demo_missing_dataset_creates_nothing(tmp_path, capsys):
    code = demo.main(["--dataset", str(tmp_path / "nowhere"), "--sequence", "0", "--out", str(tmp_path / "demo")])
    one_line_error(capsys, code, "demo", "nowhere", "dataset folder not found")
    assert sorted(tmp_path.iterdir()) == []


@pytest.mark.parametrize("module, argv", [
    (evaluate, ["--dataset", "d", "--sequence", "x", "--report", "r.json"]),
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml", "--epochs", "0"]),
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml", "--min-class-points", "-1"]),
    (kitti_to_bag, ["--dataset", "d", "--sequence", "0", "--out", "b", "--frames", "5:2"]),
    (play_bag, ["bag", "--rate", "-1"]),
    (demo, ["--frames", "0"]),
    (synthetic, ["--out", "x", "--frames", "-2"]),
    (evaluate, ["--no-such-flag"]),
])
def test_bad_arguments_are_one_line_exit_2(module, argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        module.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and ": error: " in lines[0] and "Traceback" not in err, err
    assert sorted(tmp_path.iterdir()) == []


def _missing_devices() -> list:
    """--device values this machine lacks, with what the one line must name."""
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    no_cuda = pytest.mark.skipif(count > 0, reason="this machine has a CUDA device, so --device cuda is valid here")
    return [pytest.param("cuda", ("'cuda' requested", "has no CUDA device", "use device auto or cpu"), marks=no_cuda),
            pytest.param(f"cuda:{count}", (f"'cuda:{count}' requested",)),
            pytest.param("tpu", ("unknown device 'tpu'", "use auto, cpu or cuda[:N]"))]


@pytest.mark.parametrize("device, needles", _missing_devices())
def test_evaluate_refuses_a_device_it_cannot_use_before_any_work(clean_root, tmp_path, capsys, device, needles):
    before = tree(tmp_path)
    with pytest.raises(SystemExit) as exit_info:  # refused while the arguments are parsed
        evaluate.main(["--dataset", str(clean_root), "--sequence", "0", "--report", str(tmp_path / "r.json"),
                       "--write-labels", str(tmp_path / "out"), "--quiet", "--device", device])
    one_line_error(capsys, exit_info.value.code, "evaluate", "argument --device:", *needles)
    assert tree(tmp_path) == before


@pytest.mark.parametrize("device, needles", _missing_devices())
@pytest.mark.parametrize("module, argv", [
    (train, ["--dataset", "d", "--sequences", "0", "--out", "k.yaml"]),
    (bench, []),
])
def test_train_and_bench_refuse_a_device_they_cannot_use_before_any_work(module, argv, device, needles, capsys,
                                                                          tmp_path, monkeypatch):
    """Both run on CUDA when asked (``--device cuda``); a device this machine lacks is one line, exit 2."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        module.main([*argv, "--device", device])
    one_line_error(capsys, exit_info.value.code, module.PROG, "argument --device:", *needles)
    assert sorted(tmp_path.iterdir()) == []


def test_bench_never_overwrites_a_dataset_it_did_not_write(tmp_path, capsys):
    """A folder of real scans without poses.txt (a velodyne-only download) is refused, not resimulated."""
    velodyne = tmp_path / "kitti" / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True)
    for number in range(3):
        (velodyne / f"{number:06d}.bin").write_bytes(np.zeros(16, np.float32).tobytes())
    before = tree(tmp_path / "kitti")
    code = bench.main(["--drive-dir", str(tmp_path / "kitti"), "--scans", "3", "--skip-ablation"])
    one_line_error(capsys, code, "bench", "not a synthetic drive")
    assert tree(tmp_path / "kitti") == before
